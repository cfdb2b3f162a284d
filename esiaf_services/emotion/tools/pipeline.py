"""EmoDB utterances through the real pipeline, for the end-to-end test and ``bench/emotion.py``.

:func:`build_recording` lays utterances end to end with silence between; :class:`EmotionPipeline`
starts the orchestrator (fusions anchored on emotion and on gender), the emotion, gender and VAD
services as processes, plays a file with the grabber and collects the fused results, with the
moment each arrived, from the orchestrator's websocket.
"""
from __future__ import annotations

import contextlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil
import soundfile
import yaml
from websockets.sync.client import connect

from esiaf.tools.cli import topic_ready
from esiaf.tools.launcher import OrchestratorClient, Supervisor, wait_until
from esiaf.tools.testing import free_port

START_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Placed:
    path: str
    start_s: float
    end_s: float


def build_recording(files: list[Path], wav: Path, gap_s: float) -> list[Placed]:
    """The files one after the other, ``gap_s`` of silence before, between and after them."""
    gap = np.zeros(int(gap_s * 16000), np.int16)
    pieces, placed, t = [gap], [], gap_s
    for path in files:
        samples, rate = soundfile.read(path, dtype="int16")
        if rate != 16000 or samples.ndim != 1:
            raise ValueError(f"{path} is not 16 kHz mono")
        placed.append(Placed(str(path), t, t + len(samples) / rate))
        pieces += [samples, gap]
        t += len(samples) / rate + gap_s
    soundfile.write(wav, np.concatenate(pieces), 16000, subtype="PCM_16")
    return placed


class EmotionPipeline:
    """orchestrator + emotion + gender + vad as processes; ``play`` adds the grabber. ``hosted``:
    gender runs in the emotion service's process (its guest), the features computed once."""

    def __init__(self, workdir: Path, emotion_model: str, gender_model: str, stream_id: str = "emotion",
                 vad_backend: str = "silero", hosted: bool = False):
        self.stream_id = stream_id
        port = free_port()
        self.url = f"http://127.0.0.1:{port}"
        config = workdir / "orchestrator.yaml"
        config.write_text(yaml.safe_dump({"fusions": [{"name": "emotion", "anchor": "emotion"},
                                                      {"name": "gender", "anchor": "gender"}]}))
        self.supervisor = Supervisor(workdir, env={"ESIAF_ORCHESTRATOR_URL": self.url, "ESIAF_STREAM_ID": stream_id})
        self.client = OrchestratorClient(self.url)
        try:
            self._start("orchestrator", ["--port", str(port), "--db", str(workdir / "esiaf.db"), "--config",
                                         str(config)], client_ready=self.client.healthy,
                        env={"ESIAF_ORCHESTRATOR_CONTROL_PORT": "0", "ESIAF_ORCHESTRATOR_RESULTS_PORT": "0"})
            if hosted:
                self._start("emotion", ["--model", emotion_model], env={
                    "ESIAF_EMOTION_GUESTS": '["gender"]', "ESIAF_GENDER_MODEL": gender_model})
                wait_until(lambda: self.client.component("gender"), self.supervisor, "gender to come up",
                           START_TIMEOUT_S)
            else:
                for service, model in (("emotion", emotion_model), ("gender", gender_model)):
                    self._start(service, ["--model", model])
            # vad_backend: how the vad cuts (features.VADS): silero per window, silero-chunks, energy
            vad_env = {"ESIAF_VAD_BACKEND": "energy"} if vad_backend == "energy" else {
                "ESIAF_VAD_BACKEND": "silero", "ESIAF_VAD_SILERO__WINDOWS": str(vad_backend == "silero").lower()}
            self._start("vad", [], env=vad_env)
            wait_until(lambda: topic_ready(self.client, "vad/speech", 1 if hosted else 2), self.supervisor,
                       "emotion and gender to subscribe to vad/speech", START_TIMEOUT_S)
        except BaseException:
            self.close()
            raise

    def _start(self, name: str, args: list[str], client_ready=None, env=None) -> None:
        child = self.supervisor.start(name, args, env=env)
        ready = client_ready or (lambda: self.client.component(name))
        wait_until(ready, self.supervisor, f"{name} to come up", START_TIMEOUT_S, child)

    def _per_service(self, measure) -> dict[str, float]:
        out = {}
        for child in self.supervisor.children:
            with contextlib.suppress(psutil.NoSuchProcess):
                out[child.name] = measure(psutil.Process(child.process.pid))
        return out

    def rss_mb(self) -> dict[str, float]:
        """Resident memory (MB) of each service's process now."""
        return self._per_service(lambda process: process.memory_info().rss / 1e6)

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds (user + system) each service has used so far."""
        return self._per_service(lambda process: sum(process.cpu_times()[:2]))

    def play(self, wav: Path, fast: bool, timeout_s: float = 300.0,
             chunk_ms: float | None = None) -> tuple[list[tuple[int, dict]], int]:
        """Plays ``wav`` (in ``chunk_ms`` chunks: the grabber's default if None); returns [(arrival
        wall-clock ns, fused result)] until stream end, and its origin."""
        fused = []
        url = self.url.replace("http", "ws") + f"/ws/fused?stream={self.stream_id}&after_id=0"
        with connect(url, open_timeout=10) as ws:
            self.supervisor.start("grabber", ["--input", str(wav)] + (["--fast"] if fast else []),
                                  env={"ESIAF_GRABBER_WAIT_FOR_SUBSCRIBERS": "1"}
                                  | ({"ESIAF_GRABBER_CHUNK_MS": str(chunk_ms)} if chunk_ms else {}))
            deadline = time.monotonic() + timeout_s
            while True:
                message = json.loads(ws.recv(timeout=max(1.0, deadline - time.monotonic())))
                if message["type"] == "stream_end":
                    break
                fused.append((time.time_ns(), message))
        stream = self.client.stream(self.stream_id)
        assert stream is not None  # it ended: it was announced
        return fused, stream["start_ns"]

    def close(self) -> None:
        self.client.close()
        self.supervisor.stop()


def labels_by_utterance(fused: list[dict], kind: str, placed: list[Placed], origin_ns: int) -> dict[str, str]:
    """Each utterance's label: that of the fused ``kind`` result overlapping it most."""
    best: dict[str, tuple[float, str]] = {}
    for f in fused:
        if f["fusion"] != kind:
            continue
        span = f["anchor"]["span"]
        start_s, end_s = (span["start_ns"] - origin_ns) / 1e9, (span["end_ns"] - origin_ns) / 1e9
        for u in placed:
            overlap = min(end_s, u.end_s) - max(start_s, u.start_s)
            if overlap > best.get(u.path, (0.0, ""))[0]:
                best[u.path] = (overlap, f["anchor"][kind]["label"])
    return {path: label for path, (_, label) in best.items()}
