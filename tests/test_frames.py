"""esiaf/frames.py: messages sent and taken frame by frame, over real sockets on loopback."""
import time

import pytest
import zmq

from esiaf.frames import recv_frames, send_frames, topic_frame, topic_name


@pytest.fixture
def context():
    ctx = zmq.Context()
    yield ctx
    ctx.term()


def wait_for(sock: zmq.Socket, timeout_s: float = 5.0) -> list[bytes]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if sock.poll(100):
            return recv_frames(sock)
    raise AssertionError("no message within the deadline")


@pytest.mark.parametrize("frames", [[b"only"], [topic_frame("grabber/audio", "s"), b"\x00" * 640],
                                    [b"a", b"", b"c" * 70_000]])
def test_a_message_arrives_whole_with_its_frames_in_order(context, frames):
    pull, push = context.socket(zmq.PULL), context.socket(zmq.PUSH)
    for sock in (pull, push):
        sock.setsockopt(zmq.LINGER, 0)
    port = pull.bind_to_random_port("tcp://127.0.0.1")
    push.connect(f"tcp://127.0.0.1:{port}")
    try:
        send_frames(push, frames)
        send_frames(push, [b"next"])
        assert wait_for(pull) == frames
        assert wait_for(pull) == [b"next"]  # the first message's frames did not run into the second
    finally:
        pull.close()
        push.close()


def test_nothing_waiting_and_no_room_are_zmq_again_and_leave_no_half_message(context):
    pull, push = context.socket(zmq.PULL), context.socket(zmq.PUSH)
    for sock in (pull, push):
        sock.setsockopt(zmq.LINGER, 0)
    port = pull.bind_to_random_port("tcp://127.0.0.1")
    try:
        with pytest.raises(zmq.Again):
            recv_frames(pull)
        with pytest.raises(zmq.Again):  # no peer yet: a PUSH has no room
            send_frames(push, [b"refused", b"whole"])
        push.connect(f"tcp://127.0.0.1:{port}")
        send_frames(push, [b"taken", b"whole"])
        assert wait_for(pull) == [b"taken", b"whole"]
    finally:
        pull.close()
        push.close()


def test_topic_frames_name_their_topic_and_stream():
    assert topic_frame("vad") == b"vad\0"
    assert topic_frame("vad/speech", "robot-1") == b"vad/speech\0robot-1\0"
    assert topic_name(topic_frame("vad/speech", "robot-1")) == "vad/speech"
    assert topic_name(b"\xff\xfe\0") == "\ufffd\ufffd"  # a peer's bytes never fail to decode
