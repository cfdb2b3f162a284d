"""``esiaf run``'s command line: its arguments, and the checks made before anything starts
(every value's range, the workdir, the token, the input files and folders, each stream's id, the
microphone array, --without, the orchestrator's port). A bad value is one line and exit 2
(:class:`LaunchError`); this module imports nothing heavy, so that it says so at once."""
from __future__ import annotations

import argparse
import math
import os
import re
import socket
from collections.abc import Iterable, Mapping, Sequence
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from esiaf.argparsing import OneLineParser
from esiaf.printable import MAX_NAME_CHARS, name_problem
from esiaf.tools.errors import LaunchError
from esiaf.tools.terminal import err

if TYPE_CHECKING:
    from esiaf.arrays import ArrayGeometry

ANALYSERS = ("ssl", "emotion", "gender", "voiceid")  # what --without can leave out (the recogniser anchors every line)
ON_SPEECH = ("asr", "emotion", "gender", "voiceid")  # the analysers on the VAD's output: what --replicas can scale
MAX_REPLICAS = 8
MIN_RATE_HZ, MAX_RATE_HZ = 8_000, 192_000  # the rates the components take (esiaf/receiving.py, not imported: heavy)
MAX_CHUNK_MS = 10_000.0  # a component takes at most 10 s of audio per message
MIN_CHUNK_MS = 1.0


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
    from esiaf.tools.mcap_replay import SessionError, check_session, is_mcap
    if is_mcap(path):  # a recording (esiaf run --record): its audio is replayed
        try:
            fmt = check_session(path).format
        except SessionError as exc:
            raise LaunchError(str(exc)) from None
        if not MIN_RATE_HZ <= fmt.sample_rate_hz <= MAX_RATE_HZ:
            raise LaunchError(f"input file {path}: its audio is {fmt.sample_rate_hz} Hz; the analysers take "
                              f"{MIN_RATE_HZ} to {MAX_RATE_HZ} Hz")
        return fmt.channels
    import soundfile
    try:
        info = soundfile.info(str(path))
    except Exception as exc:  # libsndfile's own error types vary by version
        raise LaunchError(f"cannot read input file {path}: {exc}") from None
    if info.frames == 0:
        raise LaunchError(f"input file {path} holds no audio")
    if not MIN_RATE_HZ <= info.samplerate <= MAX_RATE_HZ:
        raise LaunchError(f"input file {path}: its header says {info.samplerate} Hz; the analysers take "
                          f"{MIN_RATE_HZ} to {MAX_RATE_HZ} Hz")
    if info.channels < 1:
        raise LaunchError(f"input file {path}: its header says {info.channels} channels")
    return info.channels


def sound_suffixes() -> set[str]:
    """The file name endings --input FOLDER plays: what libsndfile reads, headerless .raw/.pcm, and recordings."""
    import soundfile
    return {f".{name.lower()}" for name in soundfile.available_formats()} | {".aif", ".oga", ".raw", ".pcm", ".mcap"}


def expand_inputs(paths: Sequence[Path]) -> list[Path]:
    """Each --input as the files it plays: a file itself, a folder every sound file in it (sorted by
    name, not descending into subfolders). A missing input, an empty folder or one without a sound
    file is an error."""
    files: list[Path] = []
    for path in paths:
        if not path.is_dir():
            if not path.exists():
                raise LaunchError(f"input file {path} does not exist")
            files.append(path)
            continue
        entries = sorted(entry for entry in path.iterdir() if not entry.name.startswith("."))
        if not entries:
            raise LaunchError(f"input folder {path} is empty")
        suffixes = sound_suffixes()
        sounds = [entry for entry in entries if entry.is_file() and entry.suffix.lower() in suffixes]
        if not sounds:
            raise LaunchError(f"input folder {path} holds no sound file (none of its {len(entries)} entries ends "
                              f"in {', '.join(sorted(suffixes))})")
        files.extend(sounds)
    return files


def check_inputs(paths: Sequence[Path]) -> int:
    """Checks every input file; returns their channel count, which all must share (one pipeline hears them)."""
    channels = {path: check_input(path) for path in paths}
    if len(set(channels.values())) > 1:
        counts = ", ".join(f"{path} {count}" for path, count in channels.items())
        raise LaunchError(f"the inputs are played through one pipeline: give files of one channel count, "
                          f"not {counts}")
    return next(iter(channels.values()))


def replayed_streams(paths: Sequence[Path], channels: int) -> tuple[list[Path], list[str]]:
    """Each input once per stream it plays: a recording (.mcap) once per recorded stream, each a stream
    of its own; any other file once. Returns the inputs and, beside each, the recorded stream it plays
    ("" for a file that is no recording). Every recorded stream must have the inputs' ``channels``."""
    from esiaf.tools.mcap_replay import SessionError, check_session, is_mcap, recorded_streams
    inputs: list[Path] = []
    recorded: list[str] = []
    for path in paths:
        if not is_mcap(path):
            inputs.append(path)
            recorded.append("")
            continue
        try:
            streams = recorded_streams(path)
            for stream_id in streams:
                fmt = check_session(path, stream_id).format
                if fmt.channels != channels:
                    raise LaunchError(f"input file {path}: its stream {stream_id} has {fmt.channels} channel(s), "
                                      f"the other inputs {channels}: the inputs are played through one pipeline")
        except SessionError as exc:
            raise LaunchError(str(exc)) from None
        inputs.extend([path] * len(streams))
        recorded.extend(streams)
    return inputs, recorded


def source_name(path: Path, recorded_stream: str) -> str:
    """What a stream played from ``path`` is named after: the file's stem; a recording's stream among
    several, its recorded id (without the time stamp esiaf run gave it)."""
    from esiaf.tools.mcap_replay import recorded_streams, stream_name
    if not recorded_stream or len(recorded_streams(path)) <= 1:
        return path.stem
    return stream_name(recorded_stream)


def stream_ids(sources: Sequence[str], given: str | None, now: datetime | None = None) -> list[str]:
    """The stream id of each input (its file's stem, or 'mic', and the run's start time); ``given``
    (--stream-id) names the stream of a single input only."""
    if given is not None:
        check_name(given, "--stream-id")
    if given and len(sources) > 1:
        raise LaunchError(f"--stream-id names the stream of a single input, not of {len(sources)}: without it "
                          f"each stream is named after its file and the run's start time")
    if given:
        return [given]
    when = (now or datetime.now()).strftime("%Y%m%d-%H%M%S")
    if len(sources) == 1:
        return [f"{sources[0]}-{when}"]
    ids: list[str] = []
    for source in sources:  # several: ids safe in a URL query, the same stem twice made unique
        base = re.sub(r"[^A-Za-z0-9_.-]+", "_", source).strip("_.-") or "input"
        stream_id, n = f"{base}-{when}", 1
        while stream_id in ids:
            n += 1
            stream_id = f"{base}-{n}-{when}"
        ids.append(stream_id)
    return ids


def check_echo(args: argparse.Namespace) -> None:
    """--player and --playback: a player and the echo canceller in front of the analysers."""
    if args.vad_in_grabber and (args.player is not None or args.playback is not None):
        raise LaunchError("--vad-in-grabber: not possible with --player or --playback (the vad hears the echo "
                          "canceller, not the grabber)")
    if args.playback is None:
        return
    if args.player is not None:
        raise LaunchError("give --player (a live loudspeaker) or --playback (a recorded robot voice), not both")
    if not args.input or len(args.input) != 1:
        raise LaunchError("--playback plays the robot's voice on the timeline of one --input file: give one")
    if check_input(args.playback) != 1:
        raise LaunchError(f"--playback {args.playback}: the robot's voice is one channel (what its loudspeaker played)")


def check_name(name: str, what: str) -> str:
    """A name the run gives (a stream id), by the one rule for names (esiaf/printable.py)."""
    problem = name_problem(name, MAX_NAME_CHARS)
    if problem is not None:
        raise LaunchError(f"{what} {problem}")
    return name


def check_workdir(path: Path) -> Path:
    """The workdir as an absolute path, checked without making it (nothing is written before every
    argument has been checked; the launcher makes it): one that is not a folder, or that cannot be
    made or written, is a LaunchError."""
    if "\0" in str(path):
        raise LaunchError(f"--workdir {str(path)!r} holds a NUL character")
    path = path.absolute()
    if path.exists() and not path.is_dir():
        raise LaunchError(f"--workdir {path} is not a folder")
    existing = path
    while not existing.exists():  # the nearest folder that is there: it must let the rest be made
        existing = existing.parent
    if not existing.is_dir():
        raise LaunchError(f"--workdir {path} cannot be made: {existing} is not a folder")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise LaunchError(f"--workdir {path} cannot be {'written' if existing == path else 'made'}")
    return path


def check_token() -> None:
    """The token the services are to present, if one is given (ESIAF_TOKEN, ESIAF_TOKEN_FILE), can be used."""
    from esiaf.auth import TokenError, token
    try:
        token()
    except TokenError as exc:
        raise LaunchError(str(exc)) from None


def check_settings(env: Mapping[str, str], services: Iterable[str] = ()) -> None:
    """The settings every component has as the environment gives them, for all (``ESIAF_MAX_STREAMS``;
    with no ``services``, these alone) or for one service (``ESIAF_VAD_MAX_STREAMS``), each service's
    own settings the environment gives (``ESIAF_VAD_BACKEND``, ``ESIAF_VAD_CONFIG``: checked by its
    settings model, loaded without starting it), and with services the orchestrator's: all checked
    before anything starts, so a bad value is one line at once rather than once that service starts."""
    from esiaf.services import service_settings
    from esiaf.settings import ComponentSettings, SettingsError, load_settings
    common = {name.upper() for name in ComponentSettings.model_fields}
    try:
        for service in sorted(set(services) - {"orchestrator"}) or ["common"]:
            prefix = f"ESIAF_{service.upper()}_"
            given = {key: value for key, value in env.items() if key.startswith("ESIAF_")
                     and (key[len("ESIAF_"):] in common or (key.startswith(prefix) and key[len(prefix):] in common))}
            load_settings(ComponentSettings, service, env=given)
            if any(key.startswith(prefix) and key[len(prefix):] not in common for key in env):
                model = service_settings(service)
                own = {key: value for key, value in env.items() if key.startswith(prefix)}
                if model is not None:  # esiaf run may still choose the backend: only the values are checked
                    load_settings(model, service, env={**given, **own}, check_backend=False)
        if services:
            from esiaf_services.orchestrator.settings import load as orchestrator_settings
            orchestrator_settings(env=env)
    except SettingsError as exc:
        raise LaunchError(str(exc)) from None


def resolve_paths(args: argparse.Namespace) -> None:
    """The grammar and array files as absolute paths: the services run elsewhere, relative ones would break."""
    if args.grammar and args.grammar != "robocup":
        if not Path(args.grammar).is_file():
            raise LaunchError(f"grammar file {args.grammar} does not exist")
        args.grammar = str(Path(args.grammar).resolve())
    if args.array and Path(args.array).is_file():
        args.array = str(Path(args.array).resolve())


def check_recording(args: argparse.Namespace) -> None:
    """--record and --diff: a file whose folder is there, limits that are limits, one recording to diff."""
    if args.record is not None:
        if args.record.is_dir() or not args.record.absolute().parent.is_dir():
            raise LaunchError(f"--record {args.record}: give a file in a folder that exists")
        if args.record.is_file():
            raise LaunchError(f"--record {args.record} exists: give another name, or remove it")
        if args.vad_in_grabber:
            raise LaunchError("--record: not possible with --vad-in-grabber (the grabber waits for the vad's "
                              "consumers, not for the recorder)")
        args.record = args.record.absolute()
    elif args.record_max_mb or args.record_max_s or args.record_topics:
        raise LaunchError("--record-max-mb, --record-max-s and --record-topics bound a recording: give --record too")
    if args.record_max_mb < 0 or args.record_max_s < 0:
        raise LaunchError("--record-max-mb and --record-max-s take a positive limit (0: none)")
    if args.diff:
        from esiaf.tools.mcap_replay import is_mcap
        if not args.input or len(args.input) != 1 or not is_mcap(args.input[0]):
            raise LaunchError("--diff compares a replay with its recording: give one --input FILE.mcap")


def check_values(args: argparse.Namespace) -> None:
    """What the command line asks for that can be checked before the pipeline's modules are imported."""
    if args.stream_id is not None:
        check_name(args.stream_id, "--stream-id")
    if not args.host.strip():
        raise LaunchError("--host must not be empty (default 127.0.0.1)")
    args.workdir = check_workdir(args.workdir)
    check_token()
    check_settings(os.environ)
    parse_without(args.without)
    resolve_paths(args)
    check_recording(args)
    if args.input:
        args.input = expand_inputs(args.input)
        check_inputs(args.input)


def check_array(args: argparse.Namespace, channels: int) -> tuple[ArrayGeometry | None, int]:
    """The array geometry and the audio's channel count (None, channels for mono without --array)."""
    from esiaf.arrays import ArrayError, load_array
    mic_channels = parse_channels(args.mic_channels)
    if args.array is None:
        if mic_channels or args.channels:
            raise LaunchError("--mic-channels and --channels describe a microphone array: give --array too")
        if channels > 1:
            inputs = " ".join(map(str, args.input))
            err(f"esiaf: {inputs} {'has' if len(args.input) == 1 else 'have'} {channels} channels and no "
                f"--array: the analysers hear channel 0 (name the microphone array with --array, e.g. "
                f"respeaker4, to localise the speakers too)")
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


def parse_replicas(texts: Sequence[str], without: set[str], plugins: Sequence[str] = ()) -> dict[str, int]:
    """``--replicas SERVICE=N`` (repeatable): how many instances of each analyser on the VAD's output,
    or plug-in (``--with``), to start; each must be one this run starts."""
    started = [*(name for name in ON_SPEECH if name not in without), *plugins]
    replicas: dict[str, int] = {}
    for text in texts:
        name, _, count = text.partition("=")
        name = name.strip()
        if not count.strip().isdigit() or not 1 <= int(count) <= MAX_REPLICAS:
            raise LaunchError(f"--replicas takes SERVICE=N with N from 1 to {MAX_REPLICAS} (e.g. asr=2), not {text!r}")
        if name not in started:
            raise LaunchError(f"--replicas {text}: {name or 'no service'} is not an analyser this run starts on the "
                              f"VAD's output or a plug-in ({', '.join(started)})")
        replicas[name] = int(count)
    return replicas


def check_port_free(host: str, port: int, host_option: str = "--host",
                    in_use: str = "another orchestrator running? use --port") -> None:
    """``host:port`` can be listened on; else a LaunchError naming the option to change (``host_option``)
    and what to do when the port is taken (``in_use``)."""
    with socket.socket() as probe:
        # as the orchestrator will (uvicorn): connections of an earlier run in TIME_WAIT do not count
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
        except socket.gaierror as exc:
            raise LaunchError(f"cannot listen on {host}:{port}: {exc.strerror} (check {host_option})") from None
        except OSError as exc:
            raise LaunchError(f"cannot listen on {host}:{port}: {exc.strerror} ({in_use})") from None
        except (ValueError, UnicodeError) as exc:  # a NUL or an unencodable name
            raise LaunchError(f"cannot listen on {host!r}: {exc} (check {host_option})") from None


def port_number(text: str) -> int:
    """--port: a TCP port a client can reach, 1 to 65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a port is a whole number from 1 to 65535, not {text!r}") from None
    if not 1 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is a whole number from 1 to 65535, not {text}")
    return port


def chunk_ms(text: str) -> float:
    """--chunk-ms: a finite length from MIN_CHUNK_MS to MAX_CHUNK_MS."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not MIN_CHUNK_MS <= value <= MAX_CHUNK_MS:  # nan and the infinities too
        raise argparse.ArgumentTypeError(f"a chunk length in ms from {MIN_CHUNK_MS:g} to {MAX_CHUNK_MS:g}, "
                                         f"not {text!r}")
    return value


def channel_count(text: str) -> int:
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= 64:
        raise argparse.ArgumentTypeError(f"a channel count from 1 to 64, not {text!r}")
    return count


def language_code(text: str) -> str:
    """--language: a language tag as Home Assistant gives them (en, en-US, de_DE)."""
    if not re.fullmatch(r"[A-Za-z]{2,3}([-_][A-Za-z0-9]{2,8})*", text):
        raise argparse.ArgumentTypeError(f"a language code such as en or en-US, not {text!r}")
    return text


def add_recogniser_options(parser: argparse.ArgumentParser) -> None:
    """What the pipeline recognises with: esiaf run's and esiaf wyoming's."""
    parser.add_argument("--grammar", help="JSGF grammar file for the recogniser, or 'robocup' (with --asr whisper: "
                        "the allowed sentences its transcripts are matched to)")
    parser.add_argument("--vad", choices=("silero", "energy"), help="the voice activity detector: silero (default, "
                        "a neural VAD that babble does not fool) or energy (the original double threshold)")
    parser.add_argument("--asr", choices=("pocketsphinx", "whisper"), help="the recogniser (default pocketsphinx)")
    parser.add_argument("--denoiser", choices=("auto", "on", "off"), default="auto", help="the recogniser and voiceid "
                        "hear the VAD's utterances through the denoiser (DeepFilterNet 3): auto (default) voiceid and "
                        "pocketsphinx, which it helps in noise, not Whisper, which it does not; on: Whisper too; off: "
                        "none (docs/benchmarks.md)")


def add_workdir_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--workdir", type=Path, default=Path(".esiaf"), help="logs and database (default .esiaf)")
    parser.add_argument("--recover", action="store_true", help="if the workdir's database is corrupt, start on a "
                        "copy of what can still be read (the orchestrator's log says what was lost; the damaged file "
                        "is kept)")


def add_wyoming_parser(sub: argparse._SubParsersAction) -> None:
    """``esiaf wyoming``: the pipeline behind a Wyoming speech-to-text server (docs/wyoming.md)."""
    wyoming = sub.add_parser("wyoming", help="serve the pipeline as a Wyoming speech-to-text server (Home "
                             "Assistant): esiaf wyoming --port 10300")
    wyoming.add_argument("--port", dest="wyoming_port", type=port_number, default=10300,
                         help="the Wyoming server's TCP port (default 10300)")
    wyoming.add_argument("--listen", default="127.0.0.1", help="the address the Wyoming server listens on (default "
                         "127.0.0.1; 0.0.0.0: every interface, for Home Assistant on another host)")
    wyoming.add_argument("--language", action="append", type=language_code, metavar="CODE",
                         help="a language the recogniser takes, as describe lists it (default en); repeatable")
    add_recogniser_options(wyoming)
    wyoming.add_argument("--without", metavar="ANALYSERS", help="analysers to leave out, separated by commas: "
                         "emotion, gender, voiceid (the transcript is the recogniser's; they only cost CPU here)")
    wyoming.add_argument("--apart", action="store_true", help="run emotion and gender each in a process of its own")
    wyoming.add_argument("--host", default="127.0.0.1", help="orchestrator address (default 127.0.0.1)")
    wyoming.add_argument("--http-port", dest="port", type=port_number, default=8000,
                         help="orchestrator HTTP port (default 8000)")
    add_workdir_options(wyoming)
    wyoming.add_argument("-v", "--verbose", action="store_true", help="log what the launcher does")
    # what esiaf run's pipeline code reads and esiaf wyoming does not offer: one mono source, no grabber
    wyoming.set_defaults(input=None, mic=None, array=None, mic_channels=None, channels=None, replicas=[],
                         vad_in_grabber=False, plugins=[], no_beamformer=False, beamformer=None,
                         ssl_algorithm=None,
                         fast=False, player=None, playback=None, serve=True, stream_id=None, chunk_ms=None,
                         json=False, partials=False, include_robot=False, ros2=False, record=None,
                         record_topics=None, record_max_mb=0.0, record_max_s=0.0, diff=False,
                         source_topic="wyoming/audio")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = OneLineParser(prog="esiaf", description="ESIAF speech-analysis pipeline")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    run = sub.add_parser("run", help="run every service as a local process")
    source = run.add_mutually_exclusive_group(required=True)
    source.add_argument("--input", type=Path, action="append", help="sound file to play (WAV/FLAC/... of any "
                        "rate and sample type, or .raw: 16 kHz s16le mono; or an .mcap recording: its audio), or a "
                        "folder: each sound file in it; "
                        "repeatable: every file is played at once, each as a stream of its own")
    source.add_argument("--mic", metavar="DEVICE", help="ALSA capture device (see arecord -L)")
    run.add_argument("--array", help="microphone array of a multi-channel input or --mic: pepper4, respeaker4, "
                     "circular:MICS:RADIUS_M or a YAML file; starts sound source localisation")
    run.add_argument("--mic-channels", help="with --array: the channels that are the microphones, in the array's "
                     "order, where the audio has others too (ReSpeaker 6-channel firmware: 1,2,3,4)")
    run.add_argument("--channels", type=channel_count, help="with --mic and --array: channels to capture "
                     "(default: as the microphones need)")
    run.add_argument("--without", metavar="ANALYSERS", help="analysers to leave out, separated by commas: "
                     "emotion, gender, voiceid, ssl (e.g. --without emotion,gender on a slow robot)")
    run.add_argument("--replicas", action="append", default=[], metavar="SERVICE=N", help="start N instances "
                     f"(1 to {MAX_REPLICAS}) of an analyser on the VAD's output ({', '.join(ON_SPEECH)}) or of a "
                     "--with plug-in, named SERVICE-1 ... SERVICE-N, that share the streams; repeatable (e.g. "
                     "--replicas asr=2)")
    run.add_argument("--apart", action="store_true", help="run emotion and gender each in a process of its own "
                     "(default: gender is a guest in emotion's process, and each utterance's features are computed "
                     "once for both)")
    run.add_argument("--vad-in-grabber", action="store_true", help="run the vad in the grabber's process (one mono "
                     "input): no ZeroMQ hop per chunk between them, less CPU; the vad then hears only this grabber "
                     "and ends with it, so grabbers that join later (--serve) are not heard")
    run.add_argument("--with", dest="plugins", action="append", default=[], metavar="FOLDER_OR_NAME",
                     help="also run your own analyser: a folder with a __main__.py, an installed component "
                     "(entry point group esiaf.components) or a module; repeatable")
    run.add_argument("--no-beamformer", action="store_true", help="with --array: the analysers hear the first "
                     "microphone instead of the array steered at the talker")
    run.add_argument("--beamformer", choices=("mvdr", "das"), help="with --array: the beamforming method "
                     "(default mvdr; das: delay and sum)")
    run.add_argument("--ssl-algorithm", help="DOA algorithm of the ssl service (default NormMUSIC)")
    run.add_argument("--fast", action="store_true", help="play the file as fast as possible")
    run.add_argument("--player", nargs="?", const="default", metavar="DEVICE", help="the robot speaks through the "
                     "player (an ALSA playback device, default: default) and the echo canceller takes its voice out "
                     "of the microphones before anything hears them")
    run.add_argument("--playback", type=Path, metavar="ROBOT.wav", help="with one --input: what the robot said, on "
                     "the input's timeline: the player plays it in step with the input (to loudspeaker.wav in the "
                     "workdir) and the echo canceller takes it out of the microphones; ROBOT.json beside it, a list of "
                     "{start_s, text}, says what the robot says (fusion tells the robot's voice from a person's by it)")
    add_recogniser_options(run)
    run.add_argument("--serve", action="store_true", help="keep the services up after the files have played, "
                     "until Ctrl-C or SIGTERM")
    run.add_argument("--host", default="127.0.0.1", help="orchestrator address (default 127.0.0.1)")
    run.add_argument("--port", type=port_number, default=8000, help="orchestrator HTTP port (default 8000)")
    add_workdir_options(run)
    run.add_argument("--stream-id", help="name of this capture session (default: input name + time); "
                     "with a single input only")
    run.add_argument("--chunk-ms", type=chunk_ms, help="grabber chunk length in ms (default: the grabber's chunk_ms, "
                     "50 ms; see docs/benchmarks.md)")
    run.add_argument("--ros2", action="store_true", help="publish the voices as ROS 2 topics (REP-155, hri_msgs) "
                     "over DDS: the ros2 service (docs/ros2.md; ROS_DOMAIN_ID honoured)")
    run.add_argument("--record", type=Path, metavar="FILE.mcap", help="record the run to MCAP: the audio, every "
                     "result, the fused results and partials (docs/recording.md); replay it with --input FILE.mcap")
    run.add_argument("--record-topics", metavar="TOPICS", help="with --record: the audio topics to record, "
                     "separated by commas (default grabber/audio)")
    run.add_argument("--record-max-mb", type=float, default=0.0, metavar="MB", help="with --record: a new file "
                     "(FILE-2.mcap, ...) once one is this large")
    run.add_argument("--record-max-s", type=float, default=0.0, metavar="S", help="with --record: a new file once "
                     "one has been written this long")
    run.add_argument("--diff", action="store_true", help="with --input FILE.mcap: print how the replay's fused "
                     "results differ from the recorded ones (text, direction, voice per utterance)")
    run.add_argument("--json", action="store_true", help="print each fused result as JSON, and each barge_in event "
                     "(a person starting to speak while the robot plays)")
    run.add_argument("--partials", action="store_true", help="with --json: print the recognisers' partial "
                     "results too (on a terminal they are shown anyway, as one line rewritten in place)")
    run.add_argument("--include-robot", action="store_true", help="also print the robot's own voice heard back "
                     "(fused results with source robot, left out by default)")
    run.set_defaults(source_topic="grabber/audio")  # what the first services hear (esiaf wyoming: its own)
    run.add_argument("-v", "--verbose", action="store_true", help="log what the launcher does")
    add_wyoming_parser(sub)
    sub.add_parser("eval", help="evaluation harnesses through the real pipeline: esiaf eval robocup --help")
    sub.add_parser("keys", help="CURVE key pairs for ZeroMQ across hosts: esiaf keys DIR --help")
    sub.add_parser("record", help="record a running pipeline to MCAP: esiaf record --help")
    sub.add_parser("mcap", help="compare recordings: esiaf mcap diff RECORDED.mcap REPLAYED.mcap")
    return parser.parse_args(argv)
