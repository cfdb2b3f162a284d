"""Utterance classifiers behind one small interface, picked by name in the settings.

A backend turns one whole utterance (mono float samples in [-1, 1]) into a probability per
label. Two are built in:

- ``onnx``: an ONNX classifier over openSMILE functionals, plus its label map, a JSON file
  beside it (``model.onnx`` -> ``model.json``) that names the feature set and the labels in the
  order of the model's probability output. The bundled models are of this kind.
- ``python``: your own class, ``package.module:ClassName``, built with ``model_options`` as
  keyword arguments; it subclasses :class:`Classifier` (``labels`` + ``classify``).

Every failure to load is a :class:`BackendError` with one line that names the file and what
is wrong with it; the service turns it into a clean start-up error.
"""
from __future__ import annotations

import importlib
import json
from abc import ABC, abstractmethod
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from esiaf import SetupError
from esiaf.speech.opensmile import FeatureError, shared_extractor, without_digital_silence


class BackendError(Exception):
    """A model that cannot be used: missing, corrupt, or inconsistent with its label map."""


class Classifier(ABC):
    """What a backend is: labels, and a probability per label for one utterance."""

    labels: tuple[str, ...] = ()
    sample_rate_hz: int = 16000

    @abstractmethod
    def classify(self, samples: np.ndarray) -> dict[str, float]:
        """``samples``: one utterance, mono float32 in [-1, 1] at ``sample_rate_hz``."""


def resolve_model(model: str, models_dir: Path | None = None) -> Path:
    """A bundled model's name (``emotion4``: ``models_dir``/emotion4.onnx, the service's own models
    folder) or a path to an ``.onnx`` file."""
    if "/" in model or model.endswith(".onnx"):
        return Path(model)
    if models_dir is None:
        raise BackendError(f"model {model!r} is a bundled model's name, and no models folder was given: "
                           f"name an .onnx file")
    return models_dir / f"{model}.onnx"


class OnnxClassifier(Classifier):
    """openSMILE functionals of the utterance -> ONNX model -> probabilities (onnxruntime)."""

    def __init__(self, model: str, label_map: str = "", threads: int = 1, models_dir: Path | None = None):
        path = resolve_model(model, models_dir)
        map_path = Path(label_map) if label_map else path.with_suffix(".json")
        if not path.is_file():
            raise BackendError(f"model file {path} does not exist")
        try:
            card = json.loads(map_path.read_text())
            self.labels = tuple(card["labels"])
            feature_set = card["features"]
            self.sample_rate_hz = int(card.get("sample_rate_hz", 16000))
        except OSError as exc:
            raise BackendError(f"cannot read the label map {map_path} of model {path}: {exc.strerror}") from None
        except (ValueError, KeyError, TypeError) as exc:
            raise BackendError(f"label map {map_path} is not JSON with 'labels' and 'features': {exc}") from None
        self.card = card
        try:
            import onnxruntime
        except ImportError:
            raise BackendError("the onnxruntime package is missing: pip install -e '.[emotion]'") from None
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = threads
        options.log_severity_level = 4  # errors come back as exceptions, not C++ log lines
        try:
            self.session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as exc:  # onnxruntime raises its own Fail/InvalidGraph/... types
            raise BackendError(f"model file {path} is not a usable ONNX model: {str(exc).splitlines()[0]}") from None
        try:
            # one per process and feature set: classifiers hosted together compute an utterance's features once
            self.features = shared_extractor(feature_set, self.sample_rate_hz)
        except FeatureError as exc:
            raise BackendError(f"label map {map_path}: {exc}") from None
        self._input = self.session.get_inputs()[0].name
        outputs = [o.name for o in self.session.get_outputs()]
        self._output = "probabilities" if "probabilities" in outputs else outputs[-1]
        width = self.session.get_inputs()[0].shape[-1]
        size = self.features.extractor.size
        if isinstance(width, int) and width != size:
            raise BackendError(f"model {path} takes {width} features but {feature_set} has {size}")
        probe = self._run(np.zeros(size, dtype=np.float32), path)
        if probe.shape != (len(self.labels),):
            raise BackendError(f"model {path} gives {probe.shape[0]} probabilities but its label map "
                               f"{map_path} names {len(self.labels)} labels")

    def _run(self, vector: np.ndarray, path: Path | str = "model") -> np.ndarray:
        try:
            output = self.session.run([self._output], {self._input: vector[None, :]})[0]
        except Exception as exc:
            raise BackendError(f"{path} failed to run: {str(exc).splitlines()[0]}") from None
        return np.asarray(output, dtype=np.float64).reshape(-1)

    def classify(self, samples: np.ndarray) -> dict[str, float]:
        probabilities = self._run(self.features(without_digital_silence(samples)))
        return dict(zip(self.labels, probabilities.tolist(), strict=True))


def python_classifier(model: str, **options: Any) -> Classifier:
    """``package.module:ClassName`` built with ``options``."""
    module_name, sep, class_name = model.partition(":")
    if not sep or not module_name or not class_name:
        raise BackendError(f"a python backend's model is 'package.module:ClassName', not {model!r}")
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as exc:
        raise BackendError(f"cannot import the classifier {model}: {exc}") from None
    if not (isinstance(cls, type) and issubclass(cls, Classifier)):
        raise BackendError(f"{model} is not a subclass of esiaf.speech.classifiers.Classifier")
    try:
        classifier = cls(**options)
    except Exception as exc:  # the user's constructor: report it in one line
        raise BackendError(f"{model}({options}) failed: {type(exc).__name__}: {exc}") from None
    if not classifier.labels:
        raise BackendError(f"{model} has no labels")
    return classifier


BACKENDS: dict[str, Callable[..., Classifier]] = {
    "onnx": lambda model, **options: OnnxClassifier(model, **options),
    "python": python_classifier,
}


def load_classifier(service: str, backend: str, model: str, options: dict[str, Any],
                    models_dir: Path | None = None) -> Classifier:
    """A service's model, as its settings name it (a bundled one from ``models_dir``, the service's
    models folder); a SetupError (one line) if it cannot be used."""
    try:
        return load_backend(backend, model, options, models_dir)
    except BackendError as exc:
        raise SetupError(f"{service} model: {exc}") from None


def load_backend(backend: str, model: str, options: dict[str, Any] | None = None,
                 models_dir: Path | None = None) -> Classifier:
    if backend not in BACKENDS:
        raise BackendError(f"unknown backend {backend!r}; known: {', '.join(BACKENDS)}")
    try:
        if backend == "onnx":
            return OnnxClassifier(model, **(options or {}), models_dir=models_dir)
        return BACKENDS[backend](model, **(options or {}))
    except TypeError as exc:
        raise BackendError(f"bad model_options for the {backend} backend: {exc}") from None
