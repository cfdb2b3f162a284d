"""The torch-legacy reader (against a file written here by hand, byte for byte as torch 1.x did)
and the open-set scoring with anonymous voices."""
from __future__ import annotations

import pickle
import struct

import numpy as np
import pytest

from services.voiceid import torch_legacy
from services.voiceid.scoring import AnonymousVoices, VoiceBook, probability


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
    from services.voiceid.encoder import weights_path
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


def test_anonymous_voices_keep_their_ids_and_are_bounded():
    voices = AnonymousVoices(threshold=0.9, limit=2)
    assert voices.assign(_unit([1, 0, 0]))[0] == "voice-1"
    assert voices.assign(_unit([0, 1, 0]))[0] == "voice-2"
    assert voices.assign(_unit([1, 0.05, 0]))[0] == "voice-1"  # heard again
    assert voices.assign(_unit([0, 0, 1]))[0] == "voice-3"  # voice-2, least recently heard, is forgotten
    assert list(voices.voices) == ["voice-1", "voice-3"]
    assert voices.assign(_unit([0, 1, 0]))[0] == "voice-4"


def test_the_fused_voice_is_the_results_label_not_the_best_enrolled_score():
    from services.orchestrator.aggregate import label_aggregate
    stranger = {"span": {"start_ns": 0, "end_ns": 2_000_000_000},
                "voice_id": {"label": "voice-2", "probability": 0.9, "class_probabilities": {"Anna": 0.6}}}
    aggregate = label_aggregate([stranger], "voice_id", (0, 2_000_000_000))
    assert aggregate["label"] == "voice-2" and aggregate["probability"] == pytest.approx(0.9)
    assert aggregate["distribution"] == {"voice-2": pytest.approx(0.9), "unknown": pytest.approx(0.1)}
