"""The control plane's messages (esiaf/control_messages.py): what each end accepts, refuses and sends,
and that docs/protocol.md lists them as the module defines them."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from esiaf.control_messages import (
    MAX_MESSAGE_BYTES,
    MAX_PCM_BYTES,
    Ack,
    BargeIn,
    BeatNow,
    Command,
    Fatal,
    Heartbeat,
    LocalState,
    MessageError,
    Play,
    Say,
    State,
    StopPlaying,
    Unknown,
    Unrecognised,
    encode,
    parse_to_component,
    parse_to_data_thread,
    parse_to_orchestrator,
)

FMT = {"sample_rate_hz": 16000, "sample_type": "int16", "endianness": "little", "channels": 1}


def test_a_heartbeat_reads_as_sent_and_a_malformed_optional_field_as_absent():
    beat = {"type": "heartbeat", "component_id": "vad-1", "control_key": "k", "stats": {"results_sent": 4},
            "sent_ns": 5, "clock": {"offset_ns": -3, "uncertainty_ns": 2}, "state_version": 3, "interval_s": 2}
    parsed = parse_to_orchestrator(json.dumps(beat).encode())
    assert isinstance(parsed, Heartbeat) and parsed.state_version == 3 and parsed.interval_s == 2.0
    assert parsed.clock is not None and parsed.clock.offset_ns == -3
    wrong = {**beat, "state_version": "3", "sent_ns": 2**63, "interval_s": True, "stats": [1],
             "clock": {"offset_ns": 10**30, "uncertainty_ns": 0}, "control_key": 7}
    parsed = parse_to_orchestrator(json.dumps(wrong).encode())
    assert isinstance(parsed, Heartbeat) and parsed.component_id == "vad-1"  # still a heartbeat: life
    assert (parsed.state_version, parsed.sent_ns, parsed.interval_s, parsed.stats, parsed.clock,
            parsed.control_key) == (None,) * 6


def test_a_type_the_orchestrator_does_not_know_still_names_its_sender():
    parsed = parse_to_orchestrator(b'{"type": "hello", "component_id": "vad-1", "control_key": "k"}')
    assert isinstance(parsed, Unrecognised) and parsed.type == "hello" and parsed.control_key == "k"


@pytest.mark.parametrize("data", [b"not json", b"[1, 2]", b'"heartbeat"', b"{}", b'{"type": 5}',
                                  b"[" * 100_000, b" " * (MAX_MESSAGE_BYTES + 1)])
def test_what_is_not_a_message_is_refused_with_a_reason(data):
    for parse in (parse_to_orchestrator, parse_to_component, parse_to_data_thread):
        with pytest.raises(MessageError) as refused:
            parse(data)
        assert 0 < len(str(refused.value)) <= 200


def test_what_the_orchestrator_sends_reads_back_the_same():
    state = State(peers={"audio/raw": ["tcp://a:1"]}, formats={"audio/raw": FMT}, version=3, echo_ns=1,
                  orchestrator_ns=2)
    assert json.loads(encode(state)) == {"type": "state", "peers": {"audio/raw": ["tcp://a:1"]},
                                         "formats": {"audio/raw": FMT}, "version": 3, "echo_ns": 1,
                                         "orchestrator_ns": 2}  # absent: peer_keys, streams
    for message in (state, Ack(version=3), Unknown(), BeatNow()):
        assert parse_to_component(encode(message)) == message
    assert json.loads(encode(Ack(version=2))) == {"type": "ack", "version": 2}
    with pytest.raises(MessageError, match="formats"):  # a required field malformed: refused whole
        parse_to_component(json.dumps({"type": "state", "peers": {}, "formats": {"a": {**FMT, "channels": 0}}})
                           .encode())


def test_the_data_thread_reads_what_the_heartbeat_thread_hands_it():
    local = LocalState(component_id="vad-1", results_endpoint="tcp://o:2", peers={}, formats={"a": FMT})
    assert parse_to_data_thread(encode(local)) == local
    assert parse_to_data_thread(encode(Fatal(error="refused"))) == Fatal(error="refused")


def test_a_command_travels_as_json_and_reaches_the_data_thread_as_it_came():
    pcm = bytes(range(256)) * 4
    for order in (Say(text="Hello.", voice="kal"), Play(name="beep", pcm=pcm), StopPlaying(),
                  BargeIn(policy="duck", capture_ns=7)):
        command = Command(stream_id="robot1", order=order)
        assert parse_to_component(encode(command)) == command == parse_to_data_thread(encode(command))
    wire = json.loads(encode(Command(stream_id="r", order=Play(name="beep", pcm=b"\x01\x02"))))
    assert wire == {"type": "command", "stream_id": "r", "order": {"action": "play", "name": "beep", "pcm": "AQI="}}


@pytest.mark.parametrize("order", [{"action": "say", "text": ""}, {"action": "jump"},
                                   {"action": "barge_in", "policy": "shout", "capture_ns": 1},
                                   {"action": "play", "name": "x", "pcm": "not base64!"}])
def test_a_malformed_order_is_refused_with_a_reason(order):
    with pytest.raises(MessageError, match="order"):
        parse_to_component(json.dumps({"type": "command", "stream_id": "r", "order": order}).encode())


def test_a_play_order_longer_than_its_cap_is_refused():
    with pytest.raises(ValueError, match="at most"):
        Play(name="long", pcm=bytes(MAX_PCM_BYTES + 2))


def test_the_protocol_page_lists_each_message_with_the_modules_fields():
    text = (Path(__file__).parent.parent / "docs" / "protocol.md").read_text()
    rows = {m.group(1): re.findall(r"`(\w+)`", m.group(2))
            for m in re.finditer(r"^\| `(\w+)` \| [^|]+ \| ([^|]*) \|$", text, re.MULTILINE)}
    for model in (Heartbeat, State, Ack, Unknown, BeatNow, Command):
        kind = model.model_fields["type"].default
        fields = [f for f in model.model_fields if f != "type"]
        if model is Heartbeat:  # the clock's fields are listed after it
            fields[fields.index("clock") + 1:fields.index("clock") + 1] = ["offset_ns", "uncertainty_ns"]
        assert rows.get(kind) == fields, kind
