"""The vad's audio cut at its decision windows, and what it forwards put back into messages.

The vad decides once per Silero window (32 ms), whatever size the transport's chunks are: a stream's
chunks are cut into one :class:`Piece` per window the model completes (the samples of a window not
yet complete wait for the next chunk), each with its own capture times and probability, so that
segment boundaries, durations and hysteresis are the same at 10 ms chunks as at 100 ms. What the
segmenter forwards is sent as few messages as it can be (:func:`messages`): contiguous pieces
together, a message ending where a segment ends, at most ``MAX_MESSAGE_S`` of audio in one.

The energy backend decides per chunk, as the original did: its pieces are the chunks.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np

from esiaf.speech.segmenter import Forward
from esiaf.speech.silero import SileroStream

MAX_MESSAGE_S = 1.0  # audio in one forwarded message (a receiver refuses more than 10 s)


@dataclass(frozen=True)
class Piece:
    """Audio of one stream: payload bytes, capture times, and where it starts in the stream (frames)."""

    payload: bytes
    start_ns: int
    end_ns: int
    frame: int
    frames: int
    end_of_stream: bool = False

    def split(self, frames: int, frame_bytes: int) -> tuple[Piece, Piece]:
        """The first ``frames`` frames and the rest; the cut's capture time interpolated in the piece."""
        at_ns = self.start_ns + (self.end_ns - self.start_ns) * frames // self.frames
        cut = frames * frame_bytes
        return (Piece(self.payload[:cut], self.start_ns, at_ns, self.frame, frames),
                Piece(self.payload[cut:], at_ns, self.end_ns, self.frame + frames, self.frames - frames))


def joined(pieces: list[Piece]) -> Piece:
    """Contiguous pieces as one."""
    if len(pieces) == 1:
        return pieces[0]
    return Piece(b"".join(p.payload for p in pieces), pieces[0].start_ns, pieces[-1].end_ns, pieces[0].frame,
                 sum(p.frames for p in pieces), pieces[-1].end_of_stream)


class ChunkCutter:
    """The energy backend's: each chunk is a piece, with its level."""

    def __init__(self) -> None:
        self._frame = 0

    def cut(self, payload: bytes, start_ns: int, end_ns: int, frames: int, level: float,
            end_of_stream: bool = False) -> list[tuple[Piece, float]]:
        piece = Piece(payload, start_ns, end_ns, self._frame, frames, end_of_stream)
        self._frame += frames
        return [(piece, level)]


class WindowCutter:
    """Cuts one stream's chunks at Silero's windows: each window the chunks complete comes out as a
    piece of audio with its speech probability; at the end of the stream, what is left of an
    incomplete window comes out too, with the last window's probability."""

    def __init__(self, silero: SileroStream, frame_bytes: int):
        self.silero, self.frame_bytes = silero, frame_bytes
        self._pending: deque[Piece] = deque()  # the audio of the window not yet complete
        self._pending_frames = 0
        self._frame = 0  # frames of the stream so far
        self._last = 0.0  # the last window's probability

    def cut(self, payload: bytes, start_ns: int, end_ns: int, mono: np.ndarray,
            end_of_stream: bool = False) -> list[tuple[Piece, float]]:
        """One chunk in (its payload, capture times and channel 0 as floats): the windows it completes out."""
        frames = len(mono)
        if frames:
            self._pending.append(Piece(payload, start_ns, end_ns, self._frame, frames))
            self._frame += frames
            self._pending_frames += frames
        out = [(self._take(self.silero.window), probability) for probability in self.silero.probabilities(mono)]
        if out:
            self._last = out[-1][1]
        if end_of_stream:
            rest = (self._take(self._pending_frames) if self._pending_frames
                    else Piece(b"", end_ns, end_ns, self._frame, 0))
            out.append((replace(rest, end_of_stream=True), self._last))
        return out

    def _take(self, frames: int) -> Piece:
        taken: list[Piece] = []
        self._pending_frames -= frames
        while frames:
            piece = self._pending.popleft()
            if piece.frames > frames:
                piece, rest = piece.split(frames, self.frame_bytes)
                self._pending.appendleft(rest)
            taken.append(piece)
            frames -= piece.frames
        return joined(taken)


@dataclass(frozen=True)
class Message:
    """A message to forward: pieces joined, and whether a segment ends with it."""

    piece: Piece
    forward: Forward[Piece]  # the last piece's: ended, segment, probability


def messages(forwards: list[Forward[Piece]], rate_hz: int) -> Iterator[Message]:
    """What the segmenter forwards, as messages: contiguous pieces together, each message ending
    where a segment ends or after ``MAX_MESSAGE_S`` of audio."""
    group: list[Piece] = []
    frames = 0
    for i, forward in enumerate(forwards):
        piece = forward.item
        group.append(piece)
        frames += piece.frames
        following = forwards[i + 1].item if i + 1 < len(forwards) else None
        if (forward.ended or following is None or following.frame != piece.frame + piece.frames
                or frames + following.frames > MAX_MESSAGE_S * rate_hz):
            yield Message(joined(group), forward)
            group, frames = [], 0
