"""The warm start of fusion state from the database: latencies (so timeouts), the recent results and fused
results of each stream (for late results), and the fusions that were still waiting."""
from __future__ import annotations

import json
import logging
from collections.abc import Callable
from typing import Any

from ..fusion.engine import FusionEngine, StoredResult
from ..registry.components import Registry
from ..settings import FusionSettings
from .database import Store

log = logging.getLogger(__name__)


def restore(store: Store, engine: FusionEngine, registry: Registry,
            on_stream_announced: Callable[[str, str, dict[str, Any]], None]) -> None:
    """Fills ``engine`` (and ``registry``'s active streams) from ``store``; each stored stream
    announcement is replayed through ``on_stream_announced``."""
    for component, count, mean_ns in store.latencies():
        if mean_ns >= 0:  # a negative mean: learnt from replays by an older version; start again
            engine.latencies.restore(component, count, mean_ns)
    for stream_id, _start_ns, source, _announced_ns, info in store.streams():
        on_stream_announced(stream_id, source, json.loads(info))
    results, fused = store.recent(engine.memory_ns)
    for text in results:
        restored = StoredResult.from_json(json.loads(text))
        engine.restore_result(restored)
        # a stream heard from lately is taken to be going on: replicas serve it as their instances
        # register again, not only from its next result on
        registry.add_stream(restored.stream_id)
    for text in fused:
        engine.restore_published(json.loads(text))
    pending = store.pending()
    for fused_id, anchor, settings, waiting in pending:
        engine.restore_open(fused_id, FusionSettings.model_validate_json(settings),
                            StoredResult.from_json(json.loads(anchor)),
                            {c: tuple(w) for c, w in json.loads(waiting).items()})
    log.info("event=fusion_restored latencies=%d results=%d fused=%d pending=%d",
             len(engine.latencies.by_component), len(results), len(fused), len(pending))
