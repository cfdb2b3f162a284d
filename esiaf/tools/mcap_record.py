"""``esiaf record``: what a running pipeline carries, written to MCAP (docs/recording.md).

    esiaf record --out FILE.mcap [--url URL] [--token-file FILE] [--topics grabber/audio,...]
                 [--stream ID] [--max-mb MB] [--max-s S]

The recorder is an SDK consumer component (service ``recorder``): it subscribes to the audio topics
(each in the format its producer declared, so the audio is kept as it was sent) and writes every
chunk as an ``esiaf.AugmentedAudio``; it follows the orchestrator's websocket with partials for the
fused results (``esiaf.FusedResult``, every revision) and partials (``esiaf.Result`` of kind
``partial``), pages ``GET /results`` for every stored result (``esiaf.Result``), and notes each
component that registers, dies or leaves (``GET /components``, a ``google.protobuf.Struct``). Each
message's log time is its capture time (a chunk's start, a result's span start, a fused result's
window start, a partial's end); a component's event, the wall clock. On SIGTERM or Ctrl-C it
catches up on what the orchestrator fused meanwhile and finishes the file. ``esiaf run --record
FILE.mcap`` starts it beside the pipeline.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, ClassVar
from urllib.parse import urlencode

import httpx
from google.protobuf.struct_pb2 import Struct
from pydantic import Field
from websockets.exceptions import WebSocketException

from esiaf import auth
from esiaf.api_client import OrchestratorHTTP, declared_format, why
from esiaf.argparsing import OneLineParser
from esiaf.audio import Audio
from esiaf.component import Component
from esiaf.formats import AudioFormat
from esiaf.processor import SetupError
from esiaf.proto import esiaf_pb2 as pb
from esiaf.settings import ComponentSettings, SettingsError, load_settings
from esiaf.tools.mcap_convert import fused_from_json, partial_from_json, result_from_json
from esiaf.tools.mcap_writer import RotatingWriter, next_part
from esiaf.tools.terminal import err

log = logging.getLogger(__name__)

RESULTS_POLL_S = 1.0  # GET /results is asked this often for what was stored since
COMPONENTS_EVERY = 2  # ... and GET /components every this many polls, for components that came or changed status
COMPONENT_FIELDS = ("component_id", "name", "instance", "kind", "status", "host", "pid")
PAGE = 1000  # results and fused results per request (the API's largest page)
FUSED_TOPIC, PARTIAL_TOPIC, RESULTS_PREFIX, COMPONENTS_TOPIC = "fused", "partials", "results/", "components"


class RecorderSettings(ComponentSettings):
    out: str = ""  # the MCAP file; rotated files get a numbered suffix (session-2.mcap, ...)
    topics: list[str] = Field(default_factory=lambda: ["grabber/audio"])  # the audio topics recorded
    stream: str = ""  # only this stream's results and fused results ("" every stream's)
    max_mb: float = 0.0  # a new file once one reaches this size (0: no limit)
    max_s: float = 0.0  # ... or has been written this long (0: no limit)
    go_on: bool = False  # `out` may exist: write the next part not written yet (a recorder restarted by esiaf run)


class Recorder(Component):
    """Records audio topics, results, fused results and partials to an MCAP file."""

    service = "recorder"
    kind = "other"
    Settings = RecorderSettings
    settings: RecorderSettings
    options: ClassVar[dict[str, str]] = {}

    def __init__(self, settings: RecorderSettings) -> None:
        super().__init__(settings)
        self.started_ns = time.time_ns()
        self.writer: RotatingWriter | None = None
        self.written: set[tuple[int, int]] = set()  # (fused id, revision) written
        self._done = threading.Event()
        self._threads: list[threading.Thread] = []
        self._results_after = 0
        self.audio_s: dict[str, float] = {}  # seconds of audio recorded, per topic
        self.component_status: dict[str, str] = {}  # component id -> its status last recorded
        self._cpu_from: float | None = None  # this process's CPU time at the first chunk recorded

    def setup(self) -> None:
        s = self.settings
        for topic in s.topics:  # the producer's own format: the audio is recorded as it was sent
            declared = declared_format(s.orchestrator_url, topic, s.register_timeout_s, lambda: self.stopping)
            if declared is None:
                raise SetupError(f"no producer of {topic!r} registered with {s.orchestrator_url} within "
                                 f"{s.register_timeout_s:g} s (--topics)")
            self.add_input(topic, AudioFormat.from_dict(declared))
        self.writer = RotatingWriter(Path(s.out), max_bytes=int(s.max_mb * 1024 * 1024), max_s=s.max_s,
                                     metadata={"orchestrator": s.orchestrator_url, "topics": ",".join(s.topics),
                                               "started_ns": str(self.started_ns)},
                                     first_part=next_part(Path(s.out)) if s.go_on else 1)
        if self.writer.failed:
            raise SetupError(f"--out: {self.writer.failed}")
        from esiaf.tools.feed import FusedFeed
        query = {"partials": 1} | ({"stream": s.stream} if s.stream else {})
        ws_url = s.orchestrator_url.replace("http", "ws", 1) + "/ws/fused?" + urlencode(query)
        try:
            feed = FusedFeed(ws_url)
        except (OSError, TimeoutError, WebSocketException) as exc:  # refused, or the token refused
            raise SetupError(f"cannot follow {ws_url}: {exc}") from None
        self._threads = [threading.Thread(target=self._follow, args=(feed,), name="recorder-fused", daemon=True),
                         threading.Thread(target=self._poll_results, name="recorder-results", daemon=True)]
        for thread in self._threads:
            thread.start()

    def refresh_info(self) -> None:
        if self.writer is not None:
            self.info.update(messages=self.writer.messages, files=[str(p) for p in self.writer.paths],
                             failed=self.writer.failed)

    # -- audio ---------------------------------------------------------------------------
    def on_audio(self, audio: Audio) -> None:
        assert self.writer is not None
        if self._cpu_from is None:
            self._cpu_from = time.process_time()
        self.audio_s[audio.topic] = self.audio_s.get(audio.topic, 0.0) + (audio.end_ns - audio.start_ns) / 1e9
        message = pb.AugmentedAudio(stream_id=audio.stream_id, topic=audio.topic, publisher=audio.publisher,
                                    sequence=audio.sequence, start_ns=audio.start_ns, end_ns=audio.end_ns,
                                    format=audio.format.to_proto(), payload=audio.payload)
        message.meta.CopyFrom(audio.meta)
        self.writer.write(audio.topic, message, audio.start_ns)

    def on_end_of_stream(self, stream_id: str, audio: Audio) -> None:
        """A consumer with no outputs: nothing to pass on."""

    # -- the orchestrator's side -----------------------------------------------------------
    def _write_fused(self, value: dict[str, Any]) -> None:
        assert self.writer is not None
        key = (int(value.get("id") or 0), int(value.get("revision") or 0))
        if key in self.written:
            return
        self.written.add(key)
        fused = fused_from_json(value)
        self.writer.write(FUSED_TOPIC, fused, fused.anchor.span.start_ns)

    def _follow(self, feed: Any) -> None:
        assert self.writer is not None
        with feed:
            while not self._done.is_set():
                try:
                    text = feed.recv(timeout=0.5)
                except TimeoutError:
                    continue
                try:
                    event = json.loads(text)
                except ValueError:
                    continue
                if event.get("type") == "fused_result":
                    self._write_fused(event)
                elif event.get("type") == "partial":
                    partial = partial_from_json(event)
                    self.writer.write(PARTIAL_TOPIC, partial, partial.span.end_ns)

    def _pages(self, http: OrchestratorHTTP, path: str, after_id: int) -> Iterator[tuple[list[dict], int]]:
        """Every page of ``path`` (``GET /results`` or ``/fused``) after ``after_id``, overlapping the recording."""
        query = {"start_ns": self.started_ns - 60 * 10**9, "limit": PAGE} | (
            {"stream": self.settings.stream} if self.settings.stream else {})
        while True:
            page = http.get(path, params=query | {"after_id": after_id}).raise_for_status().json()
            yield page["items"], after_id
            if len(page["items"]) < PAGE or page.get("next_after_id") is None:
                return
            after_id = page["next_after_id"]

    def _results_once(self, http: OrchestratorHTTP) -> None:
        assert self.writer is not None
        for items, _ in self._pages(http, "/results", self._results_after):
            for item in items:
                result = result_from_json(item)
                self.writer.write(RESULTS_PREFIX + (item.get("type") or "unknown"), result, result.span.start_ns)
                self._results_after = max(self._results_after, int(item.get("id") or 0))

    def _components_once(self, http: OrchestratorHTTP) -> None:
        """A component that registered, died or left since the last look: its event, as a Struct (wall clock)."""
        listed = {str(component.get("component_id")): component
                  for component in http.get("/components").raise_for_status().json()["items"]}
        for key in set(self.component_status) - set(listed):  # left: no longer listed
            if self.component_status[key] != "gone":
                listed[key] = {"component_id": key, "status": "gone"}
        for key, component in listed.items():
            status = str(component.get("status"))
            if self.component_status.get(key) == status:
                continue
            fields = {name: component[name] for name in COMPONENT_FIELDS if component.get(name) is not None}
            self._write_event({"event": "seen" if key not in self.component_status else "status", **fields})
            self.component_status[key] = status

    def _write_event(self, fields: dict[str, Any]) -> None:
        assert self.writer is not None
        event = Struct()
        event.update(fields)
        self.writer.write(COMPONENTS_TOPIC, event, time.time_ns())

    def _poll_results(self) -> None:
        polls = 0
        with OrchestratorHTTP(self.settings.orchestrator_url) as http:
            while True:
                try:
                    if polls % COMPONENTS_EVERY == 0:
                        self._components_once(http)
                    self._results_once(http)
                except (httpx.HTTPError, ValueError, KeyError) as exc:
                    log.info("results not read: %s", exc)
                polls += 1
                if self._done.wait(RESULTS_POLL_S):
                    return

    def teardown(self) -> None:
        """Catches up on the results and fused results stored meanwhile, then finishes the file."""
        self._done.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        if self.writer is None:
            return
        try:
            with OrchestratorHTTP(self.settings.orchestrator_url) as http:
                self._components_once(http)
                self._results_once(http)
                for items, _ in self._pages(http, "/fused", 0):
                    for item in items:
                        self._write_fused(item)
        except (httpx.HTTPError, ValueError, KeyError) as exc:
            err(f"esiaf: recording: could not catch up with the orchestrator: {exc}")
        self.writer.close()
        if not self.writer.failed:
            files = ", ".join(str(path) for path in self.writer.paths)
            audio_s = max(self.audio_s.values(), default=0.0)
            cpu_s = time.process_time() - self._cpu_from if self._cpu_from is not None else 0.0
            err(f"esiaf: recorded {self.writer.messages} messages ({audio_s:.1f} s of audio, {cpu_s:.2f} CPU-s "
                f"from its first chunk) to {files}")


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = OneLineParser(prog="esiaf record", description="record a running pipeline to an MCAP file")
    parser.add_argument("--out", type=Path, required=True, help="the MCAP file (rotated: FILE-2.mcap, ...)")
    parser.add_argument("--url", default=os.environ.get("ESIAF_ORCHESTRATOR_URL", "http://127.0.0.1:8000"),
                        help="the orchestrator (default $ESIAF_ORCHESTRATOR_URL or http://127.0.0.1:8000)")
    parser.add_argument("--token-file", help="the token (default: ESIAF_TOKEN, or the file ESIAF_TOKEN_FILE names)")
    parser.add_argument("--topics", default="grabber/audio", help="audio topics to record, separated by commas "
                        "(default grabber/audio)")
    parser.add_argument("--stream", default="", help="record only this stream's results (default: every stream's)")
    parser.add_argument("--max-mb", type=float, default=0.0, help="a new file once one is this large (MB)")
    parser.add_argument("--max-s", type=float, default=0.0, help="a new file once one has been written this long")
    parser.add_argument("--go-on", action="store_true", help=argparse.SUPPRESS)  # esiaf run's: after a restart
    parser.add_argument("-v", "--verbose", action="store_true", help="log what the recorder does")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    if args.token_file:
        os.environ[auth.TOKEN_FILE_ENV] = args.token_file
        os.environ.pop(auth.TOKEN_ENV, None)
    topics = [topic.strip() for topic in args.topics.split(",") if topic.strip()]
    if args.max_mb < 0 or args.max_s < 0:
        err("esiaf record: --max-mb and --max-s take a positive limit (0: none)")
        return 2
    if args.out.is_dir() or not args.out.absolute().parent.is_dir():
        err(f"esiaf record: --out {args.out} is a folder, or its folder does not exist: give a file")
        return 2
    if args.out.exists() and not args.go_on and args.out.is_file():
        err(f"esiaf record: --out {args.out} exists: give another name, or remove it")
        return 2
    try:
        auth.token()
        settings = load_settings(RecorderSettings, "recorder", orchestrator_url=args.url.rstrip("/"),
                                 out=str(args.out), topics=topics, stream=args.stream, max_mb=args.max_mb,
                                 max_s=args.max_s, go_on=args.go_on,
                                 log_level="INFO" if args.verbose else "WARNING")
    except (SettingsError, auth.TokenError) as exc:
        err(f"esiaf record: {exc}")
        return 2
    try:  # reachable, and the token taken: said now, not after waiting for a producer
        with OrchestratorHTTP(settings.orchestrator_url) as http:
            response = http.get("/topics")
    except httpx.HTTPError as exc:
        err(f"esiaf record: cannot reach the orchestrator at {settings.orchestrator_url} (--url): {exc}")
        return 2
    if response.status_code != 200:
        err(f"esiaf record: the orchestrator at {settings.orchestrator_url} answered GET /topics with "
            f"{response.status_code}: {why(response)} (the token: ESIAF_TOKEN, ESIAF_TOKEN_FILE or --token-file)")
        return 2
    logging.basicConfig(level=settings.log_level, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    from esiaf.control import RegistrationError
    try:
        return Recorder(settings).run()
    except (SetupError, RegistrationError) as exc:
        err(f"esiaf record: {exc}")
        return 2
    except KeyboardInterrupt:
        return 0


if __name__ == "__main__":
    raise SystemExit(main())
