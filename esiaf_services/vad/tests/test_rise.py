"""A new talker within a stretch of speech: a sharp rise of the speech probability after a plateau
(esiaf/speech/rise.py), and its settings' bounds."""
import pytest

from esiaf.speech.rise import Rise, RiseParams
from esiaf_services.vad.service import VadSettings

WINDOW_NS = 32_000_000


def rises(probabilities: list[float], **params) -> list[tuple[int, int]]:
    """(window index, onset window index) of every rise found."""
    rise, found = Rise(RiseParams(**params)), []
    for i, p in enumerate(probabilities):
        onset = rise.window(i * WINDOW_NS, (i + 1) * WINDOW_NS, p)
        if onset is not None:
            found.append((i, onset // WINDOW_NS))
    return found


def test_a_jump_from_a_babble_plateau_is_a_rise_with_its_onset_at_the_ramp():
    babble = [0.40, 0.45, 0.38, 0.42, 0.50, 0.41, 0.39, 0.44, 0.43, 0.40, 0.42, 0.45]
    # the first window at rise_to ends it; its onset: the ramp's first window over the plateau (the windows
    # after it, with the plateau still behind them, say the same onset: the vad announces one per rise_every_ms)
    assert rises([*babble, 0.68, 0.92, 0.9]) == [(13, 12), (14, 12)]
    assert rises([*babble, 0.95]) == [(12, 12)]


def test_no_rise_on_a_slow_ramp_a_high_plateau_or_before_a_plateau_was_heard():
    assert rises([0.30 + 0.03 * i for i in range(20)]) == []  # 0.3 to 0.87 over 640 ms
    assert rises([0.60] * 12 + [0.95]) == []  # babble this speech-like is no plateau
    assert rises([0.10, 0.10, 0.95]) == []  # 96 ms heard: no plateau yet


@pytest.mark.parametrize("field, value", [("rise_to", 1.5), ("rise_from", -0.1), ("rise_by", 0),
                                          ("rise_plateau_ms", 10), ("rise_every_ms", -1),
                                          ("jump_to", 1.5), ("jump_from", 2), ("jump_by", 0)])
def test_the_rise_settings_are_bounded(field, value):
    with pytest.raises(ValueError, match=field):
        VadSettings(silero={field: value})
