"""CURVE across hosts: keys made by ``esiaf keys``, the real orchestrator started with
them, components with allowed keys registering, exchanging audio and storing results; peers with
no keys or unknown ones refused and counted; bad key files refused at start-up with one line."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import zmq
import zmq.auth
from zmq.utils.monitor import recv_monitor_message

from esiaf import keys
from esiaf.component import SetupError
from esiaf.results import make_result
from esiaf.tools.testing import (
    REPO,
    Orchestrator,
    free_port,
    poll,
    refused_control,
    refused_messages,
    refused_peers,
    signed_result,
)
from esiaf.transport import Transport
from tests.test_component import Sink, Source, run_on, start


def make_keys(directory: Path, *names: str) -> subprocess.CompletedProcess:
    args = [arg for name in names for arg in ("--component", name)]
    return subprocess.run([sys.executable, "-m", "esiaf", "keys", str(directory), *args], cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=60)


@pytest.fixture
def curve_dir(tmp_path) -> Path:
    made = make_keys(tmp_path / "keys", "source", "sink")
    assert made.returncode == 0, made.stderr
    return tmp_path / "keys"


@pytest.fixture
def curved(tmp_path, curve_dir, monkeypatch):
    monkeypatch.setenv(keys.CURVE_DIR_ENV, str(curve_dir))
    orchestrator = Orchestrator(tmp_path)
    yield orchestrator
    orchestrator.close()


def start_with_key(component_cls, orchestrator, monkeypatch, key_name):
    """Runs a component with its own key pair; returns once it is registered (it has read its keys)."""
    monkeypatch.setenv(keys.CURVE_KEY_ENV, key_name)
    started = start(component_cls, orchestrator.url)
    poll(lambda: orchestrator.component(component_cls.service), timeout_s=20)
    return started


def test_esiaf_keys_writes_key_pairs_the_allowed_clients_and_never_overwrites(curve_dir):
    secret = curve_dir / "orchestrator.key_secret"
    assert oct(secret.stat().st_mode & 0o777) == "0o600"
    assert sorted(p.name for p in (curve_dir / "clients").iterdir()) == ["sink.key", "source.key"]
    assert zmq.auth.load_certificate(curve_dir / "clients" / "sink.key")[0] == \
        keys.key_pair(curve_dir / "sink.key_secret")[0]
    before = secret.read_text()
    again = make_keys(curve_dir, "sink", "tts")
    assert again.returncode == 0 and "kept" in again.stdout and "ESIAF_CURVE_DIR" in again.stdout
    assert secret.read_text() == before and (curve_dir / "clients" / "tts.key").exists()


def test_components_with_allowed_keys_register_exchange_audio_and_store_results(curved, curve_dir, monkeypatch):
    sink, sink_thread = start_with_key(Sink, curved, monkeypatch, "sink")
    source, source_thread = start_with_key(Source, curved, monkeypatch, "source")
    context = zmq.Context()
    try:
        run_on(source, lambda c: (c.wait_for_subscribers("source/audio", 1, timeout_s=20),
                                  c.publish("source/audio", np.zeros(160, dtype=np.int16), 1000, 10_001_000,
                                            segmentation_ended=True, segment=(500, 9_000_000))))
        results = poll(lambda: curved.http.get("/results", params={"type": "vad"}).json()["items"], timeout_s=20)
        assert results[0]["span"] == {"start_ns": 500, "end_ns": 9_000_000}
        registered = curved.component("source")
        assert registered["audio_public_key"] == zmq.auth.load_certificate(curve_dir / "source.key")[0].decode()
        poll(lambda: curved.component("sink")["heartbeats"] > 0, timeout_s=10)  # the control socket takes it
        stranger = context.socket(zmq.SUB)  # no keys: the source refuses it and says so in its heartbeat
        stranger.setsockopt(zmq.LINGER, 0)
        stranger.connect(registered["audio_endpoint"])
        poll(lambda: curved.component("source")["stats"]["refused_subscribers"], timeout_s=10)
    finally:
        context.destroy(linger=0)
        for component, thread in ((source, source_thread), (sink, sink_thread)):
            component.stop()
            thread.join(timeout=10)


def refusals(orchestrator, socket: str, *reasons: str) -> float:
    return refused_peers(orchestrator.http.get("/metrics").text, socket, *reasons)


def test_peers_without_keys_or_with_unknown_keys_are_refused_and_counted(curved, curve_dir):
    registration = curved.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
    server_key = zmq.auth.load_certificate(curve_dir / "orchestrator.key")[0]
    rogue_public, rogue_secret = zmq.curve_keypair()
    member_public, member_secret = keys.key_pair(curve_dir / "sink.key_secret")
    context = zmq.Context()
    try:
        sockets = {}
        for who, pair in (("stranger", None), ("rogue", (rogue_public, rogue_secret)),
                          ("member", (member_public, member_secret))):
            sock = sockets[who] = context.socket(zmq.PUSH)
            sock.setsockopt(zmq.LINGER, 0)
            if pair:
                sock.curve_publickey, sock.curve_secretkey = pair
                sock.curve_serverkey = server_key
            sock.connect(registration["results_endpoint"])
            result = make_result("asr", "speech", "s", (10**18, 10**18 + 5), 1,
                                 speech={"hypotheses": [{"text": f"from the {who}", "probability": 1.0}]})
            sock.send_multipart(signed_result(registration, result))
        dealer = context.socket(zmq.DEALER)
        dealer.setsockopt(zmq.LINGER, 0)
        dealer.curve_publickey, dealer.curve_secretkey, dealer.curve_serverkey = rogue_public, rogue_secret, server_key
        dealer.setsockopt(zmq.IDENTITY, registration["component_id"].encode())
        dealer.connect(registration["control_endpoint"])
        dealer.send(b'{"type": "heartbeat"}')

        # a peer without keys is refused as "protocol" (another mechanism), or "other" when the
        # connection ends before its greeting is read; an unknown key by the ZAP handler ("auth")
        poll(lambda: refusals(curved, "results", "protocol", "other") >= 1
             and refusals(curved, "results", "auth") >= 1 and refusals(curved, "control", "auth") >= 1, timeout_s=10)
        texts = poll(lambda: [r["speech"]["hypotheses"][0]["text"] for r in
                              curved.http.get("/results").json()["items"]], timeout_s=10)
        assert texts == ["from the member"]  # the refused handshakes above never let the others through
        items = curved.http.get("/components", params={"include_dead": "true"}).json()["items"]
        assert [c["heartbeats"] for c in items if c["component_id"] == registration["component_id"]] == [0]
    finally:
        context.destroy(linger=0)


def test_a_registration_is_bound_to_the_curve_key_of_its_first_heartbeat(curved, curve_dir):
    registration = curved.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
    server_key = zmq.auth.load_certificate(curve_dir / "orchestrator.key")[0]
    beat = json.dumps({"type": "heartbeat", "component_id": registration["component_id"],
                       "control_key": registration["control_key"], "stats": {}}).encode()
    context = zmq.Context()
    try:
        dealers = {}
        for name in ("sink", "source"):  # both keys allowed; the sink's heartbeats first
            dealer = dealers[name] = context.socket(zmq.DEALER)
            dealer.setsockopt(zmq.LINGER, 0)
            dealer.curve_publickey, dealer.curve_secretkey = keys.key_pair(curve_dir / f"{name}.key_secret")
            dealer.curve_serverkey = server_key
            dealer.connect(registration["control_endpoint"])
        owner, other = dealers["sink"], dealers["source"]
        owner.send(beat)
        assert owner.poll(10_000) and owner.recv_json()["type"] == "state"
        other.send(beat)  # the right control key, from another allowed CURVE key: refused
        poll(lambda: refused_control(curved.http.get("/metrics").text, "wrong_peer_key") == 1, timeout_s=10)
        assert not other.poll(500)
        owner.send(beat)
        assert owner.poll(10_000) and owner.recv_json()["type"] == "state"
        assert curved.component("asr")["heartbeats"] == 2
    finally:
        context.destroy(linger=0)


def test_results_are_bound_to_the_curve_key_of_the_registration(curved, curve_dir):
    """A result with the right MAC but from another allowed CURVE key than the one the
    registration is bound to (its first heartbeat's) is refused; the owner's is stored."""
    registration = curved.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
    server_key = zmq.auth.load_certificate(curve_dir / "orchestrator.key")[0]
    context = zmq.Context()
    try:
        dealer = context.socket(zmq.DEALER)
        pushes = {}
        for name, sock in [("dealer", dealer), *((n, pushes.setdefault(n, context.socket(zmq.PUSH)))
                                                  for n in ("sink", "source"))]:
            sock.setsockopt(zmq.LINGER, 0)
            sock.curve_publickey, sock.curve_secretkey = keys.key_pair(
                curve_dir / f"{'sink' if name == 'dealer' else name}.key_secret")
            sock.curve_serverkey = server_key
            sock.connect(registration["control_endpoint" if name == "dealer" else "results_endpoint"])
        dealer.send(json.dumps({"type": "heartbeat", "component_id": registration["component_id"],
                                "control_key": registration["control_key"], "stats": {}}).encode())
        assert dealer.poll(10_000) and dealer.recv_json()["type"] == "state"  # bound to the sink's key
        for who in ("source", "sink"):
            result = make_result("asr", "speech", "s", (10**18, 10**18 + 5), 1,
                                 speech={"hypotheses": [{"text": f"from the {who}", "probability": 1.0}]})
            pushes[who].send_multipart(signed_result(registration, result))
        poll(lambda: refused_messages(curved.http.get("/metrics").text, "wrong_peer_key") == 1, timeout_s=10)
        texts = poll(lambda: [r["speech"]["hypotheses"][0]["text"] for r in
                              curved.http.get("/results").json()["items"]], timeout_s=10)
        assert texts == ["from the sink"]
    finally:
        context.destroy(linger=0)


def handshake_failed(sock: zmq.Socket) -> zmq.Socket:
    return sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_HANDSHAKE_FAILED_AUTH
                                   | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL)


def test_a_new_robots_key_is_let_in_on_sighup_without_a_restart(curved, curve_dir, tmp_path):
    assert make_keys(tmp_path / "later", "robot2").returncode == 0  # made on the new robot, not yet allowed
    pair = keys.key_pair(tmp_path / "later" / "robot2.key_secret")
    server_key = zmq.auth.load_certificate(curve_dir / "orchestrator.key")[0]
    registration = curved.http.post("/components", json={"name": "asr", "kind": "speech"}).json()
    context = zmq.Context()
    kept = []  # open until the end: a socket closed at once may end before its handshake

    def push(text: str) -> None:  # a new connection each time: keys are checked at the handshake
        sock = context.socket(zmq.PUSH)
        kept.append(sock)
        sock.setsockopt(zmq.LINGER, 0)
        sock.curve_publickey, sock.curve_secretkey = pair
        sock.curve_serverkey = server_key
        sock.connect(registration["results_endpoint"])
        result = make_result("asr", "speech", "s", (10**18, 10**18 + 5), 1,
                             speech={"hypotheses": [{"text": text, "probability": 1.0}]})
        sock.send_multipart(signed_result(registration, result))

    def reloads() -> list[str]:
        return re.findall(r"event=keys_reloaded dir=\S+ (clients=\d+)", (tmp_path / "orchestrator.log").read_text())

    def texts() -> list[str]:
        return [r["speech"]["hypotheses"][0]["text"] for r in curved.http.get("/results").json()["items"]]

    try:
        push("before")
        poll(lambda: refusals(curved, "results", "auth") >= 1, timeout_s=10)
        shutil.copyfile(tmp_path / "later" / "robot2.key", curve_dir / "clients" / "robot2.key")
        push("copied, not yet reloaded")
        poll(lambda: refusals(curved, "results", "auth") >= 2, timeout_s=10)
        assert texts() == []
        os.kill(curved.process.pid, signal.SIGHUP)  # the orchestrator reads its allowed keys again
        poll(lambda: reloads() == ["clients=3"], timeout_s=10)  # source, sink, robot2
        push("after")
        poll(lambda: "after" in texts(), timeout_s=10)
        assert curved.process.poll() is None  # SIGHUP does not end it
        (curve_dir / "clients" / "robot2.key").unlink()  # withdrawn again
        os.kill(curved.process.pid, signal.SIGHUP)
        poll(lambda: reloads() == ["clients=3", "clients=2"], timeout_s=10)
        refused = refusals(curved, "results", "auth")
        push("withdrawn")
        poll(lambda: refusals(curved, "results", "auth") > refused, timeout_s=10)
        assert "withdrawn" not in texts()
    finally:
        context.destroy(linger=0)


PRODUCER = """
import logging, sys
logging.basicConfig(level=logging.INFO)
from tests.test_component import Source
sys.exit(Source(Source.Settings(name="source", orchestrator_url=sys.argv[1])).run())
"""


def test_a_producers_audio_output_lets_a_new_key_in_on_sighup(curved, curve_dir, tmp_path):
    """A producer's audio output (a CURVE server) reads clients/ again on SIGHUP, as the
    orchestrator does: a new consumer's key is let in, a withdrawn one kept out, no restart."""
    assert make_keys(tmp_path / "later", "robot2").returncode == 0  # made on the new robot, not yet allowed
    pair = keys.key_pair(tmp_path / "later" / "robot2.key_secret")
    log = tmp_path / "source.log"
    with open(log, "w") as out:
        process = subprocess.Popen([sys.executable, "-c", PRODUCER, curved.url], cwd=REPO, stdout=out,
                                   stderr=subprocess.STDOUT,
                                   env={**os.environ, "PYTHONPATH": str(REPO), keys.CURVE_KEY_ENV: "source"})
    context = zmq.Context()

    def subscribe() -> str:  # a new connection each time: keys are checked at the handshake
        sock = context.socket(zmq.SUB)
        sock.setsockopt(zmq.LINGER, 0)
        sock.curve_publickey, sock.curve_secretkey = pair
        sock.curve_serverkey = registered["audio_public_key"].encode()
        monitor = sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED | sum(keys.HANDSHAKE_FAILURES))
        sock.connect(registered["audio_endpoint"])
        try:
            assert monitor.poll(10_000), "no handshake"
            return "in" if recv_monitor_message(monitor)["event"] == zmq.EVENT_HANDSHAKE_SUCCEEDED else "refused"
        finally:
            monitor.close(linger=0)
            sock.close(linger=0)

    def reloads() -> list[str]:
        return re.findall(r"event=keys_reloaded dir=\S+ (clients=\d+)", log.read_text())

    try:
        registered = poll(lambda: curved.component("source"), timeout_s=30)
        assert subscribe() == "refused"
        shutil.copyfile(tmp_path / "later" / "robot2.key", curve_dir / "clients" / "robot2.key")
        assert subscribe() == "refused"  # copied, not yet reloaded
        os.kill(process.pid, signal.SIGHUP)
        poll(lambda: reloads() == ["clients=3"], timeout_s=10)  # source, sink, robot2
        assert subscribe() == "in"
        assert process.poll() is None  # SIGHUP does not end it
        (curve_dir / "clients" / "robot2.key").unlink()  # withdrawn again
        os.kill(process.pid, signal.SIGHUP)
        poll(lambda: reloads() == ["clients=3", "clients=2"], timeout_s=10)
        assert subscribe() == "refused"
    finally:
        context.destroy(linger=0)
        process.terminate()
        process.wait(timeout=20)


def test_audio_goes_only_between_allowed_keys(curve_dir):
    env = {keys.CURVE_DIR_ENV: str(curve_dir), keys.CURVE_KEY_ENV: "source"}
    source_keys, sink_keys = keys.load(False, env), keys.load(False, {**env, keys.CURVE_KEY_ENV: "sink"})
    context = zmq.Context()
    producer = Transport(context, inputs=[], has_outputs=True, bind_host="127.0.0.1", curve=source_keys)
    try:
        subscribers = {}
        for who, pair in (("stranger", None), ("rogue", zmq.curve_keypair()),
                          ("member", (sink_keys.public, sink_keys.secret))):
            sock = subscribers[who] = context.socket(zmq.SUB)
            sock.setsockopt(zmq.LINGER, 0)
            if pair:
                sock.curve_publickey, sock.curve_secretkey = pair
                sock.curve_serverkey = source_keys.public
            sock.setsockopt(zmq.SUBSCRIBE, b"")
            monitor = handshake_failed(sock) if who != "member" else None
            sock.connect(producer.audio_endpoint)
            if monitor is not None:
                assert monitor.poll(10_000), f"the {who}'s handshake did not fail"
                recv_monitor_message(monitor)
                monitor.close(linger=0)
        events = []
        poll(lambda: events.extend(producer.events(100)) or (("subscription", ("", 1)) in events
             and [kind for kind, _ in events].count("refused") >= 2), timeout_s=10)
        assert [e for e in events if e[0] == "subscription"] == [("subscription", ("", 1))]  # the member alone
        assert "auth" in {reason for kind, reason in events if kind == "refused"}  # the rogue's key
        assert producer.audio_public_key == source_keys.public.decode()
    finally:
        for sock in subscribers.values():
            sock.close(linger=0)
        producer.close()
        context.term()


def test_a_consumer_connects_only_to_producers_with_an_allowed_key(curve_dir):
    sink_keys = keys.load(False, {keys.CURVE_DIR_ENV: str(curve_dir), keys.CURVE_KEY_ENV: "sink"})
    context = zmq.Context()
    consumer = Transport(context, inputs=["source/audio"], has_outputs=False, bind_host="127.0.0.1", curve=sink_keys)
    try:
        allowed = zmq.auth.load_certificate(curve_dir / "source.key")[0].decode()
        unknown = zmq.curve_keypair()[0].decode()
        wanted = {"tcp://127.0.0.1:1": allowed, "tcp://127.0.0.1:2": unknown}
        consumer.connect_peers(set(wanted) | {"tcp://127.0.0.1:3"}, wanted)  # :3 gave no key
        assert consumer._connected == {"tcp://127.0.0.1:1"}
    finally:
        consumer.close()
        context.term()


def test_a_consumer_connects_to_a_new_producers_key_after_sighup(curve_dir, tmp_path):
    assert make_keys(tmp_path / "later", "robot2").returncode == 0
    new_key = zmq.auth.load_certificate(tmp_path / "later" / "robot2.key")[0].decode()
    sink_keys = keys.load(False, {keys.CURVE_DIR_ENV: str(curve_dir), keys.CURVE_KEY_ENV: "sink"})
    context = zmq.Context()
    consumer = Transport(context, inputs=["source/audio"], has_outputs=False, bind_host="127.0.0.1", curve=sink_keys)
    try:
        wanted = {"tcp://127.0.0.1:1": new_key}
        consumer.connect_peers(set(wanted), wanted)
        assert consumer._connected == set()  # not an allowed key yet
        shutil.copyfile(tmp_path / "later" / "robot2.key", curve_dir / "clients" / "robot2.key")
        consumer.reload_keys_soon()  # what its SIGHUP handler does; the data thread reads them at its next poll
        list(consumer.events(100))
        consumer.connect_peers(set(wanted), wanted)
        assert consumer._connected == {"tcp://127.0.0.1:1"}
    finally:
        consumer.close()
        context.term()


def public_instead_of_secret(directory: Path) -> None:
    shutil.copyfile(directory / "orchestrator.key", directory / "orchestrator.key_secret")


def garbled(directory: Path) -> None:
    (directory / "orchestrator.key").write_text('curve\n    public-key = "not a key"\n')


def no_clients(directory: Path) -> None:
    for path in (directory / "clients").iterdir():
        path.unlink()


@pytest.mark.parametrize("spoil, orchestrator, complaint", [
    (public_instead_of_secret, True, "holds a public key only"),
    (lambda d: (d / "orchestrator.key_secret").unlink(), True, "orchestrator.key_secret: no such file"),
    (no_clients, True, "no public key (*.key) in"),
    (garbled, False, "not a 40-character Z85 CURVE key"),
    (lambda d: shutil.rmtree(d), False, "is not a directory"),
])
def test_bad_key_files_are_one_clear_line(curve_dir, spoil, orchestrator, complaint):
    spoil(curve_dir)
    with pytest.raises(keys.KeyFileError, match=re.escape(complaint)):
        keys.load(orchestrator, {keys.CURVE_DIR_ENV: str(curve_dir), keys.CURVE_KEY_ENV: "sink"})


def test_the_orchestrator_with_a_bad_key_file_exits_2_at_once(tmp_path, curve_dir):
    public_instead_of_secret(curve_dir)
    env = {**os.environ, "PYTHONPATH": str(REPO), keys.CURVE_DIR_ENV: str(curve_dir)}
    done = subprocess.run([sys.executable, "-m", "esiaf_services.orchestrator", "--port", str(free_port()),
                           "--db", str(tmp_path / "o.db")], cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith("orchestrator: ") and "public key only" in done.stderr


def test_a_component_with_a_bad_key_file_stops_with_a_setup_error(curve_dir, monkeypatch):
    monkeypatch.setenv(keys.CURVE_DIR_ENV, str(curve_dir))
    monkeypatch.setenv(keys.CURVE_KEY_ENV, "nobody")
    sink = Sink(Sink.Settings(name="sink", orchestrator_url=f"http://127.0.0.1:{free_port()}"))
    errors = []

    def run():  # on a thread: run() takes SIGINT and SIGTERM only on the main thread
        try:
            sink.run()
        except SetupError as exc:
            errors.append(str(exc))

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(timeout=20)
    assert errors and "nobody.key_secret: no such file" in errors[0]
