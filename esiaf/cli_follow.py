"""``esiaf run`` once the pipeline is up: each fused result printed as one line (or as JSON) as it
arrives, progress and the orchestrator's health on stderr, until the stream has ended."""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from typing import Any

import httpx
from websockets.exceptions import ConnectionClosed

from esiaf.launcher import START_TIMEOUT_S, LaunchError, OrchestratorClient, Supervisor, wait_until

LABELS = ("emotion", "gender", "voice_id")  # label aggregates shown on a line, in this order
DRAIN_TIMEOUT_S = 30.0  # after the grabber has finished: wait this long for the next result at most
PROGRESS_EVERY_S = 10.0  # how often to say how much of a long file has been played
LONG_FILE_S = 60.0


def format_line(fused: dict[str, Any], origin_ns: int) -> str:
    """'[12.31–14.05 s] 'go forward ten meters' (p=0.93) from 92°, angry (0.81), female (0.97)'.

    The direction is shown where SSL was fused, each label (emotion, gender, voice) with the
    share of its top class where that analyser said something about the utterance."""
    anchor = fused["anchor"]
    span = anchor["span"]
    start_s, end_s = (span["start_ns"] - origin_ns) / 1e9, (span["end_ns"] - origin_ns) / 1e9
    what = ""
    if "speech" in anchor and anchor["speech"].get("hypotheses"):
        best = anchor["speech"]["hypotheses"][0]
        if not best.get("text") and not best.get("raw_text"):
            what = "(speech not understood)"
        elif best.get("out_of_set"):
            what = f"out of set: '{best.get('raw_text', '')}' (match {best.get('match_score', 0):.2f})"
        else:
            what = f"'{best['text']}' (p={best['probability']:.2f})"
    else:
        payload = next((k for k in ("vad", "ssl", "emotion", "gender", "voice_id") if k in anchor), "")
        what = f"{payload} {json.dumps(anchor.get(payload, {}))}"
    aggregates = fused.get("aggregates") or {}
    shown = set()
    if aggregates.get("ssl"):  # where the utterance came from: the fused SSL directions' circular mean
        what += f" from {aggregates['ssl']['azimuth_deg']:.0f}°"
        shown.add("ssl")
    for kind in LABELS:  # how, and who: the top label of the fused distribution and its share
        if aggregates.get(kind):
            label, share = aggregates[kind]["label"], f" ({aggregates[kind]['probability']:.2f})"
            if kind == "voice_id":  # "by Anna (0.91)"; an anonymous voice has no probability to show
                what += f" by {label}" + ("" if label.startswith("voice-") else share)
            else:
                what += f", {label}{share}"
            shown.add(kind)
    for kind, aggregate in sorted(aggregates.items()):  # plug-ins' kinds: "duration 1.64", "pace fast (0.80)"
        if aggregate and kind not in shown and kind != "ssl":
            label = f" {aggregate['label']} ({aggregate['probability']:.2f})" if aggregate.get("label") else ""
            value = f" {aggregate['value']:.3g}" if aggregate.get("value") is not None else ""
            what += f", {kind}{label}{value}"
            shown.add(kind)
    extra = [f"{kind}×{len(results)}" for kind, results in sorted(fused.get("results", {}).items())
             if results and kind not in shown]  # fused types with results but no aggregate shown
    if fused.get("completion") not in (None, "complete"):
        extra.append(f"{fused['completion']}, missing {', '.join(fused.get('missing_components', []))}")
    revision = f" rev {fused['revision']}" if fused.get("revision", 1) > 1 else ""
    return f"[{start_s:.2f}–{end_s:.2f} s] {what}{' ' + '; '.join(extra) if extra else ''}{revision}"


@dataclass
class Following:
    """What :func:`follow` keeps track of between two messages."""
    origin_ns: int  # the stream's start: lines show times relative to it
    next_progress: float  # monotonic time of the next progress and health report
    grabber_done_at: float | None = None  # when the grabber finished playing the file
    heard_at: float = 0.0  # when the last message arrived
    warned: bool = False  # --serve: said once that the stream did not end
    ended: bool = False
    printed: int = 0
    unhealthy: str = ""  # why the orchestrator said it is unhealthy, as last reported


def follow(ws, supervisor: Supervisor, client: OrchestratorClient, grabber, args: argparse.Namespace) -> int:
    """Prints fused results until the stream has ended (file) or forever (mic, --serve)."""
    def stream_start_ns() -> int | None:
        stream = client.stream(args.stream_id)
        return stream["start_ns"] if stream else None

    origin_ns = wait_until(stream_start_ns, supervisor, "the grabber to start playing", START_TIMEOUT_S, grabber)
    if args.json:
        print(json.dumps({"type": "stream_start", "stream_id": args.stream_id, "start_ns": origin_ns}), flush=True)
    state = Following(origin_ns, next_progress=time.monotonic() + PROGRESS_EVERY_S)
    while True:
        report_when_due(state, client, args)
        watch_children(state, supervisor, grabber)
        if (code := check_drained(state, args)) is not None:
            return code
        try:
            message = json.loads(ws.recv(timeout=0.2))
        except TimeoutError:
            continue
        except ConnectionClosed as exc:
            raise LaunchError(f"the orchestrator closed the websocket: {exc}") from None
        state.heard_at = time.monotonic()  # results still arriving: the drain deadline moves on
        if (code := show_message(state, message, args)) is not None:
            return code


def report_when_due(state: Following, client: OrchestratorClient, args: argparse.Namespace) -> None:
    """Every PROGRESS_EVERY_S: how much of the file has been played, and the orchestrator's health."""
    if time.monotonic() < state.next_progress:
        return
    state.next_progress += PROGRESS_EVERY_S
    if args.input and state.grabber_done_at is None:
        show_progress(client)
    state.unhealthy = report_health(client, state.unhealthy)


def watch_children(state: Following, supervisor: Supervisor, grabber) -> None:
    """Notes the grabber's end; a grabber that failed ends the run, another service is restarted."""
    for child in supervisor.exited():
        if child is grabber and child.process.returncode == 0:
            state.grabber_done_at = state.grabber_done_at or time.monotonic()
            continue
        if child is grabber:
            raise LaunchError(supervisor.failure(child))
        supervisor.restart_when_due(child)


def check_drained(state: Following, args: argparse.Namespace) -> int | None:
    """The exit code once nothing has come for DRAIN_TIMEOUT_S after the file was played (None: go on)."""
    if not state.grabber_done_at or state.ended or \
            time.monotonic() - max(state.grabber_done_at, state.heard_at) <= DRAIN_TIMEOUT_S:
        return None
    if not args.serve:
        print(f"esiaf: no end of stream and no result {DRAIN_TIMEOUT_S:g} s after the file was played; "
              f"stopping", file=sys.stderr)
        return 1
    if not state.warned:  # --serve never stops the services on its own
        state.warned = True
        print(f"esiaf: no end of stream {DRAIN_TIMEOUT_S:g} s after the file was played; still serving",
              file=sys.stderr, flush=True)
    return None


def show_message(state: Following, message: dict[str, Any], args: argparse.Namespace) -> int | None:
    """Prints a fused result, or the stream's end; returns the exit code once the run is over."""
    if message.get("type") == "stream_end":
        state.ended = True
        if args.json:
            print(json.dumps(message), flush=True)
        print(f"esiaf: stream ended, {state.printed} fused result(s)", file=sys.stderr, flush=True)
        return None if args.serve or args.mic else 0
    if message.get("type") == "fused_result":
        state.printed += 1
        print(json.dumps(message) if args.json else format_line(message, state.origin_ns), flush=True)
    return None


def report_health(client: OrchestratorClient, reported: str) -> str:
    """Says on stderr when the orchestrator turns unhealthy (its database cannot be written) and
    when it recovers; returns what is now reported."""
    try:
        problem = client.health_problem()
    except httpx.HTTPError:
        return reported  # restarting: the supervisor says so
    if problem != reported:
        print(f"esiaf: orchestrator unhealthy: {problem}" if problem else "esiaf: orchestrator healthy again",
              file=sys.stderr, flush=True)
    return problem


def show_progress(client: OrchestratorClient) -> None:
    """'esiaf: played 40 of 300 s (13 %)' on stderr, for files longer than LONG_FILE_S."""
    try:
        info = ((client.component("grabber") or {}).get("stats") or {}).get("info", {})
    except httpx.HTTPError:
        return
    played_s, duration_s = info.get("played_s"), info.get("duration_s")
    if played_s is not None and duration_s and duration_s > LONG_FILE_S:
        print(f"esiaf: played {played_s:.0f} of {duration_s:.0f} s ({100 * played_s / duration_s:.0f} %)",
              file=sys.stderr, flush=True)
