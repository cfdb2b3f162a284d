"""GET /metrics: the orchestrator's and its components' counters in the Prometheus text format
(docs/dashboard.md has a scrape config).

Counters and gauges are read from the orchestrator's state at each scrape (the ingest's counters,
the registry, each component's last heartbeat stats: components need no port of their own); the
latency histograms are the ones the ingest observes (planes/metrics.py).
"""
from __future__ import annotations

import time
from collections.abc import Iterator

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from ..core import Orchestrator
from .deps import get_core

COMPONENT_LABELS = ["component", "component_id", "stream"]

router = APIRouter(tags=["metrics"])


@router.get("/metrics", response_class=Response,
            summary="counters, gauges and latency histograms in the Prometheus text format",
            description="Per component (from its heartbeats) and stream: results, fused results by "
                        "completion, lost, bad and refused messages, latency histograms, fusion overhead, "
                        "heartbeat age, queue depths.")
async def metrics(core: Orchestrator = Depends(get_core)) -> Response:
    return Response(generate_latest(StateCollector(core)), media_type=CONTENT_TYPE_LATEST)


def _count(value: object) -> float:
    """A counter from a peer's heartbeat: a non-negative number, else 0 (peers are untrusted)."""
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0 else 0.0


def _mapping(value: object) -> dict:
    return value if isinstance(value, dict) else {}


def _by_prefix(family: CounterMetricFamily, counters: dict[str, int], prefix: str) -> CounterMetricFamily:
    """The ingest counters named ``prefix<label>``, one sample per label."""
    for key in sorted(counters):
        if key.startswith(prefix):
            family.add_metric([key.removeprefix(prefix)], counters[key])
    return family


class StateCollector(Collector):
    """Counters and gauges read from the running orchestrator at each scrape, and its histograms."""

    def __init__(self, core: Orchestrator) -> None:
        self.core = core

    def collect(self) -> Iterator:
        yield from self.core.metrics.registry.collect()  # the latency histograms
        yield from self._orchestrator()
        yield from self._components()

    def _orchestrator(self) -> Iterator:
        core = self.core
        counters = core.ingest.counters
        results = CounterMetricFamily("esiaf_results", "results stored by the orchestrator")
        results.add_metric([], counters["results"])
        fused = _by_prefix(CounterMetricFamily("esiaf_fused_results", "fused results published (revision 1), by "
                                               "completion", labels=["completion"]), counters, "completion_")
        revisions = CounterMetricFamily("esiaf_fused_revisions", "revisions of fused results published")
        revisions.add_metric([], counters["revisions"])
        refused = _by_prefix(CounterMetricFamily("esiaf_refused_messages", "messages the orchestrator refused, by "
                                                 "reason", labels=["reason"]), counters, "refused_")
        bad = CounterMetricFamily("esiaf_bad_messages", "undecodable messages and results", labels=["kind"])
        bad.add_metric(["message"], counters["bad_messages"])
        bad.add_metric(["result"], counters["bad_results"])
        lost = CounterMetricFamily("esiaf_lost_messages", "messages lost in the orchestrator", labels=["where"])
        lost.add_metric(["db_error"], counters["lost_in_db_error"])
        peers = CounterMetricFamily("esiaf_refused_peers", "ZeroMQ handshakes refused (no or wrong key or "
                                    "token), by socket and reason", labels=["socket", "reason"])
        for (socket, reason), count in sorted(core.guard.refused.items()):
            peers.add_metric([socket, reason], count)
        http = CounterMetricFamily("esiaf_refused_http_connections", "HTTP connections closed below the app: "
                                   "peer_limit, total_limit (closed as accepted), request_timeout (a request not "
                                   "whole in time)", labels=["reason"])
        for reason, count in sorted(core.http_refused.items()):
            http.add_metric([reason], count)
        control = _by_prefix(CounterMetricFamily(
            "esiaf_refused_control_messages", "control messages refused: no_key, wrong_key (not the control_key "
            "of the named component's registration), wrong_peer_key (CURVE: another key than its registration's)",
            labels=["reason"]), core.control.counters, "refused_")
        open_fusions = GaugeMetricFamily("esiaf_open_fusions", "fusions waiting for results")
        open_fusions.add_metric([], len(core.ingest.engine.open))
        queued = GaugeMetricFamily("esiaf_store_queued_writes", "database writes not yet committed")
        queued.add_metric([], core.store.queued)
        clients = GaugeMetricFamily("esiaf_websocket_clients", "websocket clients of /ws/fused")
        clients.add_metric([], len(core.hub))
        depth = GaugeMetricFamily("esiaf_websocket_queue_depth", "messages queued for the slowest websocket "
                                  "client (it is closed at esiaf_websocket_queue_limit)")
        depth.add_metric([], max(core.hub.depths(), default=0))
        limit = GaugeMetricFamily("esiaf_websocket_queue_limit", "messages a websocket client may fall behind")
        limit.add_metric([], core.hub.max_queue)
        dropped = CounterMetricFamily("esiaf_websocket_dropped_clients", "websocket clients closed as too slow")
        dropped.add_metric([], core.hub.dropped_clients)
        yield from (results, fused, revisions, refused, peers, http, control, bad, lost, open_fusions, queued, clients,
                    depth, limit, dropped)

    def _components(self) -> Iterator:
        now_ns = time.time_ns()
        up = GaugeMetricFamily("esiaf_component_up", "1 alive, 0 dead or replaced", labels=COMPONENT_LABELS)
        age = GaugeMetricFamily("esiaf_component_heartbeat_age_seconds", "since the component's last message",
                                labels=COMPONENT_LABELS)
        heartbeats = CounterMetricFamily("esiaf_component_heartbeats", "heartbeats received", labels=COMPONENT_LABELS)
        received = CounterMetricFamily("esiaf_component_results_received", "results the orchestrator received from "
                                       "the component", labels=COMPONENT_LABELS)
        sent = CounterMetricFamily("esiaf_component_results_sent", "results the component sent (its heartbeat)",
                                   labels=COMPONENT_LABELS)
        not_sent = CounterMetricFamily("esiaf_component_results_dropped", "results the component could not send "
                                       "(its heartbeat)", labels=COMPONENT_LABELS)
        invalid = CounterMetricFamily("esiaf_component_results_invalid", "results the component made that the "
                                      "orchestrator would refuse, not sent (its heartbeat)", labels=COMPONENT_LABELS)
        inputs = CounterMetricFamily("esiaf_component_input_messages", "audio messages on an input topic, by "
                                     "outcome: received, lost (never arrived), bad (unusable)",
                                     labels=[*COMPONENT_LABELS, "topic", "outcome"])
        queued = GaugeMetricFamily("esiaf_component_input_queue_depth", "the most audio messages on an input "
                                   "topic found waiting at once in the component's last heartbeat interval (0: it "
                                   "keeps up)", labels=[*COMPONENT_LABELS, "topic"])
        outputs = CounterMetricFamily("esiaf_component_output_messages", "audio messages on an output topic, by "
                                      "outcome: published, dropped (high-water mark)",
                                      labels=[*COMPONENT_LABELS, "topic", "outcome"])
        subscribers = GaugeMetricFamily("esiaf_component_output_subscribers", "subscribers of an output topic",
                                        labels=[*COMPONENT_LABELS, "topic"])
        refused = CounterMetricFamily("esiaf_component_refused_messages", "messages the component refused, by "
                                      "reason (its heartbeat)", labels=[*COMPONENT_LABELS, "reason"])
        refused_subscribers = CounterMetricFamily("esiaf_component_refused_subscribers", "handshakes its audio "
                                                  "output refused (CURVE keys), by reason (its heartbeat)",
                                                  labels=[*COMPONENT_LABELS, "reason"])
        for component in self.core.registry.all(include_departed=True):
            labels = [component.name, component.component_id, component.stream_id]
            up.add_metric(labels, 1 if component.status == "alive" else 0)
            age.add_metric(labels, max(0, now_ns - component.last_seen_ns) / 1e9)
            heartbeats.add_metric(labels, component.heartbeats)
            received.add_metric(labels, component.results_received)
            stats = _mapping(component.stats)
            sent.add_metric(labels, _count(stats.get("results_sent")))
            not_sent.add_metric(labels, _count(stats.get("results_dropped")))
            invalid.add_metric(labels, _count(stats.get("results_invalid")))
            for topic, counts in sorted(_mapping(stats.get("inputs")).items()):
                for outcome in ("received", "lost", "bad"):
                    inputs.add_metric([*labels, str(topic), outcome], _count(_mapping(counts).get(outcome)))
                queued.add_metric([*labels, str(topic)], _count(_mapping(counts).get("queued")))
            for topic, counts in sorted(_mapping(stats.get("outputs")).items()):
                for outcome in ("published", "dropped"):
                    outputs.add_metric([*labels, str(topic), outcome], _count(_mapping(counts).get(outcome)))
                subscribers.add_metric([*labels, str(topic)], _count(_mapping(counts).get("subscribers")))
            for reason, count in sorted(_mapping(stats.get("refused")).items()):
                refused.add_metric([*labels, str(reason)], _count(count))
            for reason, count in sorted(_mapping(stats.get("refused_subscribers")).items()):
                refused_subscribers.add_metric([*labels, str(reason)], _count(count))
        yield from (up, age, heartbeats, received, sent, not_sent, invalid, inputs, queued, outputs, subscribers,
                    refused, refused_subscribers)
