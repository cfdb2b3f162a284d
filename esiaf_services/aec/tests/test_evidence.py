"""The canceller's ``echo`` events and fusion's use of them: a person speaking over the robot stands out of
a converged canceller's output, the robot's residual does not (real speex canceller, real sockets, real
orchestrator), and fusion's rule takes an utterance with nothing recognised for the person's on them."""
from __future__ import annotations

import numpy as np

from esiaf.tools.testing import poll
from esiaf_services.aec.evidence import FLOOR_MIN_BLOCKS, EchoMeter
from esiaf_services.aec.tests.test_aec import RATE, echo_path, run_through, speech, to_pcm
from esiaf_services.orchestrator.fusion.playback import is_robot, person_above_echo, played

NS = 1_000_000_000


def test_a_block_above_the_floor_is_measured_from_the_output_and_the_floor_comes_after_enough_blocks():
    meter = EchoMeter(RATE)
    quiet = np.full((meter.block_frames, 2), 30, dtype=np.int16)  # about 96 + 20 log10(30 / 32768) = 35 dB
    heard = quiet * 10  # the microphones, 20 dB above what the canceller leaves
    blocks = [b for i in range(FLOOR_MIN_BLOCKS + 2)
              for b in meter.add(NS + i * meter.block_frames * NS // RATE, heard, quiet, converged=True)]
    assert [b.above_floor_db is None for b in blocks] == [True] * (FLOOR_MIN_BLOCKS - 1) + [False] * 3
    assert abs(blocks[-1].level_db - 35.2) < 0.2 and abs(blocks[-1].above_floor_db) < 0.01
    assert abs(blocks[-1].cancelled_db - 20.0) < 0.01
    loud, = meter.add(blocks[-1].end_ns, heard * 10, quiet * 100, converged=True)  # 40 dB louder, nothing taken off
    assert abs(loud.above_floor_db - 40.0) < 0.1 and abs(loud.cancelled_db) < 0.01
    assert loud.start_ns == blocks[-1].end_ns
    half = meter.add(loud.end_ns + NS, heard[:meter.block_frames // 2], quiet[:meter.block_frames // 2],
                     converged=False)  # after a gap (a pass-through): a block of its own
    assert half == [] and meter.add(loud.end_ns + NS + meter.block_frames // 2 * NS // RATE,
                                    heard[meter.block_frames // 2:], quiet[meter.block_frames // 2:],
                                    converged=False)[0].start_ns == loud.end_ns + NS


def echo_events(orchestrator) -> list[dict]:
    answer = orchestrator.http.get("/results", params={"type": "echo", "limit": 1000})
    assert answer.status_code == 200, answer.text
    return answer.json()["items"]


def within(events: list[dict], start_s: float, end_s: float) -> list[dict]:
    return [e for e in events if NS + start_s * NS <= e["span"]["start_ns"] and e["span"]["end_ns"] <= NS + end_s * NS]


def test_a_person_over_the_robot_stands_out_of_the_converged_output_and_the_robots_residual_does_not(orchestrator):
    robot = speech(14.0)
    echo = echo_path(robot, 4, delay_ms=120, ppm=100)
    person = np.zeros_like(robot)
    said = speech(2.0)[::-1]  # another voice's sounds (the same clips backwards), 10 dB below the echo
    person[10 * RATE:12 * RATE] = said * np.sqrt(np.mean(echo[:, 0] ** 2) / np.mean(said ** 2) / 10)
    noise = np.random.default_rng(5).normal(0, np.sqrt(np.mean(echo[:, 0] ** 2)) / 100, echo.shape)  # 20 dB below
    run_through(orchestrator, to_pcm(echo + person[:, None] + noise), robot, reference_until=len(robot))
    poll(lambda: len(echo_events(orchestrator)) >= 50, timeout_s=20)
    events = echo_events(orchestrator)
    assert not any(e["echo"]["attributes"]["converged"] for e in within(events, 0.0, 0.5))
    assert all(e["echo"]["attributes"]["converged"] for e in within(events, 6.0, 14.0))
    assert person_above_echo(within(events, 10.0, 12.0))  # the person
    assert not person_above_echo(within(events, 7.0, 9.5))  # the robot's converged residual alone
    assert not person_above_echo(within(events, 0.0, 1.5))  # not converged: no evidence

    # fusion's rule: nothing recognised while the robot played is the robot's, unless these events say otherwise
    items = played([{"instance": "player-1", "sequence": 1, "span": {"start_ns": NS, "end_ns": NS + 14 * NS},
                     "playback": {"text": "say: Hello.", "attributes": {"item": 1.0, "part": 0.0}}}])
    nothing = {"speech": {"hypotheses": [{"text": "", "probability": 0.0, "words": []}]}}
    assert not is_robot(1.0, items, nothing, {}, None, within(events, 10.0, 12.0))
    assert is_robot(1.0, items, nothing, {}, None, within(events, 7.0, 9.5))
    assert is_robot(1.0, items, nothing, {}, None)  # no canceller: the overlap decides, as before

