"""Where the grabber's audio comes from: a file (WAV/FLAC/..., raw, or an MCAP recording's audio) or an
ALSA device.

A source yields (frames, channels) arrays of a fixed format, one chunk at a time.
"""
from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from esiaf import AudioFormat, SetupError
from esiaf.formats import FormatError, decode
from esiaf.receiving import MAX_CHANNELS, MAX_RATE_HZ, MIN_RATE_HZ

if TYPE_CHECKING:
    from esiaf.tools.mcap_replay import McapSource

log = logging.getLogger(__name__)

# soundfile subtype -> (dtype soundfile reads, ESIAF sample type sent); any other (compressed:
# Vorbis, Opus, MP3, FLAC's own, u-law, ...) is decoded by libsndfile to float32
_SUBTYPES = {"PCM_16": ("int16", "int16"), "PCM_24": ("int32", "int32"), "PCM_32": ("int32", "int32"),
             "PCM_S8": ("int16", "int16"), "PCM_U8": ("int16", "int16"), "FLOAT": ("float32", "float32"),
             "DOUBLE": ("float64", "float64")}
RAW_SUFFIXES = (".raw", ".pcm")


class FileSource:
    """A sound file (anything libsndfile reads) or a headerless raw file of a declared format."""

    def __init__(self, path: Path, raw_format: AudioFormat, chunk_ms: float):
        self.path = path
        if not path.is_file():
            raise SetupError(f"input file {path} does not exist or is not a file")
        self._raw = path.suffix.lower() in RAW_SUFFIXES
        if self._raw:
            self.format = raw_format
            try:
                size = path.stat().st_size
                path.open("rb").close()
            except OSError as exc:
                raise SetupError(f"cannot read input file {path}: {exc.strerror}") from None
            if size % self.format.bytes_per_frame:
                log.warning("raw file %s has %d bytes, not a whole number of %s frames; the tail is ignored",
                            path, size, self.format)
            self.total_frames = size // self.format.bytes_per_frame
        else:
            import soundfile
            try:
                info = soundfile.info(str(path))
            except (RuntimeError, soundfile.LibsndfileError) as exc:
                raise SetupError(f"cannot read input file {path}: {exc}") from None
            if not MIN_RATE_HZ <= info.samplerate <= MAX_RATE_HZ or not 1 <= info.channels <= MAX_CHANNELS:
                raise SetupError(f"input file {path}: its header says {info.samplerate} Hz and {info.channels} "
                                 f"channels; the components take {MIN_RATE_HZ} to {MAX_RATE_HZ} Hz and 1 to "
                                 f"{MAX_CHANNELS} channels")
            self._read_dtype, sample_type = _SUBTYPES.get(info.subtype, ("float32", "float32"))
            self.format = AudioFormat(info.samplerate, sample_type, "little", info.channels)
            self.total_frames = info.frames
        self.chunk_frames = max(1, round(self.format.sample_rate_hz * chunk_ms / 1000))

    def chunks(self) -> Iterator[np.ndarray]:
        if self._raw:
            with self.path.open("rb") as handle:
                step = self.chunk_frames * self.format.bytes_per_frame
                while len(data := handle.read(step)) >= self.format.bytes_per_frame:
                    usable = len(data) - len(data) % self.format.bytes_per_frame
                    yield decode(data[:usable], self.format)
            return
        import soundfile
        # read about a second at a time and cut it into chunks: a libsndfile read per chunk was about a
        # tenth of the real-time grabber's own samples in a profile (bench/framework.py --profile)
        block_frames = self.chunk_frames * max(1, self.format.sample_rate_hz // self.chunk_frames)
        with soundfile.SoundFile(str(self.path)) as handle:
            while len(block := handle.read(block_frames, dtype=self._read_dtype, always_2d=True)):
                for offset in range(0, len(block), self.chunk_frames):
                    yield block[offset:offset + self.chunk_frames]


def open_file(path: Path, raw_format: AudioFormat, chunk_ms: float,
              recorded_stream: str | None = None) -> FileSource | McapSource:
    """The source of an input file: a recording's audio (of ``recorded_stream``, None: its first stream),
    chunk by chunk as recorded, if it is MCAP (esiaf/tools/mcap_replay.py); else a sound or raw file."""
    from esiaf.tools.mcap_replay import McapSource, SessionError, is_mcap
    if not is_mcap(path):
        return FileSource(path, raw_format, chunk_ms)
    try:
        return McapSource(path, recorded_stream)
    except SessionError as exc:
        raise SetupError(str(exc)) from None


class AlsaSource:
    """Live capture from a named ALSA device (``arecord -L`` lists them)."""

    _FORMATS: ClassVar[dict[str, str]] = {"int16": "PCM_FORMAT_S16_LE", "int32": "PCM_FORMAT_S32_LE",
                                          "float32": "PCM_FORMAT_FLOAT_LE"}

    def __init__(self, device: str, fmt: AudioFormat, chunk_ms: float):
        try:
            import alsaaudio
        except ImportError:
            raise SetupError("live capture needs pyalsaaudio (pip install pyalsaaudio; "
                             "Debian: apt-get install libasound2-dev first)") from None
        if fmt.sample_type not in self._FORMATS:
            raise SetupError(f"ALSA capture supports sample types {', '.join(self._FORMATS)}, not {fmt.sample_type}")
        self.format = fmt
        self.chunk_frames = max(1, round(fmt.sample_rate_hz * chunk_ms / 1000))
        try:
            self._pcm = alsaaudio.PCM(type=alsaaudio.PCM_CAPTURE, mode=alsaaudio.PCM_NORMAL, device=device,
                                      channels=fmt.channels, rate=fmt.sample_rate_hz,
                                      format=getattr(alsaaudio, self._FORMATS[fmt.sample_type]),
                                      periodsize=self.chunk_frames)
        except alsaaudio.ALSAAudioError as exc:
            raise SetupError(f"cannot open ALSA capture device {device!r}: {exc} "
                             f"(list devices with: arecord -L)") from None
        self.device = device
        self.overruns = 0
        self._pending = b""

    def chunks(self) -> Iterator[np.ndarray]:
        step = self.chunk_frames * self.format.bytes_per_frame
        while True:
            length, data = self._pcm.read()
            if length < 0:  # -EPIPE: overrun, audio was lost
                self.overruns += 1
                log.warning("ALSA overrun device=%s overruns=%d", self.device, self.overruns)
                continue
            if length == 0 and not data:
                return  # the device has nothing more (a file-backed test device at its end)
            self._pending += data
            while len(self._pending) >= step:
                chunk, self._pending = self._pending[:step], self._pending[step:]
                try:
                    yield decode(chunk, self.format)
                except FormatError as exc:
                    log.error("bad capture chunk device=%s error=%s", self.device, exc)

    def close(self) -> None:
        self._pcm.close()
