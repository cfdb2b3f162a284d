"""The launcher's own output: one readable line per fused result, progress on long files."""
import json
import time

from esiaf.tools.cli import format_line, show_progress

ORIGIN_NS = 1_700_000_000_000_000_000


def fused(**extra):
    anchor = {"span": {"start_ns": ORIGIN_NS + 12_310_000_000, "end_ns": ORIGIN_NS + 14_050_000_000},
              "speech": {"hypotheses": [{"text": "go forward ten meters", "probability": 0.934}]}}
    return {"type": "fused_result", "id": 1, "revision": 1, "anchor": anchor, "results": {},
            "completion": "complete", "missing_components": [], **extra}


def test_a_fused_result_is_one_line_with_times_in_the_recording():
    assert format_line(fused(), ORIGIN_NS) == "[12.31–14.05 s] 'go forward ten meters' (p=0.93)"


def test_the_line_says_what_else_was_fused_how_it_completed_and_the_revision():
    line = format_line(fused(results={"ssl": [{}, {}]}, completion="timed_out", missing_components=["emotion"],
                             revision=2), ORIGIN_NS)
    assert line == ("[12.31–14.05 s] 'go forward ten meters' (p=0.93) ssl×2; timed_out, missing emotion rev 2")


def test_an_utterance_whose_recogniser_died_says_its_speech_was_lost():
    orphan = fused(completion="components_gone", missing_components=["asr"],
                   missing=[{"component": "asr", "type": "speech", "reason": "gone"}])
    orphan["anchor"] = {"span": orphan["anchor"]["span"], "vad": {"probability": 0.8}}
    assert format_line(orphan, ORIGIN_NS) == \
        "[12.31–14.05 s] (speech lost: its recogniser died) components_gone, missing asr"

    skipped = fused(completion="timed_out", missing_components=["asr"],
                    missing=[{"component": "asr", "type": "speech", "reason": "skipped"}])
    skipped["anchor"] = orphan["anchor"]
    assert format_line(skipped, ORIGIN_NS) == \
        "[12.31–14.05 s] (speech lost: its recogniser skipped it) timed_out, missing asr"


def test_a_service_is_given_up_after_a_crash_loop_but_a_rare_crash_starts_the_count_again(tmp_path, monkeypatch):
    """MAX_RESTARTS deaths in a row end the run only when each came soon after its start: a service
    of a long --serve run that crashes now and then is restarted every time."""
    from esiaf.tools import launcher
    monkeypatch.setattr(launcher, "RESTART_BACKOFF_S", 0.0)
    monkeypatch.setattr(launcher, "STABLE_AFTER_S", 0.6)

    def deaths_until_given_up(seconds_alive: float, at_most: int) -> int:
        """Restarts a child that dies ``seconds_alive`` after each start: deaths until given up, or ``at_most``."""
        supervisor = launcher.Supervisor(tmp_path)
        child = supervisor.start("crashy",
                                 target=["-c", f"import time; time.sleep({seconds_alive}); raise SystemExit(3)"])
        try:
            for died in range(1, at_most + 1):
                assert child.process.wait(timeout=30) == 3
                try:
                    supervisor.restart_when_due(child)  # its death first seen: given up, or restarted at once
                except launcher.LaunchError as exc:
                    assert "not restarted: it died" in str(exc)
                    return died
            return at_most
        finally:
            supervisor.stop()

    assert deaths_until_given_up(0.0, 10) == launcher.MAX_RESTARTS + 1  # a crash loop: given up
    assert deaths_until_given_up(0.8, launcher.MAX_RESTARTS + 3) == launcher.MAX_RESTARTS + 3  # never

class Client:
    def __init__(self, info):
        self.info = info

    def by_pid(self, pid):
        return {"name": "grabber", "pid": pid, "stats": {"info": self.info}}


def test_progress_on_long_files_only(capsys):
    import types

    from esiaf.tools.cli_follow import Stream
    stream = Stream("robot1", types.SimpleNamespace(process=types.SimpleNamespace(pid=12)), "a.wav")
    show_progress(Client({"played_s": 40.2, "duration_s": 300.0}), stream, several=False)
    show_progress(Client({"played_s": 10.0, "duration_s": 20.0}), stream, several=False)
    show_progress(Client({"played_s": 40.2, "duration_s": 300.0}), stream, several=True)
    assert capsys.readouterr().err == ("esiaf: played 40 of 300 s (13 %)\n"
                                       "esiaf: stream robot1: played 40 of 300 s (13 %)\n")


def test_direction_emotion_and_gender_are_on_the_line_with_their_shares():
    aggregates = {"ssl": {"azimuth_deg": 91.6}, "emotion": {"label": "angry", "probability": 0.814},
                  "gender": {"label": "female", "probability": 0.97}}
    results = {"ssl": [{}] * 12, "emotion": [{}], "gender": [{}]}
    assert format_line(fused(aggregates=aggregates, results=results), ORIGIN_NS) == \
        "[12.31–14.05 s] 'go forward ten meters' (p=0.93) from 92°, angry (0.81), female (0.97)"
    # an analyser that had nothing to say (too short) is simply absent; one that never answered is named
    line = format_line(fused(aggregates={"gender": {"label": "male", "probability": 0.5}},
                             results={"gender": [{}], "emotion": [], "ssl": []}, completion="timed_out",
                             missing_components=["emotion"]),
                       ORIGIN_NS)
    assert line == "[12.31–14.05 s] 'go forward ten meters' (p=0.93), male (0.50) timed_out, missing emotion"


class _Silent:
    """A websocket on which nothing arrives: after ``polls`` receives the orchestrator 'closes' it."""

    def __init__(self, polls):
        self.polls = polls

    def recv(self, timeout):
        from websockets.exceptions import ConnectionClosed
        self.polls -= 1
        if self.polls < 0:
            raise ConnectionClosed(None, None)
        raise TimeoutError


def _follow_a_played_file_that_never_ends(monkeypatch, serve):
    import argparse
    import types

    from esiaf.tools import cli, cli_follow
    from esiaf.tools.launcher import LaunchError

    monkeypatch.setattr(cli_follow, "DRAIN_TIMEOUT_S", 0.0)  # where follow() reads it
    grabber = types.SimpleNamespace(process=types.SimpleNamespace(returncode=0, pid=1), reported=False)
    supervisor = types.SimpleNamespace(exited=lambda: [grabber], refusals=list, keep_spares=lambda: None, children=[])
    client = types.SimpleNamespace(stream=lambda stream_id: {"start_ns": ORIGIN_NS, "source": "grabber-1"},
                                   report_dead=lambda pid: None, components=list)
    args = argparse.Namespace(stream_id="s", json=False, input="a.wav", serve=serve, mic=None)
    try:
        return cli.follow(_Silent(polls=5), supervisor, client, [cli_follow.Stream("s", grabber, "a.wav")], args)
    except LaunchError:  # the websocket went away while it still listened
        return "kept serving"


def test_without_serve_the_launcher_gives_up_when_no_end_of_stream_comes(monkeypatch, capsys):
    assert _follow_a_played_file_that_never_ends(monkeypatch, serve=False) == 1
    assert "no end of stream s: no result and no service at work" in capsys.readouterr().err


def test_serve_never_stops_the_services_on_its_own(monkeypatch, capsys):
    # it keeps listening until the websocket goes away, and says once that the stream did not end
    assert _follow_a_played_file_that_never_ends(monkeypatch, serve=True) == "kept serving"
    assert capsys.readouterr().err.count("still serving") == 1


def test_the_line_ends_with_who_spoke():
    named = {"emotion": {"label": "angry", "probability": 0.81}, "voice_id": {"label": "Anna", "probability": 0.912}}
    assert format_line(fused(aggregates=named, results={"emotion": [{}], "voice_id": [{}]}), ORIGIN_NS) == \
        "[12.31–14.05 s] 'go forward ten meters' (p=0.93), angry (0.81) by Anna (0.91)"
    anonymous = {"voice_id": {"label": "voice-2", "probability": 1.0}}
    assert format_line(fused(aggregates=anonymous, results={"voice_id": [{}]}), ORIGIN_NS) == \
        "[12.31–14.05 s] 'go forward ten meters' (p=0.93) by voice-2"


def test_speech_not_understood_still_says_from_where():
    result = fused(aggregates={"ssl": {"azimuth_deg": 91.6}}, results={"ssl": [{}]})
    result["anchor"]["speech"]["hypotheses"] = [{"text": "", "probability": 0.0}]
    assert format_line(result, ORIGIN_NS) == "[12.31–14.05 s] (speech not understood) from 92°"


def test_esiaf_run_names_a_misspelt_variable_before_it_starts_anything():
    import os
    import socket
    import subprocess
    import sys

    from esiaf.tools.testing import REPO
    with socket.socket() as taken:  # the port in use stops the run right after the check
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        done = subprocess.run([sys.executable, "-m", "esiaf", "run", "--input", "examples/robocup_questions.wav",
                               "--port", str(taken.getsockname()[1])], cwd=REPO, capture_output=True, text=True,
                              env={**os.environ, "ESIAF_VDA_DB_MIN": "3"}, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("esiaf: ESIAF_VDA_DB_MIN names no service ("), done.stderr


class _Feed:
    """A websocket that delivers ``messages``, then nothing (each receive waits its timeout) until,
    after ``polls`` silent receives, the orchestrator 'closes' it."""

    def __init__(self, messages, polls):
        self.messages, self.polls = [json.dumps(m) for m in messages], polls

    def recv(self, timeout):
        if self.messages:
            return self.messages.pop(0)
        time.sleep(timeout)
        _Silent.recv(self, timeout)  # type: ignore[arg-type]  # the same countdown to a closed websocket


def _follow_two_streams_of_which_one_ends(monkeypatch, serve, b_returncode=0):
    import argparse
    import types

    from esiaf.tools import cli_follow
    from esiaf.tools.launcher import LaunchError

    monkeypatch.setattr(cli_follow, "DRAIN_TIMEOUT_S", 0.3)
    grabbers = [types.SimpleNamespace(process=types.SimpleNamespace(returncode=code, pid=i), reported=False)
                for i, code in enumerate((0, b_returncode))]
    supervisor = types.SimpleNamespace(exited=lambda: grabbers, refusals=list, keep_spares=lambda: None, children=[],
                                       failure=lambda child: "service grabber-2 failed")
    client = types.SimpleNamespace(stream=lambda stream_id: {"start_ns": ORIGIN_NS, "source": "grabber-1"},
                                   report_dead=lambda pid: None, components=list)
    args = argparse.Namespace(json=False, input=["a.wav", "b.wav"], serve=serve, mic=None)
    streams = [cli_follow.Stream("a", grabbers[0], "a.wav"), cli_follow.Stream("b", grabbers[1], "b.wav")]
    feed = _Feed([{**fused(), "stream_id": "a"}, {**fused(), "stream_id": "other"},
                  {"type": "stream_end", "stream_id": "a"}], polls=10)
    try:
        return cli_follow.follow(feed, supervisor, client, streams, args)
    except LaunchError:
        return "kept serving"


def test_several_streams_each_end_or_are_given_up_on_before_the_run_ends(monkeypatch, capsys):
    assert _follow_two_streams_of_which_one_ends(monkeypatch, serve=False) == 1
    out, err = capsys.readouterr()
    assert out == "[a] [12.31–14.05 s] 'go forward ten meters' (p=0.93)\n"  # another source's stream is not shown
    assert "esiaf: stream a ended, 1 fused result(s)" in err
    assert "no end of stream b: no result and no service at work for 0.3 s after b.wav was played; " \
        "stopping it" in err
    assert "no end of stream a" not in err


def test_serve_goes_on_after_a_stream_without_end_and_a_failed_grabber(monkeypatch, capsys):
    assert _follow_two_streams_of_which_one_ends(monkeypatch, serve=True) == "kept serving"
    assert capsys.readouterr().err.count("no end of stream b 0.3 s after b.wav was played; still serving") == 1
    assert _follow_two_streams_of_which_one_ends(monkeypatch, serve=True, b_returncode=1) == "kept serving"
    err = capsys.readouterr().err
    assert err.count("service grabber-2 failed\nesiaf: stream b has no more audio; still serving") == 1
    assert "no end of stream" not in err


def test_a_barge_in_is_printed_as_json_with_the_fused_results_and_said_on_stderr_without(capsys):
    import argparse
    import types

    from esiaf.tools import cli_follow
    event = {"type": "barge_in", "stream_id": "s", "capture_ns": ORIGIN_NS + 2_500_000_000, "policy": "stop"}
    for as_json in (True, False):
        stream = cli_follow.Stream("s", types.SimpleNamespace(), "a.wav")
        stream.origin_ns = ORIGIN_NS
        state = cli_follow.Following(streams={"s": stream}, next_progress=0.0)
        args = argparse.Namespace(json=as_json, serve=False, mic=None)
        assert cli_follow.show_message(state, event, args) is None
        out, err = capsys.readouterr()
        if as_json:
            assert json.loads(out) == event and stream.printed == 0  # not counted as a fused result
        else:
            assert out == "" and "barge-in at 2.50 s (stop)" in err


def test_the_launcher_waits_while_the_services_still_work_through_a_played_file(monkeypatch, capsys):
    """A loaded machine drains a backlog for longer than DRAIN_TIMEOUT_S after the file has played: as
    long as the services' heartbeats say they take in or send something, the launcher waits; once
    they stop, it gives up after DRAIN_TIMEOUT_S as before (before: it gave up while the asr worked)."""
    started = time.monotonic()

    def components():  # the asr takes in one chunk more at each heartbeat for 1.5 s, then nothing
        received = int(min(time.monotonic() - started, 1.5) * 20)
        asr = {"status": "alive", "stats": {"inputs": {"vad/audio": {"received": received}}, "results_sent": 3}}
        gone = {"status": "dead", "stats": {"inputs": {"grabber/audio": {"received": int(time.monotonic() * 1e3)}}}}
        return [asr, gone]  # a dead component's counts are not work

    code = _follow_while(monkeypatch, components, [])
    waited = time.monotonic() - started
    err = capsys.readouterr().err
    assert code == 1 and 1.5 + 0.4 <= waited < 4.0, (code, waited, err)
    assert err.count("esiaf: the input has been played; the services are still working through it") == 1
    assert "no end of stream s: no result and no service at work for 0.4 s after a.wav was played" in err


def test_work_done_counts_what_live_services_took_in_and_sent():
    from esiaf.tools.cli_follow import work_done
    stats = {"inputs": {"a": {"received": 5, "lost": 2}, "b": {"received": 1}},
             "outputs": {"x": {"published": 7, "dropped": 4}}, "results_sent": 2}
    assert work_done([{"status": "alive", "stats": stats}, {"status": "dead", "stats": stats},
                      {"status": "alive"}, {"status": "alive", "stats": {"inputs": {"c": None}}}]) == 15


def _follow_while(monkeypatch, components, children):
    """follow() on one played file that never ends, the services' counts and processes as given."""
    import argparse
    import types

    from esiaf.tools import cli_follow

    monkeypatch.setattr(cli_follow, "DRAIN_TIMEOUT_S", 0.4)
    monkeypatch.setattr(cli_follow, "WORK_CHECK_EVERY_S", 0.05)
    monkeypatch.setattr(cli_follow, "PROGRESS_EVERY_S", 0.5)
    grabber = types.SimpleNamespace(process=types.SimpleNamespace(returncode=0, pid=1), reported=False)
    supervisor = types.SimpleNamespace(exited=lambda: [grabber], refusals=list, keep_spares=lambda: None,
                                       children=children)
    client = types.SimpleNamespace(stream=lambda stream_id: {"start_ns": ORIGIN_NS, "source": "grabber-1"},
                                   report_dead=lambda pid: None, components=components, health_problem=str)
    args = argparse.Namespace(json=False, input="a.wav", serve=False, mic=None)
    return cli_follow.follow(_Feed([], polls=100), supervisor, client, [cli_follow.Stream("s", grabber, "a.wav")],
                             args)


def test_the_launcher_waits_while_a_service_sits_in_one_long_decode(monkeypatch, capsys):
    """A service busy on the CPU (one Whisper decode of tens of seconds under load) moves no count; the
    launcher waits for it as long as it works, then gives up as before."""
    import subprocess
    import sys
    import types

    busy = "import time\nt = time.monotonic()\nwhile time.monotonic() - t < 1.5: pass\ntime.sleep(60)"
    with subprocess.Popen([sys.executable, "-c", busy]) as decoding:
        try:
            started = time.monotonic()
            code = _follow_while(monkeypatch, list, [types.SimpleNamespace(name="asr", process=decoding)])
            waited = time.monotonic() - started
        finally:
            decoding.kill()
    err = capsys.readouterr().err
    assert code == 1 and 1.5 + 0.4 <= waited < 6.0, (code, waited, err)
    assert "esiaf: the input has been played; the services are still working through it (asr)" in err


def test_the_launcher_gives_up_at_the_drain_limit_even_while_services_work(monkeypatch, capsys):
    from esiaf.tools import cli_follow
    monkeypatch.setattr(cli_follow, "DRAIN_LIMIT_S", 1.0)
    counts = iter(range(10**6))  # every heartbeat says more was taken in: never quiet
    code = _follow_while(monkeypatch, lambda: [{"status": "alive", "stats": {"results_sent": next(counts)}}], [])
    err = capsys.readouterr().err
    assert code == 1 and "no end of stream s: still not done 1 s after a.wav was played; stopping" in err, err
