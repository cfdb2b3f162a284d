from __future__ import annotations

from fastapi import APIRouter, Depends

from ..core import Orchestrator
from ..models import TopicConsumer, TopicInfo, TopicList, TopicProducer
from ..registry import Component
from .deps import get_core

router = APIRouter(tags=["topics"])


def _subscribers(producer: Component, topic: str) -> int | None:
    outputs = (producer.stats or {}).get("outputs")
    reported = outputs.get(topic) if isinstance(outputs, dict) else None
    count = reported.get("subscribers") if isinstance(reported, dict) else None
    return count if isinstance(count, int) else None


@router.get("/topics", response_model=TopicList,
            summary="topics: producers, consumers, assigned format, subscriber counts")
async def list_topics(core: Orchestrator = Depends(get_core)) -> TopicList:
    registry = core.registry
    formats = registry.formats()
    return TopicList(items=[
        TopicInfo(topic=topic, format=formats[topic],
                  producers=[TopicProducer(component_id=p.component_id, name=p.name,
                                           audio_endpoint=p.audio_endpoint,
                                           subscribers=_subscribers(p, topic))
                             for p in registry.producers(topic)],
                  consumers=[TopicConsumer(component_id=c.component_id, name=c.name)
                             for c in registry.consumers(topic)])
        for topic in registry.topic_names()])
