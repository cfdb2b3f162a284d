"""A consumer for tests/test_replicas.py, run as its own process (so a test can kill it): writes
each audio message it takes, as "stream sequence", to a file.

    PYTHONPATH=. python tests/replica_sink.py ORCHESTRATOR_URL OUT_FILE INSTANCE_ID
"""
from __future__ import annotations

import sys
from pathlib import Path

from esiaf import Audio, AudioFormat, Component


class ReplicaSink(Component):
    service = "sink"

    def __init__(self, settings, out: Path):
        super().__init__(settings)
        self.add_input("source/audio", AudioFormat(16000, "int16"))
        self.out = out.open("a", buffering=1)

    def on_audio(self, audio: Audio) -> None:
        self.out.write(f"{audio.stream_id} {audio.sequence}\n")


if __name__ == "__main__":
    url, out, instance = sys.argv[1:4]
    sink = ReplicaSink(ReplicaSink.Settings(name="sink", orchestrator_url=url, instance=instance), Path(out))
    sys.exit(sink.run())
