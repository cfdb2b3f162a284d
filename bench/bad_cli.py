"""Bad values given to ``esiaf run``, ``esiaf wyoming`` and to the services: how each is answered.

    python -m bench.bad_cli [--repo DIR] [--only SUBSTRING] [--port 18690]

Runs every case of CASES (a bad option, setting or input file) as a process and prints one row per
case: its exit code, the lines it wrote on stderr, whether a traceback was among them, and its wall
and CPU seconds; then the totals: cases that did not exit 2, that wrote more than one line, that
wrote a traceback, that took longer than 2 s (wall clock, and CPU time: on a shared machine the wall
clock says more about the other processes), that waited longer than 20 s. ``--repo``: the checkout
that runs (a worktree of main: the code before a change). tests/test_bad_cli.py runs the same cases.
"""
from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if __name__ == "__main__":
    sys.path[0] = str(REPO)  # the repository first: esiaf from this checkout

import argparse  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import struct  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402

WAV = str(REPO / "examples" / "robocup_questions.wav")
TIMEOUT_S = 90.0  # a case that waits longer is stopped and counted as slow


@dataclass
class Case:
    name: str
    args: list[str]  # after `esiaf run` (or the service's command line)
    env: dict[str, str] = field(default_factory=dict)
    command: str = "run"  # "run": esiaf run; "wyoming": esiaf wyoming; else python -m esiaf_services.<command>


def wav_header(rate_hz: int, channels: int = 1, bits: int = 16, samples: int = 444) -> bytes:
    """A WAV file of ``samples`` zero frames, whose header says ``rate_hz``, ``channels`` and ``bits``."""
    data = bytes(samples * max(channels, 1) * max(bits // 8, 1))
    fmt = struct.pack("<HHIIHH", 1, channels, rate_hz, rate_hz * channels * bits // 8, channels * bits // 8, bits)
    return (b"RIFF" + struct.pack("<I", 36 + len(data)) + b"WAVEfmt " + struct.pack("<I", 16) + fmt
            + b"data" + struct.pack("<I", len(data)) + data)


def port_cases() -> list[Case]:
    return [Case(f"--port {port}", ["--input", WAV, "--port", port]) for port in
            ("-1", "70000", "0", "65536", "abc", "1.5", "", "99999999999999999999")]


def chunk_cases() -> list[Case]:
    return [Case(f"--chunk-ms {value}", ["--input", WAV, "--chunk-ms", value]) for value in
            ("nan", "inf", "-inf", "-5", "0", "100000000", "abc", "1e400", "0.001")]


def workdir_cases() -> list[Case]:
    return [Case("--workdir a file", ["--input", WAV, "--workdir", "{file}"]),
            Case("--workdir under a file", ["--input", WAV, "--workdir", "{file}/sub"]),
            Case("--workdir in /proc", ["--input", WAV, "--workdir", "/proc/esiaf"]),
            Case("--workdir in /sys", ["--input", WAV, "--workdir", "/sys/esiaf/x"]),
            Case("--workdir under /dev/null", ["--input", WAV, "--workdir", "/dev/null/esiaf"])]


def token_cases() -> list[Case]:
    return [Case("ESIAF_TOKEN_FILE missing", ["--input", WAV], {"ESIAF_TOKEN_FILE": "{tmp}/no-token"}),
            Case("ESIAF_TOKEN_FILE a folder", ["--input", WAV], {"ESIAF_TOKEN_FILE": "{tmp}"}),
            Case("ESIAF_TOKEN_FILE empty", ["--input", WAV], {"ESIAF_TOKEN_FILE": "{empty}"}),
            Case("ESIAF_TOKEN a newline", ["--input", WAV], {"ESIAF_TOKEN": "a\nb"})]


def setting_cases() -> list[Case]:
    values = {"ESIAF_MAX_STREAMS": ("0", "-1", "abc", "nan"), "ESIAF_VAD_MAX_STREAMS": ("0",),
              "ESIAF_AUDIO_QUEUE": ("0", "x"), "ESIAF_LOG_LEVEL": ("LOUD",), "ESIAF_REGISTER_TIMEOUT_S": ("nan",)}
    # settings of one service only, checked by its settings model before anything starts
    own = {"ESIAF_VAD_BACKEND": "nope", "ESIAF_GRABBER_CHUNK_MS": "nan", "ESIAF_VAD_SILERO__THRESHOLD": "high",
           "ESIAF_ASR_WHISPER__BEAM_SIZE": "0.5"}
    return [*(Case(f"{name}={value}", ["--input", WAV], {name: value})
              for name, values_of in values.items() for value in values_of),
            *(Case(f"{name}={value}", ["--input", WAV], {name: value}) for name, value in own.items())]


def vocabulary_cases() -> list[Case]:
    """The asr's vocabulary file (asr/vocabulary.py: at most 1,000 entries and 64 KiB)."""
    files = {"missing": "{tmp}/no-vocabulary.txt", "a folder": "{tmp}", "empty": "{empty}",
             "of 100,000 lines": "{hugevocab}", "not UTF-8": "{latin1}"}
    return [*(Case(f"ESIAF_ASR_VOCABULARY {what}", ["--input", WAV], {"ESIAF_ASR_VOCABULARY": path})
              for what, path in files.items()),
            Case("asr ESIAF_ASR_VOCABULARY of 100,000 lines", [], {"ESIAF_ASR_VOCABULARY": "{hugevocab}"},
                 command="asr")]


def input_cases() -> list[Case]:
    return [Case("a 1 Hz WAV", ["--input", "{wav1hz}"]),
            Case("a 1,000,003 Hz WAV", ["--input", "{wav1mhz}"]),
            Case("a 4 kHz WAV", ["--input", "{wav4k}"]),
            Case("a WAV of 0 channels", ["--input", "{wav0ch}"]),
            Case("a WAV of 0 bits", ["--input", "{wav0bit}"]),
            Case("a truncated WAV header", ["--input", "{wavcut}"]),
            Case("an input that is missing", ["--input", "{tmp}/nope.wav"]),
            Case("an input that is not audio", ["--input", "{file}"]),
            Case("an empty input folder", ["--input", "{emptydir}"])]


def option_cases() -> list[Case]:
    on_wav = {"--stream-id empty": ["--stream-id", ""], "--stream-id of 300 characters": ["--stream-id", "s" * 300],
              "--stream-id with an escape": ["--stream-id", "a\x1b[2Jb"],
              "--stream-id with a newline": ["--stream-id", "a\nb"],
              "--replicas asr=0": ["--replicas", "asr=0"], "--replicas asr=99": ["--replicas", "asr=99"],
              "--replicas nope=2": ["--replicas", "nope=2"], "--without foo": ["--without", "foo"],
              "--mic-channels a,b": ["--array", "respeaker4", "--mic-channels", "a,b"],
              "--array nosuch": ["--array", "nosuch"], "--array circular:0:0.1": ["--array", "circular:0:0.1"],
              "--host 256.1.1.1": ["--host", "256.1.1.1"], "--host empty": ["--host", ""],
              "--grammar missing": ["--grammar", "{tmp}/nope.gram"], "--with missing": ["--with", "{tmp}/nope"],
              "--asr nope": ["--asr", "nope"], "--vad nope": ["--vad", "nope"], "an unknown option": ["--bogus"]}
    return [*(Case(name, ["--input", WAV, *args]) for name, args in on_wav.items()),
            *(Case(f"--channels {count}", ["--mic", "default", "--array", "respeaker4", "--channels", count])
              for count in ("0", "-1")),
            Case("no --input or --mic", [])]


def service_cases() -> list[Case]:
    return [*(Case(f"orchestrator --port {port}", ["--port", port], command="orchestrator")
              for port in ("-1", "70000", "abc")),
            Case("orchestrator --db in /proc", ["--db", "/proc/esiaf/o.db"], command="orchestrator"),
            Case("orchestrator --db a folder", ["--db", "{tmp}"], command="orchestrator"),
            Case("orchestrator ESIAF_TOKEN_FILE missing", [], {"ESIAF_TOKEN_FILE": "{tmp}/no-token"},
                 command="orchestrator"),
            Case("vad ESIAF_MAX_STREAMS=0", [], {"ESIAF_MAX_STREAMS": "0"}, command="vad"),
            Case("vad ESIAF_TOKEN_FILE missing", [], {"ESIAF_TOKEN_FILE": "{tmp}/no-token"}, command="vad"),
            Case("grabber ESIAF_GRABBER_CHUNK_MS=nan", ["--input", WAV], {"ESIAF_GRABBER_CHUNK_MS": "nan"},
                 command="grabber"),
            Case("grabber a 1 Hz WAV", ["--input", "{wav1hz}"], command="grabber")]


def wyoming_cases() -> list[Case]:
    """esiaf wyoming's own options, and a setting of its service."""
    given = {"--port 0": ["--port", "0"], "--port abc": ["--port", "abc"],
             "--http-port 70000": ["--http-port", "70000"], "--listen 256.1.1.1": ["--listen", "256.1.1.1"],
             "--language e": ["--language", "e"],
             "--grammar missing": ["--grammar", "{tmp}/nope.gram"], "--without foo": ["--without", "foo"],
             "--input (esiaf run's)": ["--input", WAV], "ESIAF_TOKEN_FILE missing": []}
    return [*(Case(f"wyoming {name}", args, {"ESIAF_TOKEN_FILE": "{tmp}/no-token"} if not args else {},
                   command="wyoming") for name, args in given.items()),
            Case("wyoming ESIAF_WYOMING_MAX_SESSIONS=0", [], {"ESIAF_WYOMING_MAX_SESSIONS": "0"}, command="wyoming")]


CASES = [*port_cases(), *chunk_cases(), *workdir_cases(), *token_cases(), *setting_cases(), *vocabulary_cases(),
         *input_cases(), *option_cases(), *service_cases(), *wyoming_cases()]


def prepare(tmp: Path) -> dict[str, str]:
    """The files the cases name, made in ``tmp``; returns what each placeholder stands for."""
    (tmp / "file").write_text("not a folder, not audio\n")
    (tmp / "empty").write_text("")
    (tmp / "emptydir").mkdir(exist_ok=True)
    (tmp / "hugevocab").write_text("".join(f"name{i}\n" for i in range(100_000)))
    (tmp / "latin1").write_bytes("Zo\xeb\n".encode("latin-1"))
    files = {"wav1hz": wav_header(1), "wav1mhz": wav_header(1_000_003), "wav4k": wav_header(4000, samples=8000),
             "wav0ch": wav_header(16000, channels=0), "wav0bit": wav_header(16000, bits=0),
             "wavcut": wav_header(16000)[:30]}
    for name, data in files.items():
        (tmp / f"{name}.wav").write_bytes(data)
    return {"tmp": str(tmp), "file": str(tmp / "file"), "empty": str(tmp / "empty"),
            "hugevocab": str(tmp / "hugevocab"), "latin1": str(tmp / "latin1"),
            "emptydir": str(tmp / "emptydir"), **{name: str(tmp / f"{name}.wav") for name in files}}


@dataclass
class Outcome:
    code: int | None  # None: still running at TIMEOUT_S, stopped
    lines: list[str]
    wall_s: float
    cpu_s: float

    @property
    def traceback(self) -> bool:
        return any("Traceback" in line for line in self.lines)


def run_case(case: Case, tmp: Path, repo: Path = REPO, port: int = 18690, timeout_s: float = TIMEOUT_S) -> Outcome:
    """Runs ``case`` in its own workdir, with the orchestrator's HTTP port ``port`` (as a user would give
    them, unless the case names its own; ``port`` + 1 and + 2 must be free too)."""
    places = prepare(tmp)
    args = [arg.format(**places) for arg in case.args]
    if case.command == "run":
        command = [sys.executable, "-m", "esiaf", "run", *args]
        if "--workdir" not in args:
            command += ["--workdir", str(tmp / "work")]
        if "--port" not in args:
            command += ["--port", str(port)]
    elif case.command == "wyoming":  # esiaf wyoming: the orchestrator on port, the Wyoming server on port + 1
        command = [sys.executable, "-m", "esiaf", "wyoming", *args, "--workdir", str(tmp / "work")]
        command += [] if "--http-port" in args else ["--http-port", str(port)]
        command += [] if "--port" in args else ["--port", str(port + 1)]
    else:
        command = [sys.executable, "-m", f"esiaf_services.{case.command}", *args]
        if case.command == "orchestrator" and "--db" not in args:
            command += ["--db", str(tmp / "o.db")]
        if case.command == "orchestrator" and "--port" not in args:
            command += ["--port", str(port + 1)]
    env = {**{k: v for k, v in os.environ.items() if not k.startswith("ESIAF_")}, "PYTHONPATH": str(repo),
           "ESIAF_ORCHESTRATOR_URL": f"http://127.0.0.1:{port + 2}", "ESIAF_ORCHESTRATOR_CONTROL_PORT": "0",
           "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0",
           **{name: value.format(**places) for name, value in case.env.items()}}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    started = time.monotonic()
    process = subprocess.Popen(command, cwd=repo, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True, errors="replace", start_new_session=True)
    try:
        _, stderr = process.communicate(timeout=timeout_s)
        code: int | None = process.returncode
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, 9)
        _, stderr = process.communicate()
        code = None
    wall_s = time.monotonic() - started
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime
    return Outcome(code, stderr.strip().splitlines(), wall_s, cpu_s)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout that runs")
    parser.add_argument("--only", default="", help="only the cases whose name holds this")
    parser.add_argument("--port", type=int, default=18690, help="the HTTP port of the cases' orchestrators "
                        "(this one and the next two)")
    args = parser.parse_args()
    cases = [case for case in CASES if args.only in case.name]
    outcomes = []
    for case in cases:
        with tempfile.TemporaryDirectory(prefix="esiaf-bad-cli-") as tmp:
            outcome = run_case(case, Path(tmp), args.repo.resolve(), args.port)
        outcomes.append(outcome)
        first = outcome.lines[0][:90] if outcome.lines else ""
        print(f"{case.name!r:42} exit={outcome.code} lines={len(outcome.lines)} traceback={outcome.traceback} "
              f"wall_s={outcome.wall_s:.1f} cpu_s={outcome.cpu_s:.1f} | {first}", flush=True)
    print(f"cases={len(cases)} not_exit_2={sum(o.code != 2 for o in outcomes)} "
          f"not_one_line={sum(len(o.lines) != 1 for o in outcomes)} tracebacks={sum(o.traceback for o in outcomes)} "
          f"wall_over_2_s={sum(o.wall_s > 2.0 for o in outcomes)} cpu_over_2_s={sum(o.cpu_s > 2.0 for o in outcomes)} "
          f"waits_over_20_s={sum(o.wall_s > 20.0 for o in outcomes)}")


if __name__ == "__main__":
    main()
