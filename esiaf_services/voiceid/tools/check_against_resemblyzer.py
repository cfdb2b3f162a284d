"""Compare the numpy encoder (``esiaf/speech/speaker/ge2e.py``) with resemblyzer's own, number by number.

This tool needs torch and resemblyzer, which the project never installs and never imports at run
time. Run it from a throwaway venv outside the repository::

    python3 -m venv /tmp/torchvenv
    /tmp/torchvenv/bin/pip install torch resemblyzer==0.1.4 'setuptools<81' pyyaml pydantic soundfile
    ESIAF_SHARED_DATA=/work/shared/data PYTHONPATH=. \\
        /tmp/torchvenv/bin/python esiaf_services/voiceid/tools/check_against_resemblyzer.py [--files 10]

(``setuptools<81``: webrtcvad, which resemblyzer imports, still needs ``pkg_resources``; pyyaml and
pydantic only for ``esiaf.scenes.speech_bounds``.) The weights both sides read are the same file,
the installed resemblyzer's ``pretrained.pt``.

For ``--files`` EmoDB utterances spread over the corpus it prints, stage by stage:

- ``resample``: a 44.1 kHz copy of the file (made with soxr) brought back to 16 kHz as the
  orchestrator's WAV enrolment does (``scipy.signal.resample_poly``, ``esiaf_services/orchestrator/api/voices.py``)
  and as ``preprocess_wav`` does (``librosa.resample``): relative max difference of the samples, and
  cosine between the numpy embeddings of the two;
- ``volume``: the -30 dBFS raise (``normalize_volume``) against ``resemblyzer.audio.normalize_volume``;
- ``trim``: what resemblyzer's webrtcvad trimming keeps (``preprocess_wav``) against the speech
  span the project embeds (``esiaf.scenes.speech_bounds``, as ``bench/voiceid.py``), in samples;
- ``mel``: the mel filterbank and the mel spectrogram of the same samples against librosa's, both
  with librosa's current padding (zeros since librosa 0.10) and with the reflect padding of the
  librosa that resemblyzer was written for (relative max difference);
- ``slices``: the partial windows (``partial_starts`` against ``compute_partial_slices``);
- ``lstm``: the same (partials, 160, 40) mel batch through the numpy network and through torch's;
- ``same input``: the utterance embedding of resemblyzer's preprocessed samples by both
  (``reflect max``: against torch fed librosa's spectrogram with reflect padding);
- ``as used``: the project's embedding of the speech span against
  ``VoiceEncoder().embed_utterance(preprocess_wav(path))``, i.e. what the service computes against
  what resemblyzer computes from the file.

Embeddings are compared by cosine and max absolute difference. The numpy encoder is run at
resemblyzer's 1.3 partials a second (its own default is denser, 2.5: that is a choice, not a
port). With ``--bench``, it also embeds every EmoDB utterance as resemblyzer does
(``embed_utterance(preprocess_wav(file))``, its own trimming instead of the speech span) and
prints ``bench/voiceid.py``'s clean figures for them.
"""
from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from pathlib import Path

import numpy as np
import soundfile

warnings.filterwarnings("ignore")  # webrtcvad's pkg_resources, scipy's ndimage.morphology

try:
    import librosa
    import soxr
    import torch
    from resemblyzer import VoiceEncoder as TorchEncoder
    from resemblyzer import audio as res_audio
    from resemblyzer import preprocess_wav
    from scipy.signal import resample_poly
except ImportError as exc:  # pragma: no cover - the point is to say where it runs
    sys.exit(f"check_against_resemblyzer: {exc}. Run it from a venv with torch and resemblyzer "
             f"(see this file's docstring), never the project's.")

from esiaf.scenes import speech_bounds  # noqa: E402 (after the check above: one clear line without torch)
from esiaf.speech.speaker import ge2e as np_encoder  # noqa: E402
from esiaf.tools.testing import SHARED_DATA  # noqa: E402


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-30))


def slices_agree(lengths: range) -> int:
    """How many lengths get different partial windows from the two implementations."""
    bad = 0
    for n in lengths:
        _, mel_slices = TorchEncoder.compute_partial_slices(n, 1.3, 0.75)
        if [s.start for s in mel_slices] != np_encoder.partial_starts(n):
            bad += 1
    return bad


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument("--files", type=int, default=10, help="EmoDB utterances compared (spread over the corpus)")
    parser.add_argument("--bench", action="store_true", help="bench/voiceid.py's clean figures of resemblyzer's "
                                                                 "own embeddings of all of EmoDB")
    args = parser.parse_args()
    torch.set_num_threads(1)
    wavs = sorted((SHARED_DATA / "emodb" / "wav").glob("*.wav"))
    if not wavs:
        sys.exit(f"check_against_resemblyzer: no EmoDB under {SHARED_DATA} (set ESIAF_SHARED_DATA)")
    chosen = wavs[::max(1, len(wavs) // args.files)][:args.files]
    reference = TorchEncoder(device="cpu", verbose=False)
    ours = np_encoder.VoiceEncoder(np_encoder.weights_path())

    filters = librosa.filters.mel(sr=16000, n_fft=400, n_mels=40)
    print(f"mel filterbank: max |numpy - librosa| = {np.max(np.abs(np_encoder.mel_filters() - filters)):.2e} "
          f"(filters up to {filters.max():.2e})")
    print(f"partial windows: {slices_agree(range(400, 160000, 37))} of {len(range(400, 160000, 37))} lengths differ")
    columns = ("file", "resample", "resample cos", "volume", "raw s", "span s", "trimmed s", "mel now",
               "mel reflect", "lstm max", "same cos", "same max", "reflect max", "used cos", "used max")
    print("\t".join(columns))
    rows = []
    for path in chosen:
        raw, rate = soundfile.read(path, dtype="float32")
        assert rate == 16000
        high = soxr.resample(raw, 16000, 44100)
        ours_16k = resample_poly(high, 160, 441).astype(np.float32)  # gcd(44100, 16000) = 100, as voices.py
        theirs_16k = librosa.resample(high, orig_sr=44100, target_sr=16000)
        n = min(ours_16k.size, theirs_16k.size)
        resample = rel_diff(ours_16k[:n], theirs_16k[:n])
        resample_cos = cosine(ours.embed(ours_16k, partials_per_s=np_encoder.RESEMBLYZER_PARTIALS_PER_S),
                              ours.embed(theirs_16k, partials_per_s=np_encoder.RESEMBLYZER_PARTIALS_PER_S))
        volume = float(np.max(np.abs(np_encoder.normalize_volume(raw) -
                                     res_audio.normalize_volume(raw, -30, increase_only=True))))
        first, last = speech_bounds(raw)
        span = raw[first:last]
        trimmed = preprocess_wav(path)
        # mel spectrogram and network on resemblyzer's own preprocessed, padded samples
        wav_slices, mel_slices = TorchEncoder.compute_partial_slices(len(trimmed), 1.3, 0.75)
        padded = np.pad(trimmed, (0, max(0, wav_slices[-1].stop - len(trimmed))))
        mel_ours = np_encoder.mel_spectrogram(padded)
        mel_now = res_audio.wav_to_mel_spectrogram(padded)
        mel_reflect = librosa.feature.melspectrogram(y=padded, sr=16000, n_fft=400, hop_length=160, n_mels=40,
                                                     pad_mode="reflect").astype(np.float32).T
        batch = np.stack([mel_now[s] for s in mel_slices])
        with torch.no_grad():
            partial_torch = reference(torch.from_numpy(batch)).numpy()
        partial_numpy = ours.embed_mels(batch)
        same_torch = reference.embed_utterance(trimmed)
        with torch.no_grad():  # the same with the reflect padding of resemblyzer's day
            partials = reference(torch.from_numpy(np.stack([mel_reflect[s] for s in mel_slices]))).numpy()
        reflect_torch = partials.mean(axis=0) / np.linalg.norm(partials.mean(axis=0))
        same_numpy = ours.embed(trimmed, partials_per_s=np_encoder.RESEMBLYZER_PARTIALS_PER_S)
        used_numpy = ours.embed(span, partials_per_s=np_encoder.RESEMBLYZER_PARTIALS_PER_S)
        row = (path.name, resample, resample_cos, volume, raw.size / 16000, span.size / 16000, trimmed.size / 16000,
               rel_diff(mel_ours, mel_now), rel_diff(mel_ours, mel_reflect),
               float(np.max(np.abs(partial_numpy - partial_torch))),
               cosine(same_numpy, same_torch), float(np.max(np.abs(same_numpy - same_torch))),
               float(np.max(np.abs(same_numpy - reflect_torch))),
               cosine(used_numpy, same_torch), float(np.max(np.abs(used_numpy - same_torch))))
        rows.append(row)
        print("\t".join([row[0]] + [f"{v:.2e}" if i in (1, 3, 7, 8, 9, 11, 12, 14) else
                                    f"{v:.6f}" if i in (2, 10, 13) else f"{v:.2f}" for i, v in enumerate(row) if i]),
              flush=True)
    values = np.array([r[3:] for r in rows], float)
    print(f"same input: cosine min {values[:, 7].min():.6f}, max |diff| {values[:, 8].max():.2e} "
          f"({values[:, 9].max():.2e} with reflect padding); as used: cosine mean {values[:, 10].mean():.4f} "
          f"min {values[:, 10].min():.4f}, max |diff| {values[:, 11].max():.3f}; "
          f"lstm max |diff| {values[:, 6].max():.2e}; resampling: samples differ by {max(r[1] for r in rows):.2e} "
          f"of the peak at most, embeddings' cosine min {min(r[2] for r in rows):.6f}")
    if args.bench:
        bench_resemblyzer(reference, wavs)


def bench_resemblyzer(reference: TorchEncoder, wavs: list[Path]) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[3]))
    bench = importlib.import_module("bench.voiceid")  # a script's functions (not a package mypy should follow)
    evaluate, show = bench.evaluate, bench.show
    names = [p.name for p in wavs]
    speakers, neutral = [n[:2] for n in names], [n[5] == "N" for n in names]
    embeddings = np.stack([reference.embed_utterance(preprocess_wav(p)) for p in wavs])
    show({f"resemblyzer_{k}": v for k, v in evaluate(names, speakers, neutral, embeddings).items()})
    calm = [i for i, n in enumerate(neutral) if n]
    show({f"resemblyzer_neutral_{k}": v for k, v in evaluate([names[i] for i in calm], [speakers[i] for i in calm],
                                                             [True] * len(calm), embeddings[calm]).items()})


if __name__ == "__main__":
    main()
