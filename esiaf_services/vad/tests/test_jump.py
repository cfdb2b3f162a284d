"""A person's onset from quiet is announced at once (``silero.jump_to``: the barge-in's speech_start does not
wait for ``speech_start_ms`` of speech), and the vad's segments stay what they were. The Silero backend on
the example's questions."""
import soundfile

from esiaf_services.vad.tests.test_joined_late import EXAMPLE, played


def test_a_jump_from_quiet_is_announced_at_once_and_the_segments_are_unchanged():
    length_s = soundfile.info(str(EXAMPLE)).duration
    jump, wait = played(0.0, length_s, 1), played(0.0, length_s, 1, silero={"jump_to": 0})
    assert len(wait.starts) >= 3 and len(jump.starts) == len(wait.starts), (jump.starts, wait.starts)
    for (onset, decided), (_, waited) in zip(jump.starts, wait.starts, strict=True):
        # decided within a chunk (50 ms) of the jump's window, not speech_start_ms (150 ms) of speech later
        assert decided - onset <= 96_000_000, (onset, decided)
        assert waited - decided >= 64_000_000, (decided, waited)
    assert jump.found == wait.found and jump.found
