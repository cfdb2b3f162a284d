"""Where the player's audio goes: an ALSA playback device, or a file or FIFO (tests, simulations).

A sink takes int16 mono chunks. ``write`` returns when the chunk is queued: an ALSA device blocks
while its buffer is full (so it paces the player), a file does not (the player paces itself).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from esiaf import SetupError

log = logging.getLogger(__name__)


class AlsaSink:
    """A named ALSA playback device (``aplay -L`` lists them)."""

    paced = True  # write() blocks at the device's pace

    def __init__(self, device: str, sample_rate_hz: int, chunk_frames: int):
        try:
            import alsaaudio
        except ImportError:
            raise SetupError("playing to a device needs pyalsaaudio (pip install pyalsaaudio; "
                             "Debian: apt-get install libasound2-dev first)") from None
        try:
            self._pcm = alsaaudio.PCM(type=alsaaudio.PCM_PLAYBACK, mode=alsaaudio.PCM_NORMAL, device=device,
                                      channels=1, rate=sample_rate_hz, format=alsaaudio.PCM_FORMAT_S16_LE,
                                      periodsize=chunk_frames)
        except alsaaudio.ALSAAudioError as exc:
            why = "another program plays to it" if "busy" in str(exc).lower() else "list devices with: aplay -L"
            raise SetupError(f"cannot open ALSA playback device {device!r}: {exc} ({why})") from None
        self.device = device
        self.underruns = 0

    def write(self, pcm: np.ndarray) -> None:
        if self._pcm.write(pcm.astype("<i2").tobytes()) < 0:  # -EPIPE: the device ran dry, it recovers
            self.underruns += 1
            log.warning("ALSA underrun device=%s underruns=%d", self.device, self.underruns)

    def drop(self) -> None:
        """Stop now: what the device still holds is not played."""
        self._pcm.drop()

    def close(self) -> None:
        self._pcm.close()


class FileSink:
    """Raw s16le (or a WAV file, by its suffix) written to ``path``: a FIFO is opened at the first write,
    so a reader may come later."""

    paced = False

    def __init__(self, path: Path, sample_rate_hz: int):
        self.path = path
        self.sample_rate_hz = sample_rate_hz
        if not path.parent.is_dir():
            raise SetupError(f"cannot play to {path}: its folder does not exist")
        self._raw: BinaryIO | None = None
        self._wav: Any = None  # a soundfile.SoundFile

    def write(self, pcm: np.ndarray) -> None:
        if self.path.suffix.lower() == ".wav":
            if self._wav is None:
                import soundfile
                self._wav = soundfile.SoundFile(str(self.path), "w", self.sample_rate_hz, 1, "PCM_16")
            self._wav.write(pcm)
            return
        if self._raw is None:
            try:
                self._raw = self.path.open("wb", buffering=0)
            except OSError as exc:
                raise SetupError(f"cannot play to {self.path}: {exc.strerror}") from None
        self._raw.write(pcm.astype("<i2").tobytes())

    def drop(self) -> None:
        """A file holds nothing back to drop."""

    def close(self) -> None:
        for handle in (self._wav, self._raw):
            if handle is not None:
                handle.close()
