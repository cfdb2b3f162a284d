"""The ``esiaf`` command: ``esiaf run`` starts the whole pipeline as local processes.

    esiaf run --input FILE [--array SPEC] [--fast] [--grammar FILE|robocup] [--serve] [--without emotion,...]
    esiaf run --mic DEVICE [--array SPEC]
    esiaf eval robocup [--runs N] [--seed S] [--snr LO:HI] [--array SPEC] [-- RUN OPTIONS]
    esiaf keys DIR [--component NAME ...]      (CURVE key pairs: esiaf/keys.py)

It starts the orchestrator, the recogniser, the VAD, the emotion, gender and voiceid services (on the VAD's
output, like the recogniser) and the grabber (with a microphone array also the ssl service and the
beamformer, the VAD hearing the array steered at the talker; with ``--no-beamformer`` the channel
splitter instead, the VAD hearing the first microphone), prints each fused result as one line as
it arrives, and with ``--input`` exits once the file has been played and its last fused result
printed. ``--without`` leaves analysers out; the orchestrator's default fusion waits only for
the analysers that are running.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import socket
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path
from typing import Any

import httpx
from websockets.exceptions import ConnectionClosed

from esiaf import auth
from esiaf.feed import FusedFeed
from esiaf.launcher import LaunchError, OrchestratorClient, Supervisor, fixed_ports, wait_until
from esiaf.plugins import resolve as resolve_plugin

log = logging.getLogger("esiaf")

ANALYSERS = ("ssl", "emotion", "gender", "voiceid")  # what --without can leave out (the recogniser anchors every line)
LABELS = ("emotion", "gender", "voice_id")  # label aggregates shown on a line, in this order
START_TIMEOUT_S = 60.0
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


def check_input(path: Path) -> int:
    """Checks the input file; returns its channel count. Any rate and sample type is fine: the
    grabber sends the file as it is and the SDK converts it to what each consumer takes."""
    if not path.exists():
        raise LaunchError(f"input file {path} does not exist")
    if not path.is_file():
        raise LaunchError(f"input {path} is not a file")
    try:
        path.open("rb").close()
    except OSError as exc:
        raise LaunchError(f"cannot read input file {path}: {exc.strerror}") from None
    if path.suffix.lower() in (".raw", ".pcm"):
        return 1  # headerless: read as 16 kHz int16 mono
    import soundfile
    try:
        info = soundfile.info(str(path))
    except Exception as exc:  # libsndfile's own error types vary by version
        raise LaunchError(f"cannot read input file {path}: {exc}") from None
    if info.frames == 0:
        raise LaunchError(f"input file {path} holds no audio")
    return info.channels


def check_array(args: argparse.Namespace, channels: int):
    """The array geometry and the audio's channel count (None, channels for mono without --array)."""
    from esiaf.arrays import ArrayError, load_array
    mic_channels = parse_channels(args.mic_channels)
    if args.array is None:
        if mic_channels or args.channels:
            raise LaunchError("--mic-channels and --channels describe a microphone array: give --array too")
        if channels > 1:
            print(f"esiaf: {args.input} has {channels} channels and no --array: the analysers hear channel 0 "
                  f"(name the microphone array with --array, e.g. respeaker4, to localise the speakers too)",
                  file=sys.stderr, flush=True)
        return None, channels
    try:
        array = load_array(args.array)
        if not channels:  # live capture: as many channels as asked, or as the microphones need
            channels = args.channels or (max(mic_channels) + 1 if mic_channels else array.mics)
        array.select_channels(channels, mic_channels)
    except ArrayError as exc:
        raise LaunchError(str(exc)) from None
    return array, channels


def parse_channels(text: str | None) -> list[int]:
    if not text:
        return []
    try:
        return [int(part) for part in text.split(",")]
    except ValueError:
        raise LaunchError(f"--mic-channels takes channel numbers separated by commas (e.g. 1,2,3,4), "
                          f"not {text!r}") from None


def parse_without(text: str | None) -> set[str]:
    """The analysers ``--without`` leaves out."""
    names = {part.strip() for part in (text or "").split(",") if part.strip()}
    unknown = sorted(names - set(ANALYSERS))
    if unknown:
        raise LaunchError(f"--without takes analysers separated by commas ({', '.join(ANALYSERS)}), "
                          f"not {', '.join(unknown)}")
    return names


def check_port_free(host: str, port: int) -> None:
    with socket.socket() as probe:
        # as the orchestrator will (uvicorn): connections of an earlier run in TIME_WAIT do not count
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except OSError as exc:
            raise LaunchError(f"cannot listen on {host}:{port}: {exc.strerror} (another orchestrator running? "
                              f"use --port)") from None


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="esiaf", description="ESIAF speech-analysis pipeline")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run every service as a local process")
    source = run.add_mutually_exclusive_group(required=True)
    source.add_argument("--input", type=Path, help="sound file to play (WAV/FLAC/... of any rate and sample type, "
                        "or .raw: 16 kHz s16le mono)")
    source.add_argument("--mic", metavar="DEVICE", help="ALSA capture device (see arecord -L)")
    run.add_argument("--array", help="microphone array of a multi-channel input or --mic: pepper4, respeaker4, "
                     "circular:MICS:RADIUS_M or a YAML file; starts sound source localisation")
    run.add_argument("--mic-channels", help="with --array: the channels that are the microphones, in the array's "
                     "order, where the audio has others too (ReSpeaker 6-channel firmware: 1,2,3,4)")
    run.add_argument("--channels", type=int, help="with --mic and --array: channels to capture "
                     "(default: as the microphones need)")
    run.add_argument("--without", metavar="ANALYSERS", help="analysers to leave out, separated by commas: "
                     "emotion, gender, voiceid, ssl (e.g. --without emotion,gender on a slow robot)")
    run.add_argument("--with", dest="plugins", action="append", default=[], metavar="FOLDER_OR_NAME",
                     help="also run your own analyser: a folder with a __main__.py, an installed component "
                     "(entry point group esiaf.components) or a module; repeatable")
    run.add_argument("--no-beamformer", action="store_true", help="with --array: the analysers hear the first "
                     "microphone instead of the array steered at the talker")
    run.add_argument("--beamformer", choices=("mvdr", "das"), help="with --array: the beamforming method "
                     "(default mvdr; das: delay and sum)")
    run.add_argument("--ssl-algorithm", help="DOA algorithm of the ssl service (default NormMUSIC)")
    run.add_argument("--fast", action="store_true", help="play the file as fast as possible")
    run.add_argument("--grammar", help="JSGF grammar file for the recogniser, or 'robocup' (with --asr whisper: "
                     "the allowed sentences its transcripts are matched to)")
    run.add_argument("--vad", choices=("silero", "energy"), help="the voice activity detector: silero (default, "
                     "a neural VAD that babble does not fool) or energy (the original double threshold)")
    run.add_argument("--asr", choices=("pocketsphinx", "whisper"), help="the recogniser (default pocketsphinx)")
    run.add_argument("--serve", action="store_true", help="keep the services up after the file has played")
    run.add_argument("--host", default="127.0.0.1", help="orchestrator address (default 127.0.0.1)")
    run.add_argument("--port", type=int, default=8000, help="orchestrator HTTP port (default 8000)")
    run.add_argument("--workdir", type=Path, default=Path(".esiaf"), help="logs and database (default .esiaf)")
    run.add_argument("--recover", action="store_true", help="if the workdir's database is corrupt, start on a copy "
                     "of what can still be read (the orchestrator's log says what was lost; the damaged file is kept)")
    run.add_argument("--stream-id", help="name of this capture session (default: input name + time)")
    run.add_argument("--chunk-ms", type=float, default=20.0, help="grabber chunk length (default 20 ms)")
    run.add_argument("--json", action="store_true", help="print each fused result as JSON")
    run.add_argument("-v", "--verbose", action="store_true", help="log what the launcher does")
    sub.add_parser("eval", help="evaluation harnesses through the real pipeline: esiaf eval robocup --help")
    sub.add_parser("keys", help="CURVE key pairs for ZeroMQ across hosts: esiaf keys DIR --help")
    return parser.parse_args(argv)


def run(args: argparse.Namespace) -> int:
    array, channels = check_array(args, check_input(args.input) if args.input else 0)
    without = parse_without(args.without)
    wanted_plugins = [resolve_plugin(spec) for spec in args.plugins]  # a bad --with fails before anything starts
    if args.grammar and args.grammar != "robocup":
        if not Path(args.grammar).is_file():
            raise LaunchError(f"grammar file {args.grammar} does not exist")
        args.grammar = str(Path(args.grammar).resolve())  # the services run elsewhere: relative paths would break
    if args.array and Path(args.array).is_file():
        args.array = str(Path(args.array).resolve())
    check_port_free(args.host, args.port)
    stream_id = args.stream_id = args.stream_id or "{}-{}".format(
        args.input.stem if args.input else "mic", datetime.now().strftime("%Y%m%d-%H%M%S"))
    url = f"http://{args.host}:{args.port}"
    workdir = args.workdir.resolve()
    # one token per run (or the one given): every service presents it, every query needs it
    os.environ[auth.TOKEN_ENV] = auth.token() or auth.new_token()
    auth.write_token(workdir / "token", os.environ[auth.TOKEN_ENV])
    supervisor = Supervisor(workdir, env={"ESIAF_ORCHESTRATOR_URL": url, "ESIAF_STREAM_ID": stream_id})
    client = OrchestratorClient(url)
    try:
        # the default fusion: each recognised utterance with the ssl, emotion, gender and voice_id results
        # within it; the orchestrator waits only for those analysers that are running
        ports = fixed_ports(workdir)  # the same across restarts: components find it again, nothing is lost
        orchestrator = supervisor.start("orchestrator", ["--host", args.host, "--port", str(args.port),
                                                         "--db", str(workdir / "esiaf.db")]
                                        + (["--recover"] if args.recover else []),
                                        env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": str(ports["control"]),
                                             "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(ports["results"])})
        wait_until(client.healthy, supervisor, "the orchestrator to answer", START_TIMEOUT_S, orchestrator)
        # every service at once (their imports and models load in parallel), then each must register
        services = {"asr": supervisor.start("asr", (["--grammar", args.grammar] if args.grammar else [])
                                            + (["--backend", args.asr] if args.asr else []))}
        grabber_env = {"ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1", "ESIAF_GRABBER_CHUNK_MS": str(args.chunk_ms)}
        vad_env = {"ESIAF_VAD_BACKEND": args.vad} if args.vad else {}
        beamforming = array is not None and "ssl" not in without and not args.no_beamformer
        if channels <= 1 and array is None:
            services["vad"] = supervisor.start("vad", env=vad_env)
        elif beamforming:  # grabber -> ssl -> beamformer -> vad: the analysers hear the array steered at the talker
            services["vad"] = supervisor.start("vad", env={"ESIAF_VAD_INPUT_TOPIC": "beamformer/audio", **vad_env})
            beam_env = array_env("BEAMFORMER", args, channels)
            if args.beamformer:
                beam_env["ESIAF_BEAMFORMER_METHOD"] = args.beamformer
            services["beamformer"] = supervisor.start("beamformer", env=beam_env)
            grabber_env["ESIAF_GRABBER_CHANNELS"] = str(channels)
        else:  # the recogniser hears the first channel (microphone); ssl hears them all
            services["vad"] = supervisor.start("vad", env={"ESIAF_VAD_INPUT_TOPIC": "splitter/ch0", **vad_env})
            services["splitter"] = supervisor.start("splitter", env={
                "ESIAF_SPLITTER_INPUT_CHANNELS": str(channels), "ESIAF_SPLITTER_CHANNELS": "[0]"})
            grabber_env["ESIAF_GRABBER_CHANNELS"] = str(channels)
        if array is not None and "ssl" not in without:
            ssl_env = array_env("SSL", args, channels)
            if args.ssl_algorithm:
                ssl_env["ESIAF_SSL_ALGORITHM"] = args.ssl_algorithm
            services["ssl"] = supervisor.start("ssl", env=ssl_env)
            if not beamforming:
                grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"] = "2"
        labellers = [name for name in ("emotion", "gender", "voiceid") if name not in without]
        for name in labellers:  # on the VAD's output, like the recogniser
            services[name] = supervisor.start(name)
        plugins = {plugin.name: supervisor.start(plugin.name, target=plugin.target) for plugin in wanted_plugins}
        for name, child in services.items():
            wait_until(lambda name=name: client.component(name), supervisor, f"the {name} service to register",
                       START_TIMEOUT_S, child)
        registered = [wait_until(lambda child=child: client.by_pid(child.process.pid), supervisor,
                                 f"{name} (--with) to register", START_TIMEOUT_S, child)
                      for name, child in plugins.items()]
        kinds = [component["designation"] for component in registered]
        fuse_kinds(client, [kind for kind in kinds if kind != "other"])
        on_speech = sum(any(i["topic"] == "vad/speech" for i in c["inputs"]) for c in registered)
        services.update(plugins)
        if "splitter" in services:
            wait_until(lambda: topic_ready(client, "splitter/ch0", 1), supervisor,
                       "vad to subscribe to splitter/ch0", START_TIMEOUT_S, services["vad"])
        if beamforming:
            wait_until(lambda: topic_ready(client, "ssl/audio", 1), supervisor,
                       "the beamformer to subscribe to ssl/audio", START_TIMEOUT_S, services["beamformer"])
            wait_until(lambda: topic_ready(client, "beamformer/audio", 1), supervisor,
                       "vad to subscribe to beamformer/audio", START_TIMEOUT_S, services["vad"])
        wait_until(lambda: topic_ready(client, "vad/speech", 1 + len(labellers) + on_speech), supervisor,
                   f"{', '.join(['asr', *labellers])} to subscribe to vad/speech", START_TIMEOUT_S, services["vad"])
        if plugins:
            with_kinds = ", ".join(f"{n} ({k})" for n, k in zip(plugins, kinds, strict=True))
            print(f"esiaf: with {with_kinds}", file=sys.stderr)
        log.info("services: %s", ", ".join(services))
        with FusedFeed(f"ws://{args.host}:{args.port}/ws/fused?stream={stream_id}") as ws:
            source = ["--input", str(args.input.resolve())] if args.input else ["--device", args.mic]
            grabber = supervisor.start("grabber", source + (["--fast"] if args.fast else []), env=grabber_env)
            print(f"esiaf: playing {args.input or args.mic} as stream {stream_id}; "
                  f"orchestrator at {url} (API docs: {url}/docs; token in {shown_path(workdir / 'token')}); "
                  f"logs in {shown_path(workdir / 'logs')}",
                  file=sys.stderr, flush=True)
            print(f"esiaf: dashboard at {url}/?token={os.environ[auth.TOKEN_ENV]}", file=sys.stderr, flush=True)
            return follow(ws, supervisor, client, grabber, args)
    finally:
        client.close()
        supervisor.stop()


def array_env(service: str, args: argparse.Namespace, channels: int) -> dict[str, str]:
    """The settings every array consumer (ssl, beamformer) takes: the array, the channel count, the
    microphones' channels."""
    env = {f"ESIAF_{service}_ARRAY": args.array, f"ESIAF_{service}_CHANNELS": str(channels)}
    if args.mic_channels:
        env[f"ESIAF_{service}_MIC_CHANNELS"] = f"[{args.mic_channels}]"
    return env


def fuse_kinds(client: OrchestratorClient, kinds: list[str]) -> None:
    """Adds the plug-ins' result kinds to every speech-anchored fusion, so their results are on
    each line; the orchestrator then waits for them like for the built-in analysers."""
    if not kinds:
        return
    fusions = client.fusions()
    for fusion in fusions:
        if fusion["anchor"] == "speech":
            fusion["fuse"] = list(dict.fromkeys([*fusion["fuse"], *kinds]))
    client.put_fusions(fusions)


def shown_path(path: Path) -> Path:
    """``path`` relative to the current directory where it is inside it (.esiaf/logs), else absolute."""
    try:
        return path.relative_to(Path.cwd())
    except ValueError:
        return path


def topic_ready(client: OrchestratorClient, topic: str, consumers: int) -> bool:
    for entry in client.topics():
        if entry.get("topic") == topic:
            return sum(p.get("subscribers") or 0 for p in entry.get("producers", [])) >= consumers
    return False


def follow(ws, supervisor: Supervisor, client: OrchestratorClient, grabber, args: argparse.Namespace) -> int:
    """Prints fused results until the stream has ended (file) or forever (mic, --serve)."""
    def stream_start_ns() -> int | None:
        stream = client.stream(args.stream_id)
        return stream and stream["start_ns"]

    origin_ns = wait_until(stream_start_ns, supervisor, "the grabber to start playing", START_TIMEOUT_S, grabber)
    if args.json:
        print(json.dumps({"type": "stream_start", "stream_id": args.stream_id, "start_ns": origin_ns}), flush=True)
    grabber_done_at = None
    heard_at = 0.0  # when the last message arrived
    warned = False
    ended = False
    printed = 0
    next_progress = time.monotonic() + PROGRESS_EVERY_S
    unhealthy = ""  # why the orchestrator said it is unhealthy, as last reported
    while True:
        if time.monotonic() >= next_progress:
            next_progress += PROGRESS_EVERY_S
            if args.input and grabber_done_at is None:
                show_progress(client)
            unhealthy = report_health(client, unhealthy)
        for child in supervisor.exited():
            if child is grabber and child.process.returncode == 0:
                grabber_done_at = grabber_done_at or time.monotonic()
                continue
            if child is grabber:
                raise LaunchError(supervisor.failure(child))
            supervisor.restart_when_due(child)
        if grabber_done_at and not ended and time.monotonic() - max(grabber_done_at, heard_at) > DRAIN_TIMEOUT_S:
            if not args.serve:
                print(f"esiaf: no end of stream and no result {DRAIN_TIMEOUT_S:g} s after the file was played; "
                      f"stopping", file=sys.stderr)
                return 1
            if not warned:  # --serve never stops the services on its own
                warned = True
                print(f"esiaf: no end of stream {DRAIN_TIMEOUT_S:g} s after the file was played; still serving",
                      file=sys.stderr, flush=True)
        try:
            message = json.loads(ws.recv(timeout=0.2))
        except TimeoutError:
            continue
        except ConnectionClosed as exc:
            raise LaunchError(f"the orchestrator closed the websocket: {exc}") from None
        heard_at = time.monotonic()  # results still arriving: the drain deadline moves on
        if message.get("type") == "stream_end":
            ended = True
            if args.json:
                print(json.dumps(message), flush=True)
            print(f"esiaf: stream ended, {printed} fused result(s)", file=sys.stderr, flush=True)
            if args.serve or args.mic:
                continue
            return 0
        if message.get("type") != "fused_result":
            continue
        printed += 1
        print(json.dumps(message) if args.json else format_line(message, origin_ns), flush=True)


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


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["eval"]:
        from esiaf.evaluation import main as evaluate
        return evaluate(argv[1:])
    if argv[:1] == ["keys"]:
        from esiaf.keys import main as make_keys
        return make_keys(argv[1:])
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s %(message)s")
    try:
        return run(args)
    except LaunchError as exc:
        print(f"esiaf: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("esiaf: stopped", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
