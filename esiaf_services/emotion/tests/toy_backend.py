"""A Python backend for the tests: 'loud' or 'quiet' by the utterance's RMS level."""
import numpy as np

from esiaf.speech.classifiers import Classifier


class LoudnessClassifier(Classifier):
    labels = ("quiet", "loud")

    def __init__(self, threshold_rms: float = 0.05):
        self.threshold_rms = threshold_rms

    def classify(self, samples: np.ndarray) -> dict[str, float]:
        loud = float(np.sqrt(np.mean(np.square(samples))) > self.threshold_rms)
        return {"quiet": 1.0 - 0.9 * loud, "loud": 0.1 + 0.8 * loud}
