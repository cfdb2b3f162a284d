"""The latency histograms of GET /metrics (api/metrics.py renders them with the counters and gauges).

They are observed by the ingest once the results they time are committed: segment end → result
received per component, anchor received → fused result published per fusion, and fusion overhead
(completing result received → fused result handed to the websocket clients). Each orchestrator
has its own registry: nothing is global, nothing is built at import.
"""
from __future__ import annotations

from prometheus_client import CollectorRegistry, Histogram

LATENCY_BUCKETS_S = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
OVERHEAD_BUCKETS_S = (0.0001, 0.00025, 0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1)


class Metrics:
    """The histograms the ingest feeds, in their own registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.result_latency = Histogram(
            "esiaf_result_latency_seconds", "end of the audio a result covers -> the result received",
            ["component", "stream"], buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self.fused_latency = Histogram(
            "esiaf_fused_latency_seconds", "anchor result received -> its fused result published (revision 1)",
            ["fusion", "stream", "completion"], buckets=LATENCY_BUCKETS_S, registry=self.registry)
        self.fusion_overhead = Histogram(
            "esiaf_fusion_overhead_seconds", "completing result received -> fused result handed to the websocket "
            "clients (revision 1)", buckets=OVERHEAD_BUCKETS_S, registry=self.registry)
        self.timer_lateness = Histogram(
            "esiaf_fusion_timer_lateness_seconds", "a timed-out fusion's deadline -> its fused result handed to "
            "the websocket clients", buckets=OVERHEAD_BUCKETS_S, registry=self.registry)
