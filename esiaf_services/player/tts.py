"""Text to speech for the player: Debian's flite (its voices are compiled in; nothing is downloaded)."""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np


class SpeechError(RuntimeError):
    """flite is missing, has no such voice, or failed; the message says which."""


def voices() -> list[str]:
    if shutil.which("flite") is None:
        raise SpeechError("saying text needs Debian's flite (apt-get install flite)")
    output = subprocess.run(["flite", "-lv"], capture_output=True, text=True, check=False).stdout
    return output.split(":", 1)[1].split() if ":" in output else output.split()


def say(text: str, voice: str, sample_rate_hz: int) -> np.ndarray:
    """``text`` spoken by flite's ``voice``, as float samples (full scale 1) at ``sample_rate_hz``."""
    import soundfile
    import soxr
    if not text.strip():
        raise SpeechError("nothing to say: the text is empty")
    if voice not in voices():
        raise SpeechError(f"flite has no voice {voice!r}; it has {', '.join(voices())}")
    with tempfile.TemporaryDirectory(prefix="esiaf-say-") as folder:
        out = Path(folder) / "say.wav"
        done = subprocess.run(["flite", "-voice", voice, "-t", text, "-o", str(out)], capture_output=True,
                              text=True, check=False)
        if done.returncode != 0 or not out.exists():
            raise SpeechError(f"flite failed: {done.stderr.strip() or done.returncode}")
        samples, rate = soundfile.read(str(out), dtype="float64", always_2d=True)
    mono = samples[:, 0]
    return soxr.resample(mono, rate, sample_rate_hz) if rate != sample_rate_hz else mono
