from __future__ import annotations

from fastapi import APIRouter, Depends

from ..core import Orchestrator
from ..registry.components import Component
from ..registry.negotiation import bytes_per_second, conversions, key
from .deps import get_core
from .models import TopicConsumer, TopicInfo, TopicList, TopicProducer

router = APIRouter(tags=["topics"])


def _subscribers(producer: Component, topic: str) -> int | None:
    outputs = (producer.stats or {}).get("outputs")
    reported = outputs.get(topic) if isinstance(outputs, dict) else None
    count = reported.get("subscribers") if isinstance(reported, dict) else None
    return count if isinstance(count, int) else None


@router.get("/topics", response_model=TopicList,
            summary="topics: producers, consumers, declared and assigned formats, bytes/s, conversions")
async def list_topics(core: Orchestrator = Depends(get_core)) -> TopicList:
    registry = core.registry
    items = []
    for topic, fmt in sorted(registry.formats().items()):
        items.append(TopicInfo(
            topic=topic, format=fmt, strategy=registry.strategy, bytes_per_second=bytes_per_second(fmt),
            conversions=conversions(registry.declarations(topic), fmt),
            producers=[TopicProducer(component_id=p.component_id, name=p.name, format=p.outputs[topic],
                                     converts=key(p.outputs[topic]) != key(fmt),
                                     audio_endpoint=p.audio_endpoint, subscribers=_subscribers(p, topic))
                       for p in registry.producers(topic)],
            consumers=[TopicConsumer(component_id=c.component_id, name=c.name, format=c.inputs[topic],
                                     converts=key(c.inputs[topic]) != key(fmt))
                       for c in registry.consumers(topic)]))
    return TopicList(items=items)
