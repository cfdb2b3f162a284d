"""End to end: held-out speakers' utterances through grabber → vad → emotion + gender → orchestrator.

The models are the hold-out ones (``models/holdout/``, trained without speakers 03 and 08); the
training script stored what they predict for each of those speakers' utterances, judged offline on
the segments each way the VAD cuts (``features.VADS``: Silero per window or per chunk, energy)
would cut of the whole file. Played through the pipeline cut each way, where the VAD decides where
each utterance starts and ends, the labels must agree with the truth as often as offline, within
a few points.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from esiaf.speech.opensmile import VADS
from esiaf.tools.testing import REPO, shared_data
from esiaf_services.emotion.tools.pipeline import EmotionPipeline, build_recording, labels_by_utterance

pytestmark = pytest.mark.e2e
HOLDOUT = REPO / "esiaf_services" / "emotion" / "models" / "holdout"
GAP_S = 1.2  # silence between utterances: longer than the VAD's 400 ms hang-over
TOLERANCE = 0.05  # "within a few points"


@pytest.mark.parametrize("vad", VADS)
def test_held_out_speakers_through_the_pipeline_agree_with_offline_accuracy(tmp_path, vad):
    cards = {kind: json.loads((HOLDOUT / f"{model}.json").read_text())
             for kind, model in (("emotion", "emotion4"), ("gender", "gender"))}
    relative = sorted(cards["emotion"]["predictions"])  # the 4-class utterances of speakers 03 and 08
    files = [shared_data(f"emodb/{p}") for p in relative]
    placed = build_recording(files, tmp_path / "heldout.wav", GAP_S)
    name = {str(f): p for f, p in zip(files, relative, strict=True)}

    pipeline = EmotionPipeline(tmp_path, str(HOLDOUT / "emotion4.onnx"), str(HOLDOUT / "gender.onnx"), "heldout",
                               vad_backend=vad)
    try:
        # per window at the grabber's default chunk (its segments do not depend on it); per chunk at
        # the 20 ms chunks the offline spans are cut in
        arrived, origin_ns = pipeline.play(tmp_path / "heldout.wav", fast=True,
                                           chunk_ms=None if vad == "silero" else 20.0)
    finally:
        pipeline.close()
    fused = [f for _, f in arrived]

    for kind, card in cards.items():
        got = {name[path]: label for path, label in labels_by_utterance(fused, kind, placed, origin_ns).items()}
        assert len(got) >= 0.95 * len(relative), f"{kind}: only {len(got)} of {len(relative)} utterances labelled"
        truth = {p: card["predictions"][p]["truth"] for p in relative}
        # offline (training/emodb.py): the hold-out model on the longest segment this VAD cuts of each whole
        # file, the one the fused result overlapping the utterance most is about; and on all of its speech
        offline = {p: card["predictions"][p][f"predicted_longest_{vad}"] for p in relative}
        whole_key = "predicted" if card.get("vad", "silero") == vad else f"predicted_{vad}"
        pipeline_accuracy = np.mean([got.get(p) == truth[p] for p in relative])
        offline_accuracy = np.mean([offline[p] == truth[p] for p in relative])
        whole_accuracy = np.mean([card["predictions"][p][whole_key] == truth[p] for p in relative])
        agreement = np.mean([got.get(p) == offline[p] for p in relative])
        print(f"{kind} ({vad} VAD): pipeline accuracy {pipeline_accuracy:.3f}, offline {offline_accuracy:.3f} "
              f"(all of each utterance's speech {whole_accuracy:.3f}), same label as offline {agreement:.3f} "
              f"({len(relative)} utterances)")
        assert abs(pipeline_accuracy - offline_accuracy) <= TOLERANCE, (kind, pipeline_accuracy, offline_accuracy)
        assert agreement >= 0.85, (kind, agreement)
        # what the VAD's splitting at pauses costs: a few utterances (slow, sad ones) judged on a part
        assert pipeline_accuracy >= whole_accuracy - 2 * TOLERANCE, (kind, pipeline_accuracy, whole_accuracy)
