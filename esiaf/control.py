"""Registration with the orchestrator and the heartbeat thread.

Registration is HTTP (``POST /components``), retried with exponential back-off
until ``register_timeout_s``. After it, a thread owns a DEALER socket (its
routing id left to the orchestrator's ROUTER): it sends a heartbeat, which names the component
and carries the registration's ``control_key``, every ``heartbeat_interval_s`` (at once when
:meth:`ControlClient.poke` is called, and on a connection made again); once idle for
``idle_heartbeat_interval_s`` it beats that often instead, until :meth:`ControlClient.busy` says
audio or results moved. It passes every state message the orchestrator pushes or answers with
(peers and formats), and every command it sends (a player's orders), to the data thread through an
inproc PAIR socket. Each heartbeat gives back the
number of the last state applied; while it is current the answer is a short ``ack``, and the data
thread sleeps on. When the
orchestrator answers ``unknown`` (it restarted, or thought us dead) the thread
registers again; so it does when the orchestrator has been silent for longer
than ``dead_after_s`` (plus the idle interval's extra: it died, or came back on other ports), and it
keeps trying for as long as the component runs. See docs/protocol.md.

With a ``health_file``, the thread touches that file whenever the orchestrator
answers (registration, state, heartbeat replies): its age tells a container's
healthcheck (``python -m esiaf.tools.health``) that the component is registered and heard.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import httpx
import zmq

from esiaf import auth
from esiaf.api_client import OrchestratorHTTP, transient, why
from esiaf.clock import ClockEstimate
from esiaf.control_messages import (
    Ack,
    BeatNow,
    Command,
    Fatal,
    Heartbeat,
    LocalState,
    MessageError,
    State,
    Unknown,
    encode,
    parse_to_component,
)
from esiaf.keys import Curve
from esiaf.transport import STATE_ADDRESS, keep_alive

log = logging.getLogger(__name__)



class RegistrationError(Exception):
    """The orchestrator refused us (``refused``), or could not be reached in time."""

    def __init__(self, message: str, refused: bool = False):
        super().__init__(message)
        self.refused = refused


@dataclass
class Registration:
    component_id: str
    control_endpoint: str
    results_endpoint: str
    heartbeat_interval_s: float
    dead_after_s: float
    # the interval to beat at once idle for as long (0: an orchestrator that does not know it: never slower)
    idle_heartbeat_interval_s: float = 0.0
    control_key: str = ""  # this registration's control secret: every control message carries it
    key_id: str = ""  # names this registration: results carry it with a MAC keyed with control_key
    peers: dict[str, list[str]] = field(default_factory=dict)
    formats: dict[str, dict[str, Any]] = field(default_factory=dict)
    peer_keys: dict[str, str] = field(default_factory=dict)  # producer endpoint -> its CURVE public key
    streams: list[str] | None = None  # one of several instances of its service: the streams it serves
    # with outputs: the components the orchestrator names as their consumers, the only subscribers the audio
    # output takes (esiaf/gate.py); None from an orchestrator that names none
    consumers: list[str] | None = None
    # the number of the last state the orchestrator sent and we applied (0: none yet, the next answer
    # is the full state); every heartbeat gives it back, and an unchanged state is answered with an ack
    state_version: int = 0

    def local_state(self) -> LocalState:
        """What the data thread is to connect to."""
        return LocalState(peers=self.peers, formats=self.formats, peer_keys=self.peer_keys,
                          results_endpoint=self.results_endpoint, component_id=self.component_id,
                          streams=self.streams, consumers=self.consumers)


def register(url: str, request: dict[str, Any], timeout_s: float,
             stopping: Callable[[], bool] = lambda: False) -> Registration:
    """POSTs the registration, retrying while the orchestrator is unreachable or answers 5xx, and
    while our instance id is still held by a live instance (409 with Retry-After: ours, before a
    crash, until it is declared dead)."""
    said: list[str] = []

    def waiting(why: str) -> None:
        if not said:
            log.info("waiting for orchestrator url=%s error=%s (trying again for up to %g s)", url, why, timeout_s)
        said.append(why)

    with OrchestratorHTTP(url) as http:
        try:
            response = http.request("POST", "/components", json=request, retry_for_s=timeout_s, stopping=stopping,
                                    on_retry=waiting)
        except httpx.HTTPError as exc:
            raise RegistrationError(f"orchestrator at {url} not reachable after {timeout_s:g} s ({http.attempts} "
                                    f"attempts): {str(exc) or type(exc).__name__}") from None
        attempts = http.attempts
    if response.status_code == 201:
        data = response.json()
        return Registration(**{k: data[k] for k in Registration.__dataclass_fields__ if k in data})
    if transient(response):
        raise RegistrationError(f"orchestrator at {url} not reachable after {timeout_s:g} s ({attempts} attempts): "
                                f"{why(response)}")
    raise RegistrationError(f"orchestrator at {url} refused registration ({response.status_code}): {why(response)}",
                            refused=True)


def unregister(url: str, component_id: str) -> None:
    try:
        with OrchestratorHTTP(url, timeout_s=2.0) as http:
            http.delete(f"/components/{component_id}")
    except httpx.HTTPError as exc:
        log.info("could not unregister component_id=%s error=%s", component_id, exc)


def _jsonable(value: Any) -> Any:
    """Heartbeat stats may hold numpy numbers or arrays (an analyser's ``info``): sent as numbers
    and lists; anything else as its text."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if hasattr(value, "item"):
        return value.item()
    return str(value)


_ENCODER = json.JSONEncoder(default=_jsonable)  # one for every heartbeat: json.dumps(default=) makes one each call


@dataclass
class _Pace:
    """The heartbeat thread's clocks and flags (monotonic seconds; only that thread uses them)."""

    last_heard: float  # when the orchestrator last sent anything
    seen_activity: int  # ControlClient.busy()'s count at the last beat
    quiet_since: float = field(init=False)  # since when there has been nothing to do
    next_beat: float = 0.0
    # the orchestrator answers every beat: silent for dead_after_s plus this (how much longer than the
    # fast interval the beats since the last answer were) means it is gone
    extra_silence_s: float = 0.0
    poked: bool = True  # ControlClient.poke() (or a start): beat now
    beat_now: bool = True  # the orchestrator asked, or a connection was made again: beat now

    def __post_init__(self) -> None:
        self.quiet_since = self.last_heard


class ControlClient:
    """Keeps the component registered and alive; runs in its own thread."""

    def __init__(self, context: zmq.Context, url: str, request: dict[str, Any],
                 stats: Callable[[], dict[str, Any]], register_timeout_s: float, health_file: str = "",
                 curve: Curve | None = None, clock_ns: Callable[[], int] = time.time_ns):
        self._context = context
        self._clock_ns = clock_ns  # this host's clock, as capture times are stamped with it
        self.clock = ClockEstimate()  # the orchestrator's clock against it, from the heartbeats' round trips
        self._curve = curve
        self._health_file = health_file
        self._url = url
        self._request = dict(request, pid=os.getpid())
        self._stats = stats
        self._register_timeout_s = register_timeout_s
        self._stop = threading.Event()
        # poke() and stop() write a byte here: the heartbeat thread sleeps in one poll until the
        # next beat is due or something is worth reporting, instead of waking every few ms
        self._wake_read, self._wake_write = os.pipe()
        os.set_blocking(self._wake_write, False)
        self._thread: threading.Thread | None = None
        self.registration: Registration | None = None
        # busy() counts the data thread's work; while the heartbeat is slow (idle), it wakes the thread
        self._activity = 0
        self._slow = False
        self.interval_s = 0.0  # the interval the last heartbeat said it beats at
        self._monitor: zmq.Socket | None = None  # the DEALER's: connections made
        self._polling = zmq.Poller()  # the DEALER, the wake pipe and the monitor
        self.bad_messages = 0  # messages from the orchestrator that were not one (counted, logged, ignored)
        self._handshakes = 0  # ... on this DEALER
        self._quiet_s = 0.0  # quiet_for(): the data thread may hold the GIL this long; the beat says so
        self._quiet_said = threading.Event()

    @property
    def component_id(self) -> str:
        return self.registration.component_id if self.registration else ""

    @property
    def _registered(self) -> Registration:
        """The registration: start() makes it (before the heartbeat thread starts), re-registering renews it."""
        if self.registration is None:
            raise RuntimeError("the control client is used before start() registered")
        return self.registration

    def start(self) -> Registration:
        """Registers (blocking, with retries) and starts the heartbeat thread."""
        self.registration = register(self._url, self._request, self._register_timeout_s, self._stop.is_set)
        log.info("registered component_id=%s peers=%s", self.component_id, self.registration.peers)
        self._heard()
        self._thread = threading.Thread(target=self._run, name="esiaf-control", daemon=True)
        self._thread.start()
        return self.registration

    def poke(self) -> None:
        """Sends a heartbeat now (something worth reporting changed)."""
        self._wake()

    def busy(self) -> None:
        """The data thread moved audio or results: the heartbeat stays at (or, now, goes back to)
        its fast interval. Cheap enough for every chunk."""
        self._activity += 1
        if self._slow:
            self._slow = False
            self._wake()

    @contextlib.contextmanager
    def quiet_for(self, seconds: float) -> Iterator[None]:
        """Around a native call that holds the GIL (pocketsphinx's decoder does not release it) for up to
        ``seconds``: a heartbeat says first that the next may come that much later (at most the idle
        interval later, the most the orchestrator allows), so neither side takes the silence for a
        death; after it, a beat at the fast interval at once."""
        if self.registration is None or not self._thread or seconds <= self._registered.heartbeat_interval_s:
            yield
            return
        self._quiet_s, self._quiet_said = seconds, threading.Event()
        self._wake()
        self._quiet_said.wait(timeout=0.5)  # the thread beats within a millisecond unless it is stuck itself
        try:
            yield
        finally:
            self._quiet_s = 0.0
            self._wake()

    def _interval(self, now: float, quiet_since: float) -> float:
        """The fast interval, or the idle one after an idle interval with nothing to do."""
        fast, idle = self._registered.heartbeat_interval_s, self._registered.idle_heartbeat_interval_s
        self._slow = idle > fast and now - quiet_since >= idle
        return max(idle if self._slow else fast, min(self._quiet_s, idle))

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # BlockingIOError: the pipe is full, the thread is woken already
            os.write(self._wake_write, b"!")

    def stop(self, unregister_too: bool = True) -> None:
        self._stop.set()
        self._wake()
        if self._thread:
            self._thread.join(timeout=3.0)
        if unregister_too and self.registration:
            unregister(self._url, self.component_id)
        for fd in (self._wake_read, self._wake_write):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _heard(self) -> None:
        """The orchestrator answered: freshens the health file, if there is one."""
        if not self._health_file:
            return
        try:
            with open(self._health_file, "a"):
                os.utime(self._health_file)
        except OSError as exc:
            log.warning("cannot touch health_file=%s: %s", self._health_file, exc.strerror)
            self._health_file = ""

    def _dealer(self) -> zmq.Socket:
        dealer = keep_alive(self._context.socket(zmq.DEALER))
        auth.secure_socket(dealer, self._curve)
        dealer.setsockopt(zmq.LINGER, 0)
        # no IDENTITY: the ROUTER gives each connection a routing id no peer can claim, and the
        # heartbeat says who we are and proves it with the control key
        # its monitor says when a connection is made (again): a beat then, so that the orchestrator,
        # which saw the old one close, hears from the new one within its disconnect grace period
        self._monitor = dealer.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
        self._handshakes = 0
        dealer.connect(self._registered.control_endpoint)
        self._polling = self._poller(dealer)
        return dealer

    def _close(self, dealer: zmq.Socket) -> None:
        if self._monitor is not None:
            dealer.disable_monitor()
            self._monitor.close(linger=0)
            self._monitor = None
        dealer.close()

    def _run(self) -> None:
        """The heartbeat thread: beat when due, wait for an answer, a poke or the next beat, apply what
        came; register again when the orchestrator forgot us or fell silent."""
        state_out = self._context.socket(zmq.PAIR)
        state_out.setsockopt(zmq.LINGER, 0)
        state_out.connect(STATE_ADDRESS)
        dealer = self._dealer()
        pace = _Pace(time.monotonic(), self._activity)
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                if now - pace.last_heard > self._registered.dead_after_s + pace.extra_silence_s:
                    log.warning("orchestrator silent for %.1f s: registering again", now - pace.last_heard)
                    dealer = self._renew(dealer, state_out, pace)
                    continue
                if now >= pace.next_beat or pace.poked or pace.beat_now:
                    self._beat(dealer, pace, now)
                if self._wait(dealer, pace):
                    dealer = self._take(dealer, state_out, pace)
        except RegistrationError as exc:  # refused: the orchestrator will not have us any more
            log.error("%s", exc)
            state_out.send(encode(Fatal(error=str(exc))))
        except Exception as exc:  # a bug here must not leave the component running unregistered
            log.exception("heartbeat thread failed")
            state_out.send(encode(Fatal(error=f"heartbeat thread failed: {type(exc).__name__}: {exc}")))
        finally:
            self._close(dealer)
            state_out.close()

    def _beat(self, dealer: zmq.Socket, pace: _Pace, now: float) -> None:
        """Sends a heartbeat, at the fast interval or (idle) the slow one."""
        if pace.poked or self._activity != pace.seen_activity:
            pace.seen_activity, pace.quiet_since = self._activity, now
        self.interval_s = self._interval(now, pace.quiet_since)
        pace.extra_silence_s = max(pace.extra_silence_s, self.interval_s - self._registered.heartbeat_interval_s)
        beat = Heartbeat(component_id=self.component_id, control_key=self._registered.control_key,
                         stats=self._stats(), sent_ns=self._clock_ns(), clock=self.clock.report(),
                         state_version=self._registered.state_version, interval_s=self.interval_s)
        # model_dump, not encode(): stats may hold numpy numbers (an analyser's info), which _ENCODER takes
        dealer.send(_ENCODER.encode(beat.model_dump(exclude_none=True)).encode())
        pace.next_beat, pace.beat_now = now + self.interval_s, False
        if not self._quiet_said.is_set():  # set() takes a lock and notifies, at every beat
            self._quiet_said.set()

    def _wait(self, dealer: zmq.Socket, pace: _Pace) -> bool:
        """Sleeps until the next beat (or the orchestrator's silence deadline), a message or a poke;
        notes pokes and connections made again. True if the dealer has something to read."""
        wait_s = max(0.0, min(pace.next_beat, pace.last_heard + self._registered.dead_after_s + pace.extra_silence_s)
                     - time.monotonic())
        ready = dict(self._polling.poll(timeout=max(1, round(wait_s * 1000))))
        pace.poked = self._wake_read in ready
        if pace.poked:
            os.read(self._wake_read, 4096)
        if self._monitor is not None and self._monitor in ready:
            with contextlib.suppress(zmq.Again):
                while self._monitor.recv_multipart(zmq.NOBLOCK):
                    self._handshakes += 1
                    pace.beat_now = pace.beat_now or self._handshakes > 1  # again: the first took what was queued
        return dealer in ready

    def _take(self, dealer: zmq.Socket, state_out: zmq.Socket, pace: _Pace) -> zmq.Socket:
        """Takes one message from the orchestrator and acts on it; returns the dealer (a new one if it
        registered again)."""
        try:
            data = dealer.recv(zmq.NOBLOCK)
        except zmq.Again:  # libzmq may say it is readable when it is not
            return dealer
        received_ns = self._clock_ns()
        pace.last_heard = time.monotonic()  # anything it sends is life, even what we cannot read
        pace.extra_silence_s = self.interval_s - self._registered.heartbeat_interval_s
        self._heard()
        try:
            message = parse_to_component(data)
        except MessageError as exc:
            self._bad(str(exc), len(data))
            return dealer
        if isinstance(message, (State, Ack)) and message.echo_ns is not None and message.orchestrator_ns is not None:
            self.clock.add(message.echo_ns, message.orchestrator_ns, received_ns)
        if isinstance(message, State):  # the full state (an Ack: ours is still current)
            self._apply(message, state_out)
            pace.quiet_since = pace.last_heard  # a new state is something to do
            if self._slow:  # fast again, from a beat now
                pace.next_beat = pace.last_heard
        elif isinstance(message, BeatNow):  # the orchestrator saw a connection of ours close
            pace.beat_now = True
        elif isinstance(message, Command):  # an order: the data thread carries it out, in order with its work
            state_out.send(encode(message))
        elif isinstance(message, Unknown):
            log.warning("orchestrator does not know component_id=%s: registering again", self.component_id)
            return self._renew(dealer, state_out, pace)
        return dealer

    def _apply(self, state: State, state_out: zmq.Socket) -> None:
        """Keeps a new state and hands it to the data thread."""
        registration = self._registered
        registration.state_version = state.version or 0
        registration.peers, registration.formats = state.peers, {t: dict(f) for t, f in state.formats.items()}
        registration.peer_keys, registration.streams = state.peer_keys or {}, state.streams
        registration.consumers = state.consumers
        state_out.send(encode(registration.local_state()))

    def _bad(self, reason: str, size: int) -> None:
        """Counts a message from the orchestrator that is not one; logs the first and every 100th."""
        self.bad_messages += 1
        if self.bad_messages == 1 or self.bad_messages % 100 == 0:
            log.warning("ignored a control message (%d bytes, count %d): %s", size, self.bad_messages, reason)

    def _renew(self, dealer: zmq.Socket, state_out: zmq.Socket, pace: _Pace) -> zmq.Socket:
        """Registers again, on a new connection; the pace starts afresh."""
        self._close(dealer)
        self._register_again(state_out)
        dealer = self._dealer()
        pace.last_heard = pace.next_beat = pace.quiet_since = time.monotonic()
        return dealer

    def _poller(self, dealer: zmq.Socket) -> zmq.Poller:
        poller = zmq.Poller()
        poller.register(dealer, zmq.POLLIN)
        poller.register(self._wake_read, zmq.POLLIN)
        if self._monitor is not None:
            poller.register(self._monitor, zmq.POLLIN)
        return poller

    def _register_again(self, state_out: zmq.Socket) -> None:
        """Registers until it works (the component goes on meanwhile); raises only if refused."""
        while not self._stop.is_set():
            try:
                self.registration = register(self._url, self._request, self._register_timeout_s, self._stop.is_set)
            except RegistrationError as exc:
                if exc.refused:
                    raise
                log.error("%s; still trying", exc)
                continue
            log.info("registered again component_id=%s", self.component_id)
            state_out.send(encode(self._registered.local_state()))
            return
