"""The ingest's warm start from the database: latencies (so timeouts), the recent results and fused
results of each stream (for late results), and the fusions that were still waiting."""
from __future__ import annotations

import json
import logging
from typing import TYPE_CHECKING

from ..fusion.engine import StoredResult
from ..settings import FusionSettings

if TYPE_CHECKING:
    from ..planes.ingest import Ingest

log = logging.getLogger(__name__)


def restore(ingest: Ingest) -> None:
    engine, store = ingest.engine, ingest.store
    for component, count, mean_ns in store.latencies():
        if mean_ns >= 0:  # a negative mean: learnt from replays by an older version; start again
            engine.latencies.restore(component, count, mean_ns)
    for stream_id, _start_ns, source, _announced_ns, info in store.streams():
        ingest.on_stream_announced(stream_id, source, json.loads(info))
    results, fused = store.recent(engine.memory_ns)
    for text in results:
        restored = StoredResult.from_json(json.loads(text))
        engine.restore_result(restored)
        # a stream heard from lately is taken to be going on: replicas serve it as their instances
        # register again, not only from its next result on
        ingest.registry.add_stream(restored.stream_id)
    for text in fused:
        engine.restore_published(json.loads(text))
    pending = store.pending()
    for fused_id, anchor, settings, waiting in pending:
        engine.restore_open(fused_id, FusionSettings.model_validate_json(settings),
                            StoredResult.from_json(json.loads(anchor)),
                            {c: tuple(w) for c, w in json.loads(waiting).items()})
    log.info("event=fusion_restored latencies=%d results=%d fused=%d pending=%d",
             len(engine.latencies.by_component), len(results), len(fused), len(pending))
