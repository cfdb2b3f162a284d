"""The torch-legacy reader (against a file written here by hand, byte for byte as torch 1.x did)
and the open-set scoring with anonymous voices."""
from __future__ import annotations

import pickle
import struct

import numpy as np
import pytest

from esiaf.speech.speaker import torch_legacy
from esiaf_services.voiceid.scoring import AnonymousVoices, VoiceBook, probability


def _op(value) -> bytes:
    """The pickle opcodes pushing one plain value (no PROTO, no STOP)."""
    return pickle.dumps(value, protocol=2)[2:-1]


def write_legacy(path, tensors: dict[str, np.ndarray]) -> None:
    """A legacy torch checkpoint, byte for byte as torch 1.x wrote one: pickles of the magic
    number, protocol version and sys info; the state dict, each tensor a call of
    torch._utils._rebuild_tensor_v2 on a persistent storage id ("storage", torch.FloatStorage,
    key, location, size); the storage keys; then each storage's int64 count and raw bytes."""
    state = b"\x80\x02}("  # PROTO 2, EMPTY_DICT, MARK
    for key, (name, array) in enumerate(tensors.items()):
        state += _op(name) + b"ctorch._utils\n_rebuild_tensor_v2\n("
        state += b"(" + _op("storage") + b"ctorch\nFloatStorage\n" + _op(str(key)) + _op("cpu") + _op(array.size)
        state += b"tQ"  # TUPLE, BINPERSID
        state += _op(0) + _op(array.shape) + _op(tuple(s // 4 for s in array.strides)) + b"\x89"  # offset, .., False
        state += b"tR"  # TUPLE, REDUCE
    state += b"u."  # SETITEMS, STOP
    with open(path, "wb") as file:
        for value in (torch_legacy.MAGIC_NUMBER, torch_legacy.PROTOCOL_VERSION, {"little_endian": True}):
            pickle.dump(value, file, protocol=2)
        file.write(state)
        pickle.dump([str(key) for key in range(len(tensors))], file, protocol=2)
        for array in tensors.values():
            file.write(struct.pack("<q", array.size) + np.ascontiguousarray(array, "<f4").tobytes())


def test_the_legacy_reader_rebuilds_the_arrays(tmp_path):
    tensors = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.array([1.5, -2.0], np.float32)}
    path = tmp_path / "small.pt"
    write_legacy(path, tensors)
    loaded = torch_legacy.load(path)
    assert set(loaded) == {"a", "b"}
    for name, array in tensors.items():
        np.testing.assert_array_equal(loaded[name], array)


def test_the_legacy_reader_refuses_other_files(tmp_path):
    zipped = tmp_path / "new.pt"
    zipped.write_bytes(b"PK\x03\x04rest")
    with pytest.raises(torch_legacy.LegacyFormatError, match="zip checkpoint"):
        torch_legacy.load(zipped)
    other = tmp_path / "other.pt"
    other.write_bytes(pickle.dumps(42) + pickle.dumps(1001))
    with pytest.raises(torch_legacy.LegacyFormatError, match="not a legacy torch checkpoint"):
        torch_legacy.load(other)
    evil = tmp_path / "evil.pt"
    evil.write_bytes(pickle.dumps(torch_legacy.MAGIC_NUMBER) + pickle.dumps(1001) + pickle.dumps({})
                     + b"cos\nsystem\n(S'true'\ntR.")
    with pytest.raises(torch_legacy.LegacyFormatError, match=r"refusing to load os\.system"):
        torch_legacy.load(evil)


def test_the_shipped_weights_load_without_torch():
    from esiaf.speech.speaker.ge2e import weights_path
    path = weights_path()
    state = torch_legacy.load(path)["model_state"]
    assert state["lstm.weight_ih_l0"].shape == (1024, 40) and state["linear.weight"].shape == (256, 256)
    assert state["lstm.weight_hh_l2"].dtype == np.float32 and np.isfinite(state["lstm.weight_hh_l2"]).all()


def _unit(v):
    v = np.asarray(v, np.float32)
    return v / np.linalg.norm(v)


def test_scores_are_the_mean_of_the_top_k_and_the_threshold_gives_unknown():
    anna = [_unit([1, 0, 0]), _unit([1, 0.2, 0]), _unit([0, 1, 0])]
    book = VoiceBook({"anna": anna, "ben": [_unit([0, 0, 1])]}, top_k=2)
    probe = _unit([1, 0.1, 0])
    scores = book.scores(probe)
    best_two = sorted([float(e @ probe) for e in anna], reverse=True)[:2]
    assert scores["anna"] == pytest.approx(np.mean(best_two)) and scores["ben"] == pytest.approx(0.0)
    match = book.identify(probe, threshold=0.9)
    assert match.label == "anna" and match.probability > 0.5 and set(match.scores) == {"anna", "ben"}
    unknown = book.identify(_unit([0.5, 0.5, 0.7]), threshold=0.9)
    assert unknown.label == "" and unknown.probability < 0.5
    assert probability(0.9, 0.9) == pytest.approx(0.5)
    assert VoiceBook().identify(probe, 0.5).label == ""


def test_with_a_mean_weight_learnt_embeddings_move_the_mean_and_add_no_top_k_chance():
    anna, ben = [_unit([1, 0, 0]), _unit([1, 0.3, 0])], [_unit([0, 0, 1])]
    learnt = np.stack([_unit([0.2, 1, 0])] * 20)  # many learnt embeddings near the probe
    probe = _unit([0.25, 1, 0.05])
    top_k_all = VoiceBook({"anna": anna, "ben": ben}, top_k=2, learnt={"anna": learnt})
    assert top_k_all.scores(probe)["anna"] == pytest.approx(float(learnt[0] @ probe))  # two learnt ones win
    blended = VoiceBook({"anna": anna, "ben": ben}, top_k=2, learnt={"anna": learnt}, mean_weight=0.5)
    mean = _unit(np.mean(np.concatenate([np.stack(anna), learnt]), axis=0))
    expected = 0.5 * np.mean([float(e @ probe) for e in anna]) + 0.5 * float(mean @ probe)
    assert blended.scores(probe)["anna"] == pytest.approx(expected, rel=1e-5)
    assert blended.scores(probe)["anna"] < top_k_all.scores(probe)["anna"]
    # without learnt embeddings: the top-k over the enrolled and the cosine to their mean
    alone = VoiceBook({"anna": anna}, top_k=2, mean_weight=1.0)
    assert alone.scores(probe)["anna"] == pytest.approx(float(_unit(anna[0] + anna[1]) @ probe), rel=1e-5)
    # learnt embeddings of a voice not enrolled are ignored
    assert set(VoiceBook({"ben": ben}, learnt={"anna": learnt}, mean_weight=0.5).scores(probe)) == {"ben"}


def test_played_spans_merge_keep_their_bound_and_count_the_tail():
    from esiaf.playback import PlayedSpans
    ms = 1_000_000
    played = PlayedSpans(keep=2, tail_ms=300.0, max_streams=2)
    played.add_span("s1", 1000 * ms, 1050 * ms)
    played.add_span("s1", 1050 * ms, 1100 * ms)  # adjoining: one span
    assert list(played.spans["s1"]) == [[1000 * ms, 1100 * ms]]
    assert played.overlaps("s1", 900 * ms, 1001 * ms) and played.overlaps("s1", 1399 * ms, 2000 * ms)
    assert not played.overlaps("s1", 1400 * ms, 2000 * ms) and not played.overlaps("s1", 0, 1000 * ms)
    assert not played.overlaps("s2", 1000 * ms, 1100 * ms)  # another stream's
    played.add_span("s1", 5000 * ms, 5100 * ms)
    played.add_span("s1", 9000 * ms, 9100 * ms)  # the oldest goes
    assert not played.overlaps("s1", 1000 * ms, 1100 * ms) and played.overlaps("s1", 5050 * ms, 5060 * ms)


def test_anonymous_voices_keep_their_ids_and_are_bounded():
    voices = AnonymousVoices(threshold=0.9, limit=2)
    assert voices.assign(_unit([1, 0, 0]))[0] == "voice-1"
    assert voices.assign(_unit([0, 1, 0]))[0] == "voice-2"
    assert voices.assign(_unit([1, 0.05, 0]))[0] == "voice-1"  # heard again
    assert voices.assign(_unit([0, 0, 1]))[0] == "voice-3"  # voice-2, least recently heard, is forgotten
    assert list(voices.voices) == ["voice-1", "voice-3"]
    assert voices.assign(_unit([0, 1, 0]))[0] == "voice-4"


def test_the_fused_voice_is_the_results_label_not_the_best_enrolled_score():
    from esiaf_services.orchestrator.fusion.aggregate import label_aggregate
    stranger = {"span": {"start_ns": 0, "end_ns": 2_000_000_000},
                "voice_id": {"label": "voice-2", "probability": 0.9, "class_probabilities": {"Anna": 0.6}}}
    aggregate = label_aggregate([stranger], "voice_id", (0, 2_000_000_000))
    assert aggregate["label"] == "voice-2" and aggregate["probability"] == pytest.approx(0.9)
    assert aggregate["distribution"] == {"voice-2": pytest.approx(0.9), "unknown": pytest.approx(0.1)}


def test_adaptive_snorm_normalises_by_the_best_cohort_scores_of_both_sides():
    rng = np.random.default_rng(1)
    cohort = np.stack([_unit(v) for v in rng.normal(size=(30, 8))])
    anna, probe = _unit(rng.normal(size=8)), _unit(rng.normal(size=8))
    book = VoiceBook({"anna": [anna]}, top_k=1, cohort=cohort, cohort_top=5)
    raw = float(anna @ probe)
    assert book.raw_scores(probe)["anna"] == pytest.approx(raw)
    voice_side, probe_side = np.sort(cohort @ anna)[::-1][:5], np.sort(cohort @ probe)[::-1][:5]
    expected = 0.5 * ((raw - voice_side.mean()) / voice_side.std() + (raw - probe_side.mean()) / probe_side.std())
    assert book.scores(probe)["anna"] == pytest.approx(expected, rel=1e-5)
    # the voice side uses the voice's top-k score against each cohort member, as the raw score does
    two = VoiceBook({"anna": [anna, probe]}, top_k=2, cohort=cohort, cohort_top=5)
    member_scores = np.sort(np.mean(np.stack([cohort @ anna, cohort @ probe]), axis=0))[::-1][:5]
    assert two.voice_stats["anna"][0] == pytest.approx(member_scores.mean(), rel=1e-5)
    # a probe close to the cohort is pulled down, one far from it is not
    near_cohort = _unit(cohort[0] + 0.1 * anna)
    plain = VoiceBook({"anna": [anna]}, top_k=1)
    assert plain.scores(near_cohort)["anna"] == pytest.approx(book.raw_scores(near_cohort)["anna"])
    assert book.scores(near_cohort)["anna"] < book.scores(_unit(anna + 0.1 * probe))["anna"]


def test_speed_perturbation_changes_tempo_and_pitch_together():
    from esiaf.speech.speaker.augment import speed_perturbed
    t = np.arange(16000) / 16000
    tone = np.sin(2 * np.pi * 200 * t).astype(np.float32)
    faster = speed_perturbed(tone, 1.25)
    assert faster.dtype == np.float32 and abs(faster.size - 16000 / 1.25) <= 2
    spectrum = np.abs(np.fft.rfft(faster * np.hanning(faster.size)))
    assert np.argmax(spectrum) * 16000 / faster.size == pytest.approx(250, abs=2)
    np.testing.assert_array_equal(speed_perturbed(tone, 1.0), tone)
    with pytest.raises(ValueError):
        speed_perturbed(tone, 0.0)


def test_the_tilt_brightens_or_darkens_at_the_same_level():
    from esiaf.speech.speaker.augment import tilted
    rng = np.random.default_rng(2)
    noise = rng.normal(size=32000).astype(np.float32) * 0.1

    def high_share(x):
        power = np.abs(np.fft.rfft(x)) ** 2
        return power[power.size // 2:].sum() / power.sum()

    brighter, darker = tilted(noise, 0.7), tilted(noise, -0.7)
    assert high_share(brighter) > high_share(noise) + 0.1 and high_share(darker) < high_share(noise) - 0.1
    for y in (brighter, darker):
        assert y.dtype == np.float32 and np.sqrt(np.mean(y ** 2)) == pytest.approx(0.1, rel=0.05)
    np.testing.assert_allclose(tilted(noise, 0.0), noise, atol=1e-7)
    with pytest.raises(ValueError):
        tilted(noise, 1.0)


def test_reverberant_copies_have_the_tail_the_noise_level_and_the_seed():
    pytest.importorskip("pyroomacoustics")
    from esiaf.speech.speaker.augment import pink_noise, reverberant
    rng = np.random.default_rng(3)
    noise = pink_noise(64000, rng)
    power = np.abs(np.fft.rfft(noise)) ** 2
    low, high = power[100:200].mean(), power[10000:20000].mean()  # 25-50 Hz against 2.5-5 kHz
    assert np.sqrt(np.mean(noise ** 2)) == pytest.approx(1.0) and low > 20 * high
    t = np.arange(16000) / 16000
    speech = (0.1 * np.sin(2 * np.pi * 220 * t)).astype(np.float32)
    quiet = reverberant(speech, 0.3, (4.0, 5.0, 2.8), 1.0, snr_db=60.0)
    noisy = reverberant(speech, 0.3, (4.0, 5.0, 2.8), 1.0, snr_db=0.0)
    assert quiet.size == noisy.size == 16000 + 1600 and quiet.dtype == np.float32
    assert np.sqrt(np.mean(quiet[-1600:] ** 2)) > 0  # the reverberant tail
    added = noisy - quiet  # the noise alone, at the speech's level for 0 dB
    assert np.sqrt(np.mean(added ** 2)) == pytest.approx(np.sqrt(np.mean(quiet ** 2)), rel=0.02)
    np.testing.assert_array_equal(noisy, reverberant(speech, 0.3, (4.0, 5.0, 2.8), 1.0, snr_db=0.0))
    assert not np.array_equal(noisy, reverberant(speech, 0.3, (4.0, 5.0, 2.8), 1.0, snr_db=0.0, seed=1))


def test_partial_windows_and_the_whole_utterance_mode():
    from esiaf.speech.speaker.ge2e import PARTIAL_FRAMES, partial_starts
    assert partial_starts(16000 * 3) == [0, 77, 154]  # resemblyzer's 1.3 a second: a step of 77 frames
    assert partial_starts(16000 * 3, partials_per_s=2.5) == [0, 40, 80, 120, 160]
    assert partial_starts(8000) == [0]  # shorter than one partial: one, padded
    with pytest.raises(ValueError):
        partial_starts(16000, partials_per_s=0.5)  # a step longer than a partial leaves gaps
    assert PARTIAL_FRAMES == 160


def test_the_encoder_modes_give_unit_embeddings_that_agree_on_a_voice():
    from esiaf.speech.speaker.ge2e import VoiceEncoder
    encoder = VoiceEncoder()
    rng = np.random.default_rng(0)
    t = np.arange(int(16000 * 2.2)) / 16000
    voiced = sum(np.sin(2 * np.pi * 140 * k * t) / k for k in range(1, 12)) * (1 + 0.3 * np.sin(2 * np.pi * 3 * t))
    clip = (0.1 * voiced + 0.005 * rng.normal(size=t.size)).astype(np.float32)
    default, whole = encoder.embed(clip), encoder.embed(clip, whole=True)
    dense = encoder.embed(clip, partials_per_s=2.5)
    for e in (default, whole, dense):
        assert e.shape == (256,) and e.dtype == np.float32 and np.linalg.norm(e) == pytest.approx(1, abs=1e-5)
    assert float(default @ dense) > 0.95  # the same partials, more of them
