"""``esiaf run`` once the pipeline is up: each fused result printed as one line (or as JSON) as it
arrives, progress and the orchestrator's health on stderr, until every stream has ended. With several
streams each line starts with its stream's id."""
from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass, field
from typing import Any

import httpx
import psutil
from websockets.exceptions import ConnectionClosed

from esiaf.tools.launcher import START_TIMEOUT_S, LaunchError, OrchestratorClient, Supervisor, wait_until
from esiaf.tools.terminal import err, out, partial, terminal_shows_partials

log = logging.getLogger(__name__)

LABELS = ("emotion", "gender", "voice_id")  # label aggregates shown on a line, in this order
# after a grabber has finished: give up on its stream once, for this long, no result has come and no
# service has worked (taken in or sent anything, or used the CPU: a loaded machine may drain a backlog,
# or sit in one long decode, for minutes); and in any case DRAIN_LIMIT_S after the file was played
DRAIN_TIMEOUT_S = 30.0
DRAIN_LIMIT_S = 600.0
WORK_CHECK_EVERY_S = 2.0  # while a stream drains: how often the services' counts and CPU are read
BUSY_CPU_SHARE = 0.1  # a service that used this share of one core since the last check is working
PROGRESS_EVERY_S = 10.0  # how often to say how much of a long file has been played
LONG_FILE_S = 60.0


def format_line(fused: dict[str, Any], origin_ns: int) -> str:
    """'[12.31–14.05 s] 'go forward ten meters' (p=0.93) from 92°, angry (0.81), female (0.97)'.

    The direction is shown where SSL was fused, each label (emotion, gender, voice) with the
    share of its top class where that analyser said something about the utterance."""
    anchor = fused["anchor"]
    span = anchor["span"]
    start_s, end_s = (span["start_ns"] - origin_ns) / 1e9, (span["end_ns"] - origin_ns) / 1e9
    what = said(fused)
    aggregates = fused.get("aggregates") or {}
    shown = set()
    if aggregates.get("ssl"):  # where the utterance came from: the fused SSL directions' circular mean
        what += f" from {aggregates['ssl']['azimuth_deg']:.0f}°"
        shown.add("ssl")
    for kind in LABELS:  # how, and who: the top label of the fused distribution and its share
        if aggregates.get(kind):
            label, share = aggregates[kind]["label"], f" ({aggregates[kind]['probability']:.2f})"
            if kind == "voice_id":  # "by Anna (0.91)"; an anonymous or unknown voice has no probability to show
                what += f" by {label}" + ("" if label.startswith("voice-") or label == "unknown" else share)
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


def said(fused: dict[str, Any]) -> str:
    """What was said: the best hypothesis, or why there is none."""
    anchor = fused["anchor"]
    if "speech" in anchor and anchor["speech"].get("hypotheses"):
        best = anchor["speech"]["hypotheses"][0]
        if not best.get("text") and not best.get("raw_text"):
            return "(speech not understood)"
        if best.get("out_of_set"):
            return f"out of set: '{best.get('raw_text', '')}' (match {best.get('match_score', 0):.2f})"
        return f"'{best['text']}' (p={best['probability']:.2f})"
    if "nothing" in anchor:  # the recogniser's word on speech it could not answer: its VAD died (orphans.py)
        return f"(speech lost: {anchor['nothing'].get('reason', '')})"
    if lost := next((m for m in fused.get("missing", []) if m.get("type") == "speech"), None):
        # its recogniser died with it, or passed it by (orphans.py)
        return "(speech lost: its recogniser skipped it)" if lost.get("reason") == "skipped" \
            else "(speech lost: its recogniser died)"
    payload = next((k for k in ("vad", "ssl", "emotion", "gender", "voice_id") if k in anchor), "")
    return f"{payload} {json.dumps(anchor.get(payload, {}))}"


@dataclass
class Stream:
    """One input played as a stream: its grabber, and how far it has come."""
    stream_id: str
    grabber: Any  # the Child playing it
    source: str  # the file or device, as the user named it
    origin_ns: int = 0  # the stream's start: lines show times relative to it
    done_at: float | None = None  # monotonic time its grabber finished playing
    ended: bool = False  # its stream_end came
    gave_up: bool = False  # no stream_end came in time (without --serve)
    warned: bool = False  # --serve: said once that it did not end, or that its grabber failed
    printed: int = 0


@dataclass
class Following:
    """What :func:`follow` keeps track of between two messages."""
    streams: dict[str, Stream]
    next_progress: float  # monotonic time of the next progress and health report
    heard_at: float = 0.0  # when the last message of one of the streams arrived
    unhealthy: str = ""  # why the orchestrator said it is unhealthy, as last reported
    worked_at: float = 0.0  # when the services' counts last moved (read while a stream drains)
    work: int | None = None  # the services' counts as last read: what they took in and sent, summed
    cpu_s: dict[int, float] = field(default_factory=dict)  # each service process's CPU time as last read
    next_work_check: float = 0.0
    checked_at: float = 0.0  # when they were last read
    said_draining: bool = False  # said once that the pipeline is still working after a file was played


def follow(ws, supervisor: Supervisor, client: OrchestratorClient, streams: list[Stream],
           args: argparse.Namespace) -> int:
    """Prints fused results until every stream has ended (files) or forever (mic, --serve)."""
    for stream in streams:
        def stream_start_ns(stream_id: str = stream.stream_id) -> int | None:
            found = client.stream(stream_id)  # as its grabber announced it (the launcher's has no source)
            return found["start_ns"] if found and found.get("source") else None

        stream.origin_ns = wait_until(stream_start_ns, supervisor, f"the grabber to start playing {stream.source}",
                                      START_TIMEOUT_S, stream.grabber)
        if args.json:
            out(json.dumps({"type": "stream_start", "stream_id": stream.stream_id, "start_ns": stream.origin_ns}))
    state = Following({stream.stream_id: stream for stream in streams},
                      next_progress=time.monotonic() + PROGRESS_EVERY_S)
    while True:
        report_when_due(state, client, args)
        for child, line in supervisor.refusals():  # what a service refused: here within 0.2 s, not only in its log
            err(f"esiaf: {child.name} {line} (its log: {child.log_path})")
        watch_children(state, supervisor, client, args)
        watch_work(state, supervisor, client)
        if (code := check_drained(state, args)) is not None:
            return code
        try:
            message = json.loads(ws.recv(timeout=0.2))
        except TimeoutError:
            continue
        except ConnectionClosed as exc:
            raise LaunchError(f"the orchestrator closed the websocket: {exc}") from None
        if (code := show_message(state, message, args)) is not None:
            return code


def report_when_due(state: Following, client: OrchestratorClient, args: argparse.Namespace) -> None:
    """Every PROGRESS_EVERY_S: how much of each file has been played, and the orchestrator's health."""
    if time.monotonic() < state.next_progress:
        return
    state.next_progress += PROGRESS_EVERY_S
    for stream in state.streams.values():
        if args.input and stream.done_at is None:
            show_progress(client, stream, len(state.streams) > 1)
    state.unhealthy = report_health(client, state.unhealthy)


def watch_children(state: Following, supervisor: Supervisor, client: OrchestratorClient,
                   args: argparse.Namespace) -> None:
    """Reports each child that died to the orchestrator (dead at once: its streams move, what it had
    not answered is fused without it); notes each grabber's end; a grabber that failed ends the run
    (with --serve: it is said once and the services stay up), another service is restarted."""
    grabbers = {id(stream.grabber): stream for stream in state.streams.values()}
    supervisor.keep_spares()
    for child in supervisor.exited():
        if not child.reported:
            child.reported = True
            if (component_id := client.report_dead(child.process.pid)) is not None:
                log.info("reported dead service=%s component_id=%s", child.name, component_id)
        stream = grabbers.get(id(child))
        if stream is None:
            supervisor.restart_when_due(child)
        elif child.process.returncode == 0:
            stream.done_at = stream.done_at or time.monotonic()
        elif not args.serve:
            raise LaunchError(supervisor.failure(child))
        elif not stream.warned:
            stream.warned = True
            stream.done_at = stream.done_at or time.monotonic()
            err(f"esiaf: {supervisor.failure(child)}\nesiaf: stream {stream.stream_id} has no more audio; "
                f"still serving")


def work_done(components: list[dict[str, Any]]) -> int:
    """What the live services have done so far, as one number that grows while any of them works: the
    messages each has taken in and sent and the results it has sent, as their heartbeats last said."""
    total = 0
    for component in components:
        if component.get("status") != "alive":
            continue
        stats = component.get("stats") or {}
        for side, count in (("inputs", "received"), ("outputs", "published")):
            for counts in (stats.get(side) or {}).values():
                total += int((counts or {}).get(count) or 0)
        total += int(stats.get("results_sent") or 0)
    return total


def busy_services(supervisor: Supervisor, cpu_s: dict[int, float], interval_s: float) -> list[str]:
    """The services whose processes used BUSY_CPU_SHARE of a core or more since the last call (``cpu_s``:
    each process's CPU time then, updated here); a process first seen is not busy yet."""
    busy, seen = [], {}
    for child in supervisor.children:
        pid = child.process.pid
        try:
            times = psutil.Process(pid).cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        seen[pid] = times.user + times.system
        if pid in cpu_s and seen[pid] - cpu_s[pid] >= BUSY_CPU_SHARE * interval_s:
            busy.append(child.name)
    cpu_s.clear()
    cpu_s.update(seen)
    return busy


def watch_work(state: Following, supervisor: Supervisor, client: OrchestratorClient) -> None:
    """While a played stream has not ended: every WORK_CHECK_EVERY_S, whether the services still work
    (their heartbeats' counts moved, or one of the launcher's services used the CPU: a backlog behind a
    slow analyser, or one long decode, on a loaded machine), so that the drain waits for them; says so
    once when it has waited PROGRESS_EVERY_S."""
    now = time.monotonic()
    draining = [s for s in state.streams.values() if s.done_at and not s.ended and not s.gave_up]
    if not draining or now < state.next_work_check:
        return
    interval_s, state.checked_at = now - state.checked_at, now
    state.next_work_check = now + WORK_CHECK_EVERY_S
    busy = busy_services(supervisor, state.cpu_s, interval_s)
    work: int | None
    try:
        work = work_done(client.components())
    except httpx.HTTPError:
        work = state.work  # restarting: the supervisor says so
    if busy or (state.work is not None and work != state.work):
        state.worked_at = now
    state.work = work
    if not state.said_draining and now - min(s.done_at or now for s in draining) > PROGRESS_EVERY_S \
            and state.worked_at == now:
        state.said_draining = True
        err("esiaf: the input has been played; the services are still working through it"
            + (f" ({', '.join(busy)})" if busy else ""))


def check_drained(state: Following, args: argparse.Namespace) -> int | None:
    """Gives up on each stream that has not ended when, for DRAIN_TIMEOUT_S after its file was played,
    no result has come and no service has worked (:func:`watch_work`), or DRAIN_LIMIT_S after it was
    played; the exit code once every stream has ended or been given up on (None: go on). With --serve
    it only says so: the services stay up until the launcher is stopped."""
    now = time.monotonic()
    for stream in state.streams.values():
        if not stream.done_at or stream.ended or stream.gave_up or \
                (now - max(stream.done_at, state.heard_at, state.worked_at) <= DRAIN_TIMEOUT_S
                 and now - stream.done_at <= DRAIN_LIMIT_S):
            continue
        if not args.serve:
            stream.gave_up = True
            why = f"still not done {DRAIN_LIMIT_S:g} s" if now - stream.done_at > DRAIN_LIMIT_S else \
                f"no result and no service at work for {DRAIN_TIMEOUT_S:g} s"
            err(f"esiaf: no end of stream {stream.stream_id}: {why} after {stream.source} was played; stopping"
                f"{' it' if len(state.streams) > 1 else ''}")
        elif not stream.warned:  # --serve never stops the services on its own
            stream.warned = True
            err(f"esiaf: no end of stream {stream.stream_id} {DRAIN_TIMEOUT_S:g} s after {stream.source} was "
                f"played; still serving")
    return run_over(state, args)


def run_over(state: Following, args: argparse.Namespace) -> int | None:
    """Without --serve, a file's run is over once every stream has ended (0) or been given up on (1)."""
    if args.serve or args.mic or not all(s.ended or s.gave_up for s in state.streams.values()):
        return None
    return 1 if any(s.gave_up for s in state.streams.values()) else 0


def shows_partials(args: argparse.Namespace) -> bool:
    """Whether the run asks for partial results: on a terminal (shown in place), or --json --partials."""
    return bool(args.partials) if args.json else terminal_shows_partials()


def show_message(state: Following, message: dict[str, Any], args: argparse.Namespace) -> int | None:
    """Prints a fused result, a partial one, or a stream's end; returns the exit code once the run is over."""
    stream = state.streams.get(message.get("stream_id", ""))
    if stream is None:
        return None  # another source's stream (a second robot streaming into this pipeline)
    state.heard_at = time.monotonic()  # results still arriving: the drain deadlines move on
    several = len(state.streams) > 1
    if message.get("type") == "stream_end":
        stream.ended = True
        if args.json:
            out(json.dumps(message))
        err(f"esiaf: stream {stream.stream_id + ' ' if several else ''}ended, {stream.printed} fused result(s)")
        return run_over(state, args)
    if message.get("type") == "partial":
        if args.json:
            out(json.dumps(message))
        elif not message.get("closed"):
            what = message.get("text", "")
            partial(f"[{stream.stream_id}] … {what}" if several else f"… {what}")
        else:
            partial("")
        return None
    if message.get("type") == "barge_in":  # a person started speaking while the robot played
        if args.json:
            out(json.dumps(message))
        else:
            err(f"esiaf: barge-in{' on ' + stream.stream_id if several else ''} at "
                f"{(message['capture_ns'] - stream.origin_ns) / 1e9:.2f} s ({message.get('policy', '')})")
        return None
    if message.get("type") == "fused_withdrawn":  # a later revision found it was the robot's own voice
        if args.json:
            out(json.dumps(message))
        else:
            err(f"esiaf: fused result {message['id']}{' on ' + stream.stream_id if several else ''} withdrawn: "
                "it was the robot's own voice")
        return None
    if message.get("type") == "fused_result":
        stream.printed += 1
        line = json.dumps(message) if args.json else format_line(message, stream.origin_ns)
        out(f"[{stream.stream_id}] {line}" if several and not args.json else line)
    return None


def report_health(client: OrchestratorClient, reported: str) -> str:
    """Says on stderr when the orchestrator turns unhealthy (its database cannot be written) and
    when it recovers; returns what is now reported."""
    try:
        problem = client.health_problem()
    except httpx.HTTPError:
        return reported  # restarting: the supervisor says so
    if problem != reported:
        err(f"esiaf: orchestrator unhealthy: {problem}" if problem else "esiaf: orchestrator healthy again")
    return problem


def show_progress(client: OrchestratorClient, stream: Stream, several: bool) -> None:
    """'esiaf: played 40 of 300 s (13 %)' on stderr, for files longer than LONG_FILE_S (with several
    streams: 'esiaf: stream robot1-...: played ...')."""
    try:
        info = ((client.by_pid(stream.grabber.process.pid) or {}).get("stats") or {}).get("info", {})
    except httpx.HTTPError:
        return
    played_s, duration_s = info.get("played_s"), info.get("duration_s")
    if played_s is not None and duration_s and duration_s > LONG_FILE_S:
        err(f"esiaf: {f'stream {stream.stream_id}: ' if several else ''}played {played_s:.0f} of "
            f"{duration_s:.0f} s ({100 * played_s / duration_s:.0f} %)")
