"""How a message travels: its topic frame, and its frames sent and taken without waiting.

The frames are sent and taken with less Python per message than pyzmq's
``send_multipart``/``recv_multipart``: those combine their flags as enum members on every call (an
``enum.Flag`` union runs a few Python calls) and check each frame's type; the SDK's frames are bytes.

Paced at 20 ms the data thread runs these cold every chunk (bench/framework.py --profile).
The semantics are pyzmq's: a message is sent frame by frame with SNDMORE, and ZeroMQ delivers all of
it or none (only its first frame can meet the high-water mark: zmq.Again, nothing sent).
"""
from __future__ import annotations

from collections.abc import Sequence

import zmq

_NOBLOCK = int(zmq.NOBLOCK)
_MORE_NOBLOCK = int(zmq.SNDMORE | zmq.NOBLOCK)
_RCVMORE = int(zmq.RCVMORE)


def topic_frame(topic: str, stream_id: str | None = None) -> bytes:
    """Topics travel NUL-terminated, so subscribing to "vad" does not also match "vad2"; the stream
    follows, NUL-terminated too, so a SUB can take one stream of a topic (``topic\0stream\0``) or
    all of them (``topic\0``), and the producer's XPUB filters."""
    frame = topic.encode() + b"\0"
    return frame if stream_id is None else frame + stream_id.encode() + b"\0"


def topic_name(frame: bytes) -> str:
    return frame.split(b"\0", 1)[0].decode(errors="replace")


def send_frames(sock: zmq.Socket, frames: Sequence[bytes]) -> None:
    """Sends ``frames`` as one message without blocking; zmq.Again if refused."""
    last = len(frames) - 1
    for index, frame in enumerate(frames):
        sock.send(frame, _MORE_NOBLOCK if index < last else _NOBLOCK)


def recv_frames(sock: zmq.Socket, _flags: int = _NOBLOCK) -> list[bytes]:
    """The next message's frames without blocking; zmq.Again if none is waiting."""
    frames = [sock.recv(_NOBLOCK)]
    while sock.getsockopt(_RCVMORE):
        frames.append(sock.recv(_NOBLOCK))
    return frames
