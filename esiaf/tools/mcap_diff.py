"""What a replay changed: the recorded fused results against new ones, utterance by utterance (text,
direction, voice), matched by their windows' times from each stream's start (docs/recording.md).

    esiaf mcap diff RECORDED.mcap REPLAYED.mcap     (exit 0: the same; 1: they differ; 2: a bad file)

Recordings of several streams are compared stream by stream: each recorded stream with the replayed
stream of the same name (its id without the time stamp ``esiaf run`` adds, as ``esiaf run --input
RECORDED.mcap --record REPLAYED.mcap`` names the replayed streams), else in the order of their
first chunks.

``esiaf run --input RECORDED.mcap --diff`` prints the same against the fused results of its replay.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from esiaf.argparsing import OneLineParser
from esiaf.proto import esiaf_pb2 as pb
from esiaf.tools.mcap_replay import SessionError, check_session, recorded_fused, recorded_streams, stream_name
from esiaf.tools.terminal import err, out

DIRECTION_TOLERANCE_DEG = 10.0  # directions closer than this are the same


@dataclass(frozen=True)
class Utterance:
    """One fused result as the diff compares it: its window from its stream's start, and what was found."""
    start_s: float
    end_s: float
    text: str
    direction_deg: float | None
    voice: str

    def shown(self) -> str:
        return f"{self.start_s:7.2f}-{self.end_s:.2f} s"


def utterance(fused: pb.FusedResult, origin_ns: int) -> Utterance:
    anchor = fused.anchor
    text = anchor.speech.hypotheses[0].text if anchor.HasField("speech") and anchor.speech.hypotheses else ""
    ssl = fused.aggregates.ssl if fused.aggregates.HasField("ssl") and fused.aggregates.ssl.directions else None
    voice = fused.aggregates.voice_id.label if fused.aggregates.HasField("voice_id") else ""
    return Utterance((anchor.span.start_ns - origin_ns) / 1e9, (anchor.span.end_ns - origin_ns) / 1e9, text,
                     None if ssl is None else ssl.azimuth_deg, voice)


def _overlap(a: Utterance, b: Utterance) -> float:
    return min(a.end_s, b.end_s) - max(a.start_s, b.start_s)


def _angle(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def _direction(value: float | None) -> str:
    return "none" if value is None else f"{value:.0f} deg"


def changes(old: Utterance, new: Utterance) -> list[str]:
    """How ``new`` differs from ``old``: text, direction (beyond the tolerance), voice."""
    found = []
    if old.text != new.text:
        found.append(f"text {old.text!r} -> {new.text!r}")
    if (old.direction_deg is None) != (new.direction_deg is None) or (
            old.direction_deg is not None and new.direction_deg is not None
            and _angle(old.direction_deg, new.direction_deg) > DIRECTION_TOLERANCE_DEG):
        found.append(f"direction {_direction(old.direction_deg)} -> {_direction(new.direction_deg)}")
    if old.voice != new.voice:
        found.append(f"voice {old.voice or 'none'!r} -> {new.voice or 'none'!r}")
    return found


def diff(recorded: Sequence[Utterance], replayed: Sequence[Utterance]) -> list[str]:
    """One line per difference (an utterance changed, lost or new) and a last line counting them. Each
    recorded utterance is matched to the unmatched replayed one whose window overlaps it most."""
    lines: list[str] = []
    unmatched = list(replayed)
    for old in recorded:
        best = max(unmatched, key=lambda new: _overlap(old, new), default=None)
        if best is None or _overlap(old, best) <= 0:
            lines.append(f"- {old.shown()} recorded {old.text!r}: not in the replay")
            continue
        unmatched.remove(best)
        found = changes(old, best)
        if found:
            lines.append(f"~ {old.shown()} " + "; ".join(found))
    lines.extend(f"+ {new.shown()} replayed {new.text!r}: not in the recording" for new in unmatched)
    lines.append(f"diff: {len(recorded)} recorded utterances, {len(replayed)} replayed, "
                 f"{len(lines)} difference{'s' if len(lines) != 1 else ''}")
    return lines


def session_utterances(path: Path, stream_id: str | None = None) -> list[Utterance]:
    """A recording's utterances of one recorded stream (None: its first), from that stream's start."""
    info = check_session(path, stream_id)
    return [utterance(fused, info.start_ns) for fused in recorded_fused(path) if fused.stream_id == info.stream_id]


def parse_args(argv: Sequence[str]) -> argparse.Namespace:
    parser = OneLineParser(prog="esiaf mcap", description="ESIAF recordings (MCAP)")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=OneLineParser)
    compare = sub.add_parser("diff", help="the fused results of two recordings of the same audio, compared")
    compare.add_argument("recorded", type=Path)
    compare.add_argument("replayed", type=Path)
    return parser.parse_args(argv)


def compare(recorded: Path, replayed: Path) -> tuple[list[str], bool]:
    """The diff lines of each stream of ``recorded`` against the stream of ``replayed`` in the same
    place (several: each under a line naming both), and whether they are the same."""
    old_streams, new_streams = recorded_streams(recorded), recorded_streams(replayed)
    if len(old_streams) != len(new_streams):
        raise SessionError(f"{recorded} holds {len(old_streams)} streams, {replayed} {len(new_streams)}: "
                           "not a replay of the same recording")
    by_name = {stream_name(stream): stream for stream in new_streams}
    if len(by_name) == len(new_streams) and {stream_name(stream) for stream in old_streams} == set(by_name):
        new_streams = [by_name[stream_name(stream)] for stream in old_streams]
    lines: list[str] = []
    same = True
    for old, new in zip(old_streams, new_streams, strict=True):
        if len(old_streams) > 1:
            lines.append(f"stream {old} (replayed as {new}):")
        found = diff(session_utterances(recorded, old), session_utterances(replayed, new))
        same = same and len(found) == 1
        lines += found
    return lines, same


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        lines, same = compare(args.recorded, args.replayed)
    except SessionError as exc:
        err(f"esiaf mcap: {exc}")
        return 2
    for line in lines:
        out(line)
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
