"""The ZeroMQ sockets of one component (see docs/protocol.md).

- an XPUB bound for all output topics, so the component can count its subscribers; it refuses
  (rather than silently drops) at the high-water mark, so loss is counted;
- a SUB connected to the producers of the input topics, as the orchestrator names them;
- a PUSH to the orchestrator's results socket;
- an inproc PAIR on which the control thread hands over the orchestrator's state.

With CURVE keys (``ESIAF_CURVE_DIR``, esiaf/keys.py) the XPUB is a CURVE server that takes only the
allowed client keys, the SUB connects to each producer with the public key the orchestrator gave
with its endpoint (an allowed key, or no connection), and the PUSH to the orchestrator's key;
without, the PUSH presents the token (PLAIN), and the XPUB is a PLAIN server that takes only the
consumers the orchestrator named, with the token (esiaf/gate.py): the SUB presents its component id
and the token. The allowed keys are read again on SIGHUP (:meth:`Transport.reload_keys_soon`,
keys.reload_clients).

Flow control (docs/protocol.md): a replay's audio (a stream in ``replays``, esiaf/receiving.py) waits
for its consumers where live audio is dropped and counted: a SUB whose queue is full stops reading
its TCP connection, the XPUB's queue fills and refuses (XPUB_NODROP); the send waits on the socket's
ZMQ_FD (the consumer's credit) and the wake pipe (stop()). ``audio_queue`` bounds every queue. A
consumer that stops reading (frozen, or stuck in a handler) keeps its connection STALL_MS.

One thread uses a Transport: the component's data thread.
"""
from __future__ import annotations

import contextlib
import logging
import os
import re
import select
import socket
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any, TypeVar, cast

import zmq
from zmq.auth.thread import ThreadAuthenticator
from zmq.utils.monitor import recv_monitor_message

from esiaf import auth, keys
from esiaf.control_messages import parse_to_data_thread
from esiaf.frames import recv_frames, send_frames, topic_frame, topic_name  # topic_*: here of old
from esiaf.gate import ConsumerGate

if TYPE_CHECKING:
    from esiaf.proto import esiaf_pb2 as pb
    from esiaf.receiving import Replays

log = logging.getLogger(__name__)

STATE_ADDRESS = "inproc://esiaf-control-state"
AUDIO_HWM = 100_000  # messages queued per connection before loss (minutes of audio): the audio_queue default
RESULTS_HWM = 10_000
# With a bounded audio_queue (below AUDIO_HWM), each audio connection's kernel buffers too (the kernel would
# otherwise hold some MB, a minute of 16 kHz audio, ahead of the consumer)
BOUNDED_TCP_BUFFER_BYTES = 64 * 1024
# A producer's audio may go unacknowledged this long, not UNACKED_MS, before the connection is dropped: a
# consumer that does not read (frozen with SIGSTOP, a decode that holds it) closes its TCP window once its
# kernel buffer is full, and at 4 s a consumer frozen for 20 s was cut off and lost what was queued for it.
# Its queue meanwhile is bounded by audio_queue; a consumer cut off by the network notices at its end (it
# only receives: the kernel's keepalive probes) within seconds, and connects again
STALL_MS = 60_000
FLUSH_LINGER_MS = 2_000  # data sockets get this long to deliver the last messages at shutdown
REPLAY_LINGER_MS = 60_000  # ... a replay's producer that ended (not stopped): its slowest consumer's pace
ANY_HOST = ("0.0.0.0", "*", "::")
# a departed producer is dropped once it left this long ago and the input has been quiet this long: a
# consumer behind it (a loaded machine, a replay) may find its queue empty for a moment while the rest
# of the producer's audio is still in the kernel's buffers, and dropping it then loses that rest
LEAVE_GRACE_S = 1.0
LEAVE_LIMIT_S = STALL_MS / 1000  # ... and in any case this long after it left (other streams keep it busy)


# The kernel's TCP keepalive on every TCP socket, not ZMTP heartbeats (those would wake each
# process's libzmq I/O thread about three times a second per connection, most of an idle component's
# CPU): a peer cut off by the network (a cable, `docker network disconnect`) is noticed within seconds
# (an idle connection's probes go unanswered for KEEPALIVE_IDLE_S + KEEPALIVE_CNT * KEEPALIVE_INTVL_S;
# data goes unacknowledged for UNACKED_MS, TCP_USER_TIMEOUT) and the connection made again, instead
# of a half-open TCP connection swallowing messages until the kernel gives up on it (minutes). The
# probes are the kernel's: no process wakes while all is well. A peer whose process is frozen but
# whose kernel answers keeps its connection: the control plane's heartbeats find it (docs/protocol.md).
KEEPALIVE_IDLE_S = 1
KEEPALIVE_INTVL_S = 1
KEEPALIVE_CNT = 3
UNACKED_MS = 4_000


SocketT = TypeVar("SocketT", bound=zmq.Socket)


def keep_alive(sock: SocketT) -> SocketT:
    """Turns TCP keepalive on (before connect/bind): a connection cut off is dropped and redone."""
    sock.setsockopt(zmq.TCP_KEEPALIVE, 1)
    sock.setsockopt(zmq.TCP_KEEPALIVE_IDLE, KEEPALIVE_IDLE_S)
    sock.setsockopt(zmq.TCP_KEEPALIVE_INTVL, KEEPALIVE_INTVL_S)
    sock.setsockopt(zmq.TCP_KEEPALIVE_CNT, KEEPALIVE_CNT)
    sock.setsockopt(zmq.TCP_MAXRT, UNACKED_MS)
    return sock


_ENDPOINT = re.compile(r"^tcp://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]{1,253}):(\d{1,5})$")


def valid_endpoint(endpoint: str) -> bool:
    """``tcp://HOST:PORT`` with a port in 1..65535: the only endpoints components exchange."""
    match = _ENDPOINT.match(endpoint) if isinstance(endpoint, str) else None
    return match is not None and 0 < int(match.group(2)) < 65536


class TransportError(Exception):
    """A socket could not be bound: the message says which address."""


def _take(sock: zmq.Socket, receive: Callable[..., Any] = zmq.Socket.recv) -> Any:
    """``receive(sock)`` without blocking, or None if nothing was there after all."""
    try:
        return receive(sock, zmq.NOBLOCK)
    except zmq.Again:
        return None


def _nothing() -> None:
    pass


def _bound_buffers(sock: zmq.Socket, audio_queue: int, option: int) -> None:
    """A bounded audio queue bounds the kernel buffer too."""
    if audio_queue < AUDIO_HWM:
        sock.setsockopt(option, BOUNDED_TCP_BUFFER_BYTES)


class Transport:
    def __init__(self, context: zmq.Context, *, inputs: Iterable[str], has_outputs: bool,
                 bind_host: str, audio_port: int = 0, advertise_host: str = "", curve: keys.Curve | None = None,
                 audio_queue: int = AUDIO_HWM, replays: Replays | None = None, identity: str = ""):
        """``identity``: the component id a consumer presents to its producers (without CURVE keys)."""
        self._curve = curve
        self._replays = replays  # the streams whose audio and results wait for consumers (None: none)
        self._stopping = False  # stop(): no send waits any more
        self._replayed = False  # a replay's audio was sent: at its end (not stopped) it gets REPLAY_LINGER_MS
        self._clients = curve.clients if curve is not None else frozenset()  # SIGHUP reads them again
        self._reload = False  # SIGHUP came: read the allowed keys again at the next poll
        self._authenticator: ThreadAuthenticator | None = None
        self._gate: ConsumerGate | None = None  # without CURVE keys: the consumers the orchestrator named
        self._refusals: zmq.Socket | None = None  # the XPUB's monitor: subscribers refused at the handshake
        self._poller = zmq.Poller()
        self._connected: set[str] = set()
        self._leaving: dict[str, float] = {}  # producers gone, still to be drained: endpoint -> since (monotonic)
        self._heard_at = 0.0  # monotonic time audio last came in
        self._results_endpoint = ""
        # called whenever audio or results move (the control client's busy(): it keeps the heartbeat fast)
        self.on_busy: Callable[[], None] = _nothing
        self.state = context.socket(zmq.PAIR)
        self.state.setsockopt(zmq.LINGER, 0)
        self.state.bind(STATE_ADDRESS)
        self._poller.register(self.state, zmq.POLLIN)
        self.pub: zmq.Socket | None = None
        self.sub: zmq.Socket | None = None
        if has_outputs:
            self._open_output(context, bind_host, audio_port, audio_queue)
        topics = list(inputs)
        if topics:
            self._open_input(context, topics, audio_queue, identity)
        self._topics = topics
        self._streams: list[str] | None = None  # the streams taken: None, all of them
        # stop() from a signal handler or another thread writes here: a poll that waits long ends at once
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_read, False)
        os.set_blocking(self._wake_write, False)
        self._poller.register(self._wake_read, zmq.POLLIN)
        self.push = keep_alive(context.socket(zmq.PUSH))
        auth.secure_socket(self.push, curve)  # the orchestrator's results socket takes only known peers
        self.push.setsockopt(zmq.LINGER, FLUSH_LINGER_MS)
        self.push.setsockopt(zmq.SNDHWM, RESULTS_HWM)
        self._advertised_host = advertise_host or (socket.gethostname() if bind_host in ANY_HOST else bind_host)

    def _open_output(self, context: zmq.Context, bind_host: str, audio_port: int, audio_queue: int) -> None:
        """The XPUB the outputs' audio goes out on (a CURVE server with keys, else a PLAIN one), bound; raises
        TransportError."""
        curve = self._curve
        self.pub = keep_alive(context.socket(zmq.XPUB))
        self.pub.setsockopt(zmq.LINGER, FLUSH_LINGER_MS)
        self.pub.setsockopt(zmq.SNDHWM, audio_queue)
        _bound_buffers(self.pub, audio_queue, zmq.SNDBUF)
        self.pub.setsockopt(zmq.TCP_MAXRT, STALL_MS)
        self.pub.setsockopt(zmq.XPUB_VERBOSER, 1)
        self.pub.setsockopt(zmq.XPUB_NODROP, 1)
        if curve is not None:  # a CURVE server: only consumers with an allowed key may subscribe
            self._authenticator = ThreadAuthenticator(context)
            self._authenticator.start()
            self._authenticator.configure_curve(domain="*", location=str(curve.clients_dir))
            keys.server(self.pub, curve)
        else:  # a PLAIN server: only the consumers the orchestrator named, with the token
            self._gate = ConsumerGate(context, auth.token())
            self.pub.plain_server = True
        self._refusals = self.pub.get_monitor_socket(sum(keys.HANDSHAKE_FAILURES))
        self._poller.register(self._refusals, zmq.POLLIN)
        try:
            if audio_port:
                self.pub.bind(f"tcp://{bind_host}:{audio_port}")
            else:
                self.pub.bind_to_random_port(f"tcp://{bind_host}")
        except zmq.ZMQError as exc:
            self.close()
            where = f"{bind_host}:{audio_port or 'any port'}"
            raise TransportError(f"cannot bind audio output on {where}: {exc}") from None
        self._poller.register(self.pub, zmq.POLLIN)

    def _open_input(self, context: zmq.Context, topics: list[str], audio_queue: int, identity: str) -> None:
        """The SUB the inputs' audio comes in on, subscribed to ``topics`` (connected later)."""
        self.sub = keep_alive(context.socket(zmq.SUB))
        self.sub.setsockopt(zmq.LINGER, 0)
        self.sub.setsockopt(zmq.RCVHWM, audio_queue)
        _bound_buffers(self.sub, audio_queue, zmq.RCVBUF)
        if self._curve is None:  # who we are to producers (esiaf/gate.py), with the token if there is one
            self.sub.plain_username = (identity or "anonymous").encode()
            if token := auth.token():
                self.sub.plain_password = token.encode()
        for topic in topics:
            self.sub.setsockopt(zmq.SUBSCRIBE, topic_frame(topic))
        self._poller.register(self.sub, zmq.POLLIN)

    @property
    def audio_endpoint(self) -> str | None:
        """Where consumers reach this component's outputs (None without outputs)."""
        if self.pub is None:
            return None
        port = self.pub.getsockopt_string(zmq.LAST_ENDPOINT).rsplit(":", 1)[1]
        return f"tcp://{self._advertised_host}:{port}"

    @property
    def audio_public_key(self) -> str | None:
        """With CURVE keys, the public key consumers need to reach this component's outputs."""
        return self._curve.public.decode() if self._curve is not None and self.pub is not None else None

    def events(self, timeout_ms: float, take_audio: bool = True) -> Iterator[tuple[str, Any]]:
        """What is ready, waiting up to ``timeout_ms`` for the first: ("state", LocalState | Fatal),
        ("subscription", (topic, +1 | -1)), ("refused", reason) for a subscriber refused at the
        handshake (with CURVE keys) and, if ``take_audio``, ("audio", frames)."""
        if self._leaving and take_audio:
            self._drop_departed()
        if self._leaving:  # departed producers are dropped once their grace period is over
            timeout_ms = min(timeout_ms, LEAVE_GRACE_S * 1000)
        ready = dict(self._poller.poll(timeout=int(timeout_ms)))  # what pyzmq makes of a float
        while ready:
            if ready.pop(self._wake_read, None):
                self._drain_wake()
                if self._reload:
                    self._reload_keys()
            # libzmq may say a socket is readable when it is not: each is read without blocking
            if self.state in ready and (frame := _take(self.state)) is not None:
                yield "state", parse_to_data_thread(frame)  # our own heartbeat thread's: a bug if refused
            if self.pub is not None and self.pub in ready and (frame := _take(self.pub)) is not None:
                yield "subscription", (topic_name(frame[1:]), 1 if frame[:1] == b"\x01" else -1)
            if self._refusals is not None and self._refusals in ready and (
                    event := _take(self._refusals, recv_monitor_message)) is not None:
                yield "refused", keys.HANDSHAKE_FAILURES.get(event["event"], "other")
            if self.sub is not None and self.sub in ready and take_audio and (
                    frames := _take(self.sub, recv_frames)) is not None:
                self.on_busy()
                self._heard_at = time.monotonic()
                yield "audio", frames
            ready = dict(self._poller.poll(timeout=0))
            if not take_audio:
                ready.pop(self.sub, None)

    def name_consumers(self, source: str, consumers: list[str] | None) -> None:
        """The consumers the orchestrator named in ``source``'s state (this component's, or a guest's that
        publishes through its socket): the only subscribers the audio output takes without CURVE keys
        (None: it named none, any subscriber with the token). Safe from any thread."""
        if self._gate is not None:
            self._gate.name(source, consumers if isinstance(consumers, list) else None)

    def reload_keys_soon(self) -> None:
        """SIGHUP: the allowed client keys are read again at the next poll, on the data thread
        (which owns the ZAP handler's pipe); safe from a signal handler."""
        self._reload = True
        self.wake()

    def _reload_keys(self) -> None:
        self._reload = False
        allowed = keys.reload_clients(self._curve, self._authenticator)
        if allowed is not None:
            self._clients = allowed

    def stop(self) -> None:
        """The component is stopping: a wait for input or for a consumer's room ends now, and no send
        waits any more (safe from any thread and from signal handlers)."""
        self._stopping = True
        self.wake()

    def wake(self) -> None:
        """Ends a wait in :meth:`events` now (safe from any thread and from signal handlers)."""
        with contextlib.suppress(OSError):  # full (already woken) or closed
            os.write(self._wake_write, b"!")

    def _drain_wake(self) -> None:
        try:
            while os.read(self._wake_read, 4096):
                pass
        except OSError:  # empty
            pass

    def take_streams(self, streams: Sequence[str] | None) -> None:
        """Takes only these streams of the input topics (None: all), as the orchestrator assigns
        them to this instance of a replicated service: subscribes to the new ones before it drops
        the old ones, so a stream that stays is never missed."""
        wanted = None if streams is None else sorted({s for s in streams if isinstance(s, str)})
        if self.sub is None or wanted == self._streams:
            return
        def frames(streams: list[str] | None) -> set[bytes]:
            return {topic_frame(t) for t in self._topics} if streams is None else \
                {topic_frame(t, s) for t in self._topics for s in streams}
        before, after = frames(self._streams), frames(wanted)
        for frame in after - before:
            self.sub.setsockopt(zmq.SUBSCRIBE, frame)
        for frame in before - after:
            self.sub.setsockopt(zmq.UNSUBSCRIBE, frame)
        log.info("streams taken: %s", "all" if wanted is None else ", ".join(wanted) or "none")
        self._streams = wanted

    def send_audio(self, topic: str, message: pb.AugmentedAudio) -> tuple[bool, list[bytes]]:
        """Sends a message on ``topic``: whether it went (False if refused at the high-water mark; a
        replay's message is marked so and waits for room instead, False only if stop() came first), and
        its frames as sent."""
        assert self.pub is not None, "audio sent without a declared output"
        replay = self._replays is not None and self._replays.mark(message)
        self._replayed |= replay
        frames = [topic_frame(topic, message.stream_id), message.SerializeToString()]
        return self._send(self.pub, frames, replay), frames

    def send_results(self, frames: Sequence[bytes], stream_id: str = "") -> bool:
        """False if the orchestrator is not taking results (queue full); a replay's results wait for room."""
        return self._send(self.push, frames, self._replays is not None and stream_id in self._replays)

    def _send(self, sock: zmq.Socket, frames: Sequence[bytes], wait: bool) -> bool:
        """Sends without blocking; if refused and ``wait``, waits until the peer has taken enough (libzmq's
        activate_write command signals the socket's ZMQ_FD) or stop() (the wake pipe), and tries again:
        no timeout, nothing wakes while the peer is stalled. (An XPUB says POLLOUT even while full.)"""
        while True:
            try:
                send_frames(sock, frames)
            except zmq.Again:
                if not wait or self._stopping:
                    return False
            else:
                self.on_busy()
                return True
            room = select.poll()  # made once a wait: the consumer takes half its queue between two
            room.register(cast(int, sock.getsockopt(zmq.FD)), select.POLLIN)
            room.register(self._wake_read, select.POLLIN)
            if any(fd == self._wake_read for fd, _ in room.poll()):
                self._drain_wake()
                if self._reload:
                    self._reload_keys()
            sock.getsockopt(zmq.EVENTS)  # libzmq takes its commands (the peer's credit) before the next try

    def connect_peers(self, wanted: set[str], peer_keys: dict[str, str] | None = None) -> None:
        """Connects the input socket to exactly these producer endpoints (with CURVE keys, each
        with the producer's public key in ``peer_keys``, which must be an allowed client key).

        A producer that has gone is disconnected only once its queued messages have been taken
        (no input pending, and none for LEAVE_GRACE_S, LEAVE_GRACE_S after it went; LEAVE_LIMIT_S after
        it went in any case): a slow consumer keeps the end of a stream, and libzmq never tears down a
        pipe that still holds a message.
        """
        if self.sub is None:
            return
        for endpoint in wanted & self._leaving.keys():  # back before it was dropped: it stays connected
            del self._leaving[endpoint]
        refused = set()
        for endpoint in wanted - self._connected:
            try:
                if not valid_endpoint(endpoint):
                    raise ValueError("tcp://HOST:PORT expected")
                if self._curve is not None:
                    self._secure_input(self.sub, self._curve, self._clients,
                                       peer_keys.get(endpoint) if isinstance(peer_keys, dict) else None)
                self.sub.connect(endpoint)
            except (ValueError, zmq.ZMQError) as exc:  # what a peer registered is never fatal here
                log.error("not connecting to producer endpoint=%.200r: %s", endpoint, exc)
                refused.add(endpoint)
                continue
            self._leaving.pop(endpoint, None)
            log.info("connected to producer endpoint=%s", endpoint)
        wanted = wanted - refused
        for endpoint in self._connected - wanted:
            self._leaving.setdefault(endpoint, time.monotonic())
        self._connected = set(wanted) | set(self._leaving)
        self._drop_departed()

    @staticmethod
    def _secure_input(sub: zmq.Socket, curve: keys.Curve, clients: frozenset[bytes], key: object) -> None:
        """Sets the server key of the next connect: libzmq takes the options at each connect."""
        if not isinstance(key, str) or key.encode() not in clients:
            raise ValueError(f"its CURVE public key {str(key)[:40]!r} is not one of those in {curve.clients_dir}")
        auth.secure_socket(sub, curve, key.encode())

    def _drop_departed(self) -> None:
        if self.sub is None or not self._leaving or cast(int, self.sub.getsockopt(zmq.EVENTS)) & zmq.POLLIN:
            return
        now = time.monotonic()
        for endpoint, since in list(self._leaving.items()):
            quiet = now - self._heard_at >= LEAVE_GRACE_S
            if now - since >= LEAVE_LIMIT_S or (now - since >= LEAVE_GRACE_S and quiet):
                del self._leaving[endpoint]
                self._connected.discard(endpoint)
                self.sub.disconnect(endpoint)
                log.info("disconnected from producer endpoint=%s", endpoint)

    def connect_results(self, endpoint: str) -> None:
        if endpoint and endpoint != self._results_endpoint:
            if not valid_endpoint(endpoint):
                log.error("not connecting to a bad results endpoint=%.200r", endpoint)
                return
            if self._results_endpoint:
                self.push.disconnect(self._results_endpoint)
            self.push.connect(endpoint)
            self._results_endpoint = endpoint

    def close(self) -> None:
        if self.pub is not None and not self.pub.closed and self._replayed and not self._stopping:
            self.pub.setsockopt(zmq.LINGER, REPLAY_LINGER_MS)  # the end of a file: all of it reaches the consumers
        for sock in (self.state, self._refusals, self.sub, self.pub, self.push):
            if sock is not None and not sock.closed:
                sock.close()
        if self._authenticator is not None:
            self._authenticator.stop()
            self._authenticator = None
        if self._gate is not None:
            self._gate.close()
            self._gate = None
        for fd in (self._wake_read, self._wake_write):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._wake_read = self._wake_write = -1
