"""``esiaf run``: the launcher's wiring. It starts the orchestrator and every service as a local
process, connects them (which topic each hears, which analysers the fusion waits for), waits
until each has registered and subscribed, then plays the input and follows the results
(esiaf/tools/cli_follow.py).

Pocketsphinx and voiceid hear the vad's utterances through the denoiser (DeepFilterNet 3;
``--denoiser off``: straight from the vad; Whisper hears the vad unless ``--denoiser on``); the vad,
emotion and gender hear the audio as it is. Measured on the noisy-room harness (docs/benchmarks.md, "The
denoiser"): pocketsphinx 66.7 -> 81.7 % of the questions, Whisper 80.0 -> 71.7 %, the d-vector's
wrong names in a room 31.1 -> 10.5 % (bench/voiceid.py --denoise); with the denoiser
before the vad, the vad heard the background talkers, denoised, as speech (3.7 segments of nothing
per run instead of 0.25).
"""
from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import signal
import subprocess
from collections import Counter
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlencode

from esiaf import auth
from esiaf.services import known_services
from esiaf.settings import unknown_variables
from esiaf.tools.cli_args import (
    check_array,
    check_echo,
    check_inputs,
    check_port_free,
    check_settings,
    expand_inputs,
    parse_replicas,
    parse_without,
    replayed_streams,
    source_name,
    stream_ids,
)
from esiaf.tools.cli_follow import Stream, follow, shows_partials
from esiaf.tools.feed import FusedFeed
from esiaf.tools.launcher import (
    START_TIMEOUT_S,
    Child,
    LaunchError,
    OrchestratorClient,
    Supervisor,
    fixed_ports,
    wait_until,
)
from esiaf.tools.plugins import resolve as resolve_plugin
from esiaf.tools.terminal import err, out

if TYPE_CHECKING:
    from esiaf.arrays import ArrayGeometry

log = logging.getLogger("esiaf")

# --fast: every service's audio queues (ESIAF_AUDIO_QUEUE, messages per connection and direction): 12.5 s
# of the default 50 ms chunks. A replay waits for its slowest consumer (docs/protocol.md, "Flow control"), so a small
# queue loses nothing and keeps each process's memory flat; live use keeps the large default (a value
# given in the environment wins)
FAST_AUDIO_QUEUE = 250


@dataclass
class Pipeline:
    """The services started for a run, and how the grabber is to feed them."""
    services: dict[str, Child]
    grabber_env: dict[str, str]
    beamforming: bool  # grabber -> ssl -> beamformer -> vad
    labellers: list[str]  # the analysers on the VAD's output besides the recogniser
    replicas: dict[str, int]  # analysers on the VAD's output run as several instances (--replicas)
    guests: set[str] = field(default_factory=set)  # labellers run in another labeller's process (not --apart)
    vad_in_grabber: bool = False  # the vad is a guest in the grabber's process (--vad-in-grabber)
    microphones: str = "grabber/audio"  # what the first services hear: aec/audio with --player or --playback
    microphone_consumers: int = 1  # ... how many services subscribe to it
    # the topic each service on the vad's output hears: vad/speech, or denoiser/speech (vad -> denoiser -> them)
    inputs: dict[str, str] = field(default_factory=dict)
    # the topic Whisper's second opinion in the asr hears besides the asr's input ("": none; asr/service.py)
    second_opinion_topic: str = ""


def run(args: argparse.Namespace) -> int:
    args.recorded_streams, channels = [], 0  # beside each input, the recorded stream it replays ("": no recording)
    if args.input:  # every file and folder checked before anything starts
        args.input = expand_inputs(args.input)
        channels = check_inputs(args.input)
        args.input, args.recorded_streams = replayed_streams(args.input, channels)
    array, channels = check_array(args, channels)
    names = [source_name(path, recorded) for path, recorded in zip(args.input, args.recorded_streams, strict=True)] \
        if args.input else ["mic"]
    ids = stream_ids(names, args.stream_id)
    without = parse_without(args.without)
    wanted_plugins = [resolve_plugin(spec) for spec in args.plugins]  # a bad --with fails before anything starts
    replicas = parse_replicas(args.replicas, without, [plugin.name for plugin in wanted_plugins])
    check_echo(args)
    if args.vad_in_grabber:
        check_vad_in_grabber(args, channels, array, replicas)
    services = known_services() | {p.name for p in wanted_plugins}
    for name in unknown_variables(os.environ, services):
        err(f"esiaf: {name} names no service ({', '.join(sorted(services))}) and no common setting: "
            "ignored; a typo?")
    check_settings(os.environ, services)
    check_port_free(args.host, args.port)
    args.stream_id = ids[0] if len(ids) == 1 else None
    workdir, supervisor, client = prepare(args, {"ESIAF_STREAM_ID": ids[0]} if len(ids) == 1 else {})
    url = client.url
    try:
        start_orchestrator(args, supervisor, client, workdir)
        refuse_reused(client, ids, workdir)
        # every service at once (their imports and models load in parallel), then each must register
        pipeline = start_services(args, supervisor, array, channels, without, replicas)
        plugin_of: dict[str, str] = {}  # each plug-in instance's plug-in
        plugins: dict[str, Child] = {}
        for plugin in wanted_plugins:
            started = start_replicas(supervisor, plugin.name, replicas.get(plugin.name, 1), target=plugin.target)
            plugins.update(started)
            plugin_of.update(dict.fromkeys(started, plugin.name))
        registered = wait_for_registration(client, supervisor, pipeline.services, plugins)
        pipeline.services.update(plugins)
        on_speech = [plugin_of[name] for name, component in registered.items()
                     if any(i["topic"] == "vad/speech" for i in component["inputs"])]
        # replicas take their streams later (reserve_streams): here, the other plug-in instances count
        wait_for_subscriptions(client, supervisor, pipeline, sum(name not in replicas for name in on_speech))
        if replicas:
            reserve_streams(client, supervisor, pipeline, ids, on_speech)
        supervisor.ready()  # the vad's spare starts now
        if plugins:
            with_kinds = ", ".join(f"{n} ({c['kind']})" for n, c in registered.items())
            err(f"esiaf: with {with_kinds}")
        log.info("services: %s", ", ".join(pipeline.services))
        for name, count in replicas.items():
            err(f"esiaf: {name} as {count} instances sharing the streams ({name}-1 ... {name}-{count})")
        # one stream: only its results; several: every stream's, each line told by its stream_id
        # partial results: on a terminal, one line rewritten in place; with --json only if --partials asks
        query = {**({"stream": ids[0]} if len(ids) == 1 else {}), **({"partials": 1} if shows_partials(args) else {}),
                 **({"include_robot": "true"} if args.include_robot else {})}
        feed_url = f"ws://{args.host}:{args.port}/ws/fused" + (f"?{urlencode(query)}" if query else "")
        with FusedFeed(feed_url) as ws, recording(args, supervisor, pipeline, url):
            if args.ros2:
                pipeline.services["ros2"] = start_ros2(supervisor, client, pipeline, ids)
            streams = start_grabbers(args, supervisor, pipeline, ids)
            err(f"esiaf: orchestrator at {url} (API docs: {url}/docs; token in {shown_path(workdir / 'token')}); "
                f"logs in {shown_path(workdir / 'logs')}")
            err(f"esiaf: dashboard at {url}/?token={os.environ[auth.TOKEN_ENV]}")
            code = follow(ws, supervisor, client, streams, args)
            return show_diff(args.input[0], client, streams, args.recorded_streams, code) if args.diff else code
    finally:
        client.close()
        supervisor.stop()


def prepare(args: argparse.Namespace, env: dict[str, str]) -> tuple[Path, Supervisor, OrchestratorClient]:
    """Once every argument is checked: the workdir made, the run's token, a supervisor whose services
    find the orchestrator (with ``env`` too), a client of the orchestrator."""
    url = f"http://{args.host}:{args.port}"
    workdir = args.workdir.resolve()
    try:  # only now, every argument checked: a refused command line writes nothing
        workdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LaunchError(f"--workdir {workdir} cannot be made: {exc.strerror}") from None
    # one token per run (or the one given): every service presents it, every query needs it
    os.environ[auth.TOKEN_ENV] = auth.token() or auth.new_token()
    auth.write_token(workdir / "token", os.environ[auth.TOKEN_ENV])
    supervisor = Supervisor(workdir, env={"ESIAF_ORCHESTRATOR_URL": url} | env
                            | ({"ESIAF_AUDIO_QUEUE": os.environ.get("ESIAF_AUDIO_QUEUE", str(FAST_AUDIO_QUEUE))}
                               if args.fast else {}))
    return workdir, supervisor, OrchestratorClient(url)


@contextmanager
def recording(args: argparse.Namespace, supervisor: Supervisor, pipeline: Pipeline, url: str) -> Iterator[None]:
    """--record: the recorder (esiaf/tools/mcap_record.py), a consumer of the audio topics that follows the
    fused results, started before the grabbers (they wait for it too, so that it hears their first chunk) and
    stopped before the orchestrator (it catches up on what was fused meanwhile)."""
    if args.record is None:
        yield
        return
    recorder = start_recorder(args, supervisor, pipeline, url)
    try:
        yield
    finally:
        stop_recorder(recorder)


def start_recorder(args: argparse.Namespace, supervisor: Supervisor, pipeline: Pipeline, url: str) -> Child:
    topics = [topic.strip() for topic in (args.record_topics or "grabber/audio").split(",") if topic.strip()]
    if "grabber/audio" in topics:
        waited = int(pipeline.grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"])
        pipeline.grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"] = str(waited + 1)
    return supervisor.start("recorder", ["--out", str(args.record), "--url", url, "--topics", ",".join(topics),
                                         "--max-mb", str(args.record_max_mb), "--max-s", str(args.record_max_s),
                                         "--go-on"],
                            target=["-m", "esiaf.tools.mcap_record"])


def stop_recorder(recorder: Child, timeout_s: float = 3 * START_TIMEOUT_S) -> None:
    """Ends the recording: the recorder catches up with the orchestrator and finishes its file."""
    if recorder.process.poll() is None:
        recorder.process.send_signal(signal.SIGTERM)
    try:
        recorder.process.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        err(f"esiaf: the recorder did not finish in {timeout_s:g} s (its log: {recorder.log_path})")
    for line in recorder.tail().splitlines():  # its summary, or why it stopped
        if line.strip().startswith("esiaf"):
            err(line.strip())


def show_diff(recording: Path, client: OrchestratorClient, streams: list[Stream], recorded: list[str],
              code: int) -> int:
    """--diff: each replayed stream's fused results against its recorded stream's (esiaf/tools/mcap_diff.py),
    the recorded stream named first when there are several; the run's exit code."""
    from esiaf.tools.mcap_convert import fused_from_json
    from esiaf.tools.mcap_diff import diff, session_utterances, utterance
    for stream, recorded_stream in zip(streams, recorded, strict=True):
        replayed = [utterance(fused_from_json(item), stream.origin_ns or 0) for item in client.fused(stream.stream_id)]
        if len(streams) > 1:
            out(f"stream {recorded_stream} (replayed as {stream.stream_id}):")
        for line in diff(session_utterances(recording, recorded_stream), sorted(replayed, key=lambda u: u.start_s)):
            out(line)
    return code


def start_grabbers(args: argparse.Namespace, supervisor: Supervisor, pipeline: Pipeline,
                   ids: list[str]) -> list[Stream]:
    """A grabber per input, all at once, each playing its stream; with several, each is an instance of its
    own (grabber-1, grabber-2, ...: logs/grabber-1.log, ...)."""
    sources: list[list[str]] = [["--input", str(path.resolve())] for path in args.input] if args.input \
        else [["--device", args.mic]]
    recorded = args.recorded_streams or [""] * len(ids)
    streams = []
    for n, (source, stream_id, replayed) in enumerate(zip(sources, ids, recorded, strict=True), start=1):
        grabber = supervisor.start("grabber", source + (["--fast"] if args.fast else []),
                                   env={**pipeline.grabber_env, "ESIAF_STREAM_ID": stream_id,
                                        **({"ESIAF_GRABBER_INPUT_STREAM": replayed} if replayed else {})},
                                   instance=f"grabber-{n}" if len(ids) > 1 else None)
        shown = (str(args.input[n - 1]) + (f" (its stream {replayed})" if len(ids) > 1 and replayed else "")
                 if args.input else args.mic)
        streams.append(Stream(stream_id, grabber, shown))
        err(f"esiaf: playing {shown} as stream {stream_id}" + (f" ({grabber.name})" if len(ids) > 1 else ""))
    return streams


def start_ros2(supervisor: Supervisor, client: OrchestratorClient, pipeline: Pipeline, ids: list[str]) -> Child:
    """--ros2: the bridge to ROS 2 (esiaf_services/ros2), following this run's streams (one: its stream;
    several: each in a namespace of its own, /<stream id>/humans/...); the grabbers play once it follows
    the fused results (its health file is touched) and, with a beamformer, once it hears the beamformer's
    audio (each voice's audio topic), so it misses none."""
    health = supervisor.workdir / "ros2.health"
    health.unlink(missing_ok=True)
    env = {"ESIAF_ROS2_HEALTH_FILE": str(health)} | (
        {"ESIAF_ROS2_STREAM": ids[0]} if len(ids) == 1 else {"ESIAF_ROS2_NAMESPACE_PER_STREAM": "true"}) | (
        {"ESIAF_ROS2_AUDIO_TOPIC": "beamformer/audio"} if pipeline.beamforming else {})
    child = supervisor.start("ros2", env=env)
    wait_until(health.exists, supervisor, "the ros2 bridge to follow the fused results", START_TIMEOUT_S, child)
    if pipeline.beamforming:  # the vad and the bridge
        wait_until(lambda: topic_ready(client, "beamformer/audio", 2), supervisor,
                   "the ros2 bridge to subscribe to beamformer/audio", START_TIMEOUT_S, child)
    return child


def refuse_reused(client: OrchestratorClient, ids: list[str], workdir: Path) -> None:
    """A stream id this workdir's database already holds is refused before anything is played: the
    results of two capture sessions would be fused as one stream (the second's times shifted)."""
    for stream_id in ids:
        if client.stream(stream_id) is not None:
            raise LaunchError(f"stream {stream_id} was played before in {shown_path(workdir)}: give another "
                              f"--stream-id, or another --workdir")


def start_orchestrator(args: argparse.Namespace, supervisor: Supervisor, client: OrchestratorClient,
                       workdir: Path) -> None:
    """Starts the orchestrator and waits until it answers. Its default fusion: each recognised utterance
    with the ssl, emotion, gender and voice_id results within it; it waits only for those analysers
    that are running."""
    ports = fixed_ports(workdir)  # the same across restarts: components find it again, nothing is lost
    orchestrator = supervisor.start("orchestrator", ["--host", args.host, "--port", str(args.port),
                                                     "--db", str(workdir / "esiaf.db")]
                                    + (["--recover"] if args.recover else []),
                                    env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": str(ports["control"]),
                                         "ESIAF_ORCHESTRATOR_RESULTS_PORT": str(ports["results"]),
                                         # a recorded robot voice: its echo is in the recording whatever a
                                         # barge-in does, and a stopped reference would leave it uncancelled
                                         **({"ESIAF_ORCHESTRATOR_BARGE_IN_POLICY": "ignore"}
                                            if args.playback is not None else {})})
    wait_until(client.healthy, supervisor, "the orchestrator to answer", START_TIMEOUT_S, orchestrator)
    for line in client.recovered() if args.recover else []:
        err(f"esiaf: --recover: {line}")


def start_services(args: argparse.Namespace, supervisor: Supervisor, array: ArrayGeometry | None, channels: int,
                   without: set[str], replicas: dict[str, int]) -> Pipeline:
    """Starts the recogniser, the VAD (on the array steered at the talker, on the first channel or on
    the mono input), the ssl service with an array, and the labellers on the VAD's output (those in
    ``replicas`` as that many instances: asr-1, asr-2, ...)."""
    # who hears the vad's utterances denoised; the vad hears the audio as it is (see the module)
    inputs = speech_inputs(args, without)
    second_opinion_topic = second_opinion_input(inputs)
    services = start_replicas(supervisor, "asr", replicas.get("asr", 1),
                              (["--grammar", args.grammar] if args.grammar else [])
                              + (["--backend", args.asr] if args.asr else []),
                              env={"ESIAF_ASR_INPUT_TOPIC": inputs["asr"]})
    if "denoiser" in inputs:
        services["denoiser"] = supervisor.start("denoiser")
    grabber_env = {"ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1",
                   **({"ESIAF_GRABBER_CHUNK_MS": str(args.chunk_ms)} if args.chunk_ms is not None else {})}
    vad_env = {"ESIAF_VAD_BACKEND": args.vad} if args.vad else {}
    beamforming = array is not None and "ssl" not in without and not args.no_beamformer
    # with --player or --playback the first services hear the echo canceller, and the grabber waits for it alone
    microphones = start_echo_cancelling(args, supervisor, services, max(channels, 1))
    vad_in_grabber = args.vad_in_grabber
    if vad_in_grabber:  # it starts with the grabber, and the grabber waits for the vad's consumers
        grabber_env.update({"ESIAF_GRABBER_GUESTS": json.dumps(["vad"]), "ESIAF_GRABBER_WAIT_TOPIC": "vad/speech",
                            **vad_env})
        log.info("vad runs in the grabber's process")
    if not vad_in_grabber:
        heard = start_front(args, supervisor, services, channels, microphones, beamforming, grabber_env)
        services["vad"] = supervisor.start("vad", env={"ESIAF_VAD_INPUT_TOPIC": heard, **vad_env}, spare=True)
    if array is not None and "ssl" not in without:
        ssl_env = array_env("SSL", args, channels) | {"ESIAF_SSL_INPUT_TOPIC": microphones}
        if args.ssl_algorithm:
            ssl_env["ESIAF_SSL_ALGORITHM"] = args.ssl_algorithm
        services["ssl"] = supervisor.start("ssl", env=ssl_env)
        if not beamforming:
            grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"] = "2"
    consumers = int(grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"])
    if "aec" in services:
        grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"] = "1"
    labellers = [name for name in ("emotion", "gender", "voiceid") if name not in without]
    hosts = hosted_labellers(labellers, replicas, args.apart)
    for name in labellers:  # on the VAD's output (or the denoiser's), like the recogniser
        topic = {f"ESIAF_{name.upper()}_INPUT_TOPIC": inputs[name]}
        if name in hosts:
            env = {f"ESIAF_{name.upper()}_GUESTS": json.dumps(hosts[name]), **topic}
            services[name] = supervisor.start(name, env=env)
            services.update({guest: services[name] for guest in hosts[name]})  # the same process
            log.info("%s runs in the %s service's process", ", ".join(hosts[name]), name)
        elif name not in services:
            services.update(start_replicas(supervisor, name, replicas.get(name, 1), env=topic))
    guests = {guest for names in hosts.values() for guest in names}
    return Pipeline(services, grabber_env, beamforming, labellers, replicas, guests, vad_in_grabber, microphones,
                    consumers, inputs, second_opinion_topic)


def speech_inputs(args: argparse.Namespace, without: set[str]) -> dict[str, str]:
    """The topic each service on the vad's output hears (the denoiser among them where it runs). With
    ``--denoiser auto`` (the default) the denoiser runs for pocketsphinx (``--asr``, else
    ``ESIAF_ASR_BACKEND``) and voiceid, which it helps in noise, and not for Whisper, which it does not;
    emotion and gender hear the vad (not measured); ``on``: Whisper too; ``off``: no denoiser
    (docs/benchmarks.md, "The denoiser")."""
    backend = args.asr or os.environ.get("ESIAF_ASR_BACKEND") or "pocketsphinx"
    denoised = {"asr": args.denoiser == "on" or (args.denoiser == "auto" and backend == "pocketsphinx"),
                "voiceid": args.denoiser != "off" and "voiceid" not in without,
                "emotion": False, "gender": False}
    inputs = {name: "denoiser/speech" if heard else "vad/speech" for name, heard in denoised.items()}
    if any(denoised.values()):
        inputs["denoiser"] = "vad/speech"
    return inputs


def second_opinion_input(inputs: dict[str, str]) -> str:
    """The topic Whisper's second opinion in the asr hears besides the asr's input, if asked for
    (``ESIAF_ASR_SECOND_OPINION=whisper`` and ``ESIAF_ASR_SECOND_OPINION_TOPIC=vad/speech``: pocketsphinx
    hears the denoiser, Whisper the vad), so the launcher waits for that subscription too; "": none. Not the
    default: on the GPSR harness it gained nothing (docs/benchmarks.md, "GPSR commands")."""
    if os.environ.get("ESIAF_ASR_SECOND_OPINION") != "whisper":
        return ""
    topic = os.environ.get("ESIAF_ASR_SECOND_OPINION_TOPIC", "")
    return "" if topic == inputs["asr"] else topic


def start_front(args: argparse.Namespace, supervisor: Supervisor, services: dict[str, Child], channels: int,
                microphones: str, beamforming: bool, grabber_env: dict[str, str]) -> str:
    """Starts what stands between the microphones and the vad (or the denoiser before it): the
    beamformer with an array, the channel splitter for the first of several channels, nothing for one
    mono input. Returns the topic the vad is to hear."""
    if channels <= 1 and args.array is None:  # one mono input
        return microphones
    grabber_env["ESIAF_GRABBER_CHANNELS"] = str(channels)
    if beamforming:  # grabber -> ssl -> beamformer -> vad: the analysers hear the array steered at the talker
        beam_env = array_env("BEAMFORMER", args, channels)
        if args.beamformer:
            beam_env["ESIAF_BEAMFORMER_METHOD"] = args.beamformer
        services["beamformer"] = supervisor.start("beamformer", env=beam_env)
        return "beamformer/audio"
    # the recogniser hears the first channel (microphone); ssl hears them all
    services["splitter"] = supervisor.start("splitter", env={
        "ESIAF_SPLITTER_INPUT_CHANNELS": str(channels), "ESIAF_SPLITTER_CHANNELS": "[0]",
        "ESIAF_SPLITTER_INPUT_TOPIC": microphones})
    return "splitter/ch0"


def start_echo_cancelling(args: argparse.Namespace, supervisor: Supervisor, services: dict[str, Child],
                          channels: int) -> str:
    """With --player or --playback: the player and the echo canceller (grabber/audio + player/audio ->
    aec/audio); the topic the first services are to hear."""
    if args.player is None and args.playback is None:
        return getattr(args, "source_topic", "grabber/audio")  # esiaf wyoming's own source: wyoming/audio
    aec_env = {"ESIAF_AEC_CHANNELS": str(channels)}
    if args.playback is not None:
        # a replay: the robot's voice is on the input's timeline, from the stream's start; a chunk waits for
        # its reference however fast the grabber plays (--fast), until the reference ends
        player_env = {"ESIAF_PLAYER_INPUT": str(args.playback), "ESIAF_PLAYER_FOLLOW_STREAM": "true",
                      "ESIAF_PLAYER_OUTPUT": str(supervisor.workdir / "loudspeaker.wav"),
                      "ESIAF_PLAYER_WAIT_TIMEOUT_S": str(10 * START_TIMEOUT_S),
                      "ESIAF_PLAYER_FAST": "true" if args.fast else "false"}
        transcript = args.playback.with_suffix(".json")  # what the robot says in it: fusion tells its voice by it
        if transcript.is_file():
            player_env["ESIAF_PLAYER_TRANSCRIPT"] = str(transcript)
        aec_env |= {"ESIAF_AEC_EXPECT_REFERENCE": "true", "ESIAF_AEC_HOLD_MS": str(10 * START_TIMEOUT_S * 1000)}
    else:
        player_env = {"ESIAF_PLAYER_DEVICE": args.player}
    services["aec"] = supervisor.start("aec", env=aec_env)
    services["player"] = supervisor.start("player", env=player_env)
    return "aec/audio"


def check_vad_in_grabber(args: argparse.Namespace, channels: int, array: ArrayGeometry | None,
                         replicas: dict[str, int]) -> None:
    """--vad-in-grabber (esiaf/hosting.py) is possible where the vad hears the grabber's audio itself (one
    mono input: no splitter or beamformer in between), one grabber feeds it, and no replicas wait for the
    streams before the grabbers start (reserve_streams)."""
    why = ("the input has several channels (the vad hears a splitter's or beamformer's output)"
           if channels > 1 or array is not None else
           "several inputs play at once (one vad hears them all)" if args.input and len(args.input) > 1 else
           "--replicas wait for the streams before the grabber starts" if replicas else "")
    if why:
        raise LaunchError(f"--vad-in-grabber: not possible here: {why}")


def hosted_labellers(labellers: list[str], replicas: dict[str, int], apart: bool) -> dict[str, list[str]]:
    """Which labellers host which others in their process: gender in emotion's, as both classify the
    same openSMILE features of each utterance (computed once so); none with --apart, or when either
    runs as several instances (a guest is not scaled apart from its host)."""
    if apart or not {"emotion", "gender"} <= set(labellers) or {"emotion", "gender"} & set(replicas):
        return {}
    return {"emotion": ["gender"]}


def start_replicas(supervisor: Supervisor, name: str, count: int, args: Sequence[str] = (),
                   target: list[str] | None = None, env: dict[str, str] | None = None) -> dict[str, Child]:
    """One instance of a service or plug-in (``target``), under its name, or ``count`` sharing the
    streams: name-1, name-2, ..."""
    if count == 1:
        return {name: supervisor.start(name, args, env=env, target=target)}
    return {f"{name}-{n}": supervisor.start(name, args, env=env, target=target, instance=f"{name}-{n}")
            for n in range(1, count + 1)}


def wait_for_registration(client: OrchestratorClient, supervisor: Supervisor, services: dict[str, Child],
                          plugins: dict[str, Child]) -> dict[str, dict]:
    """Waits until every service and plug-in has registered; adds the plug-ins' result kinds to the
    fusion. Returns each plug-in instance's registration."""
    for name, child in services.items():
        find = client.component if name in known_services() else client.instance  # asr, or asr-1 of --replicas
        wait_until(functools.partial(find, name), supervisor, f"the {name} service to register",
                   START_TIMEOUT_S, child)
    registered = {name: wait_until(functools.partial(client.by_pid, child.process.pid), supervisor,
                                   f"{name} (--with) to register", START_TIMEOUT_S, child)
                  for name, child in plugins.items()}
    kinds = dict.fromkeys(component["kind"] for component in registered.values())  # in order, once
    fuse_kinds(client, [kind for kind in kinds if kind != "other"])
    return registered


def wait_for_subscriptions(client: OrchestratorClient, supervisor: Supervisor, pipeline: Pipeline,
                           on_speech: int) -> None:
    """Waits until each topic between the grabber and the analysers has its consumers (``on_speech``:
    the plug-ins on vad/speech), so no audio is played before anyone hears it; a grabber hosting the
    vad is told to wait for the vad's consumers itself (they subscribe once it has registered)."""
    services = pipeline.services
    if "aec" in services:
        wait_until(lambda: topic_ready(client, pipeline.microphones, pipeline.microphone_consumers), supervisor,
                   f"the first services to subscribe to {pipeline.microphones}", START_TIMEOUT_S, services["aec"])
    if "splitter" in services:
        wait_until(lambda: topic_ready(client, "splitter/ch0", 1), supervisor,
                   "vad to subscribe to splitter/ch0", START_TIMEOUT_S, services["vad"])
    if pipeline.beamforming:
        wait_until(lambda: topic_ready(client, "ssl/audio", 1), supervisor,
                   "the beamformer to subscribe to ssl/audio", START_TIMEOUT_S, services["beamformer"])
        wait_until(lambda: topic_ready(client, "beamformer/audio", 1), supervisor,
                   "vad to subscribe to beamformer/audio", START_TIMEOUT_S, services["vad"])
    if "denoiser" in pipeline.inputs:  # those that hear the denoiser (not replicas: they take streams later)
        hearing = subscribers_of(pipeline, "denoiser/speech")
        if hearing:
            wait_until(lambda: topic_ready(client, "denoiser/speech", len(hearing)), supervisor,
                       f"{', '.join(hearing)} to subscribe to denoiser/speech", START_TIMEOUT_S,
                       services["denoiser"])
    # replicas subscribe to a stream's audio once they are given the stream: here, only the others count
    waited = subscribers_of(pipeline, "vad/speech")
    subscribers = len(waited)
    if pipeline.vad_in_grabber:  # the vad registers with the grabber: the grabber waits for them before playing
        pipeline.grabber_env["ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS"] = str(subscribers + on_speech)
        return
    wait_until(lambda: topic_ready(client, "vad/speech", subscribers + on_speech), supervisor,
               f"{', '.join(waited) or 'the plug-ins'} to subscribe to vad/speech", START_TIMEOUT_S, services["vad"])


def subscribers_of(pipeline: Pipeline, topic: str) -> list[str]:
    """The services that subscribe to ``topic`` once each, as they start: neither replicas (they subscribe
    once they take a stream) nor guests (their host subscribes for them)."""
    return [name for name, heard in heard_topics(pipeline) if heard == topic and name in pipeline.services
            and name not in pipeline.replicas and name not in pipeline.guests]


def heard_topics(pipeline: Pipeline) -> list[tuple[str, str]]:
    """Each service on the vad's output and a topic it hears: its input, and the asr's second opinion's."""
    return [*pipeline.inputs.items(), *([("asr", pipeline.second_opinion_topic)] if pipeline.second_opinion_topic
                                        else [])]


def reserve_streams(client: OrchestratorClient, supervisor: Supervisor, pipeline: Pipeline, ids: list[str],
                    on_speech: list[str]) -> None:
    """With --replicas: announces the streams before their grabbers play and waits until an instance of
    each replicated service has taken each stream (subscribed to its speech). A grabber announces its
    stream only as it starts playing; a replica told of it then could miss its first utterance."""
    for stream_id in ids:
        client.announce(stream_id, {"announced_by": "esiaf run", "before": "its grabber"})
    # a replicated service subscribes once per stream (each instance to its own streams); any other, once; a
    # guest not at all (its host subscribes for it)
    for topic, producer in (("vad/speech", "vad"), ("denoiser/speech", "denoiser")):
        hearing = Counter([name for name, heard in heard_topics(pipeline) if heard == topic
                           and (name in pipeline.services or name in pipeline.replicas)
                           and name not in pipeline.guests] + (list(on_speech) if topic == "vad/speech" else []))
        subscriptions = sum(len(ids) if name in pipeline.replicas else count for name, count in hearing.items())
        if subscriptions and producer in pipeline.services:
            wait_until(functools.partial(topic_ready, client, topic, subscriptions), supervisor,
                       f"the instances of {', '.join(pipeline.replicas)} to take the streams", START_TIMEOUT_S,
                       pipeline.services[producer])


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
