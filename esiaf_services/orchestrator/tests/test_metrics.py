"""GET /metrics: components' heartbeat counters, the ingest's counters and the latency histograms,
parsed with prometheus_client's own parser; and GET / serves the dashboard's files."""
from __future__ import annotations

import re

from prometheus_client.parser import text_string_to_metric_families

from esiaf_services.orchestrator.tests.helpers import wait_until

STATS = {"inputs": {"vad/speech": {"received": 40, "lost": 3, "bad": 2, "queued": 6}},
         "outputs": {"asr/echo": {"published": 7, "dropped": 1, "subscribers": 2}},
         "results_sent": 5, "results_dropped": 1, "refused": {"bad_format": 4}, "info": {}}


def samples(http) -> dict[tuple[str, frozenset], float]:
    response = http.get("/metrics")
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    return {(sample.name, frozenset(sample.labels.items())): sample.value
            for family in text_string_to_metric_families(response.text) for sample in family.samples}


def value(metrics: dict, name: str, **labels: str) -> float:
    return metrics[(name, frozenset(labels.items()))]


def test_heartbeat_counters_per_component_and_topic(component, http):
    asr = component("asr", kind="speech", inputs=["vad/speech"])
    asr.heartbeat(STATS)
    wait_until(lambda: http.get("/components").json()["items"][0]["stats"] == STATS, what="the heartbeat's stats")
    metrics = samples(http)
    ids = {"component": "asr", "component_id": asr.id, "stream": "default"}
    assert value(metrics, "esiaf_component_up", **ids) == 1
    assert 0 <= value(metrics, "esiaf_component_heartbeat_age_seconds", **ids) < 5
    for outcome, count in (("received", 40), ("lost", 3), ("bad", 2)):
        assert value(metrics, "esiaf_component_input_messages_total", **ids, topic="vad/speech",
                     outcome=outcome) == count
    assert value(metrics, "esiaf_component_input_queue_depth", **ids, topic="vad/speech") == 6
    for outcome, count in (("published", 7), ("dropped", 1)):
        assert value(metrics, "esiaf_component_output_messages_total", **ids, topic="asr/echo",
                     outcome=outcome) == count
    assert value(metrics, "esiaf_component_output_subscribers", **ids, topic="asr/echo") == 2
    assert value(metrics, "esiaf_component_refused_messages_total", **ids, reason="bad_format") == 4
    assert value(metrics, "esiaf_component_results_sent_total", **ids) == 5
    assert value(metrics, "esiaf_component_results_dropped_total", **ids) == 1


def test_a_peer_cannot_break_the_scrape_with_odd_stats(component, http):
    asr = component("asr", kind="speech")
    odd = {"inputs": {"t": "not a mapping"}, "outputs": [], "results_sent": -3, "refused": {"x": "many"}}
    asr.heartbeat(odd)
    wait_until(lambda: http.get("/components").json()["items"][0]["stats"] == odd, what="the odd stats")
    metrics = samples(http)
    ids = {"component": "asr", "component_id": asr.id, "stream": "default"}
    assert value(metrics, "esiaf_component_results_sent_total", **ids) == 0
    assert value(metrics, "esiaf_component_refused_messages_total", **ids, reason="x") == 0


def test_results_fused_results_latencies_and_refused_messages(component, http):
    asr = component("asr", kind="speech")
    for index in range(3):
        asr.send_result(stream_id="s1", start_ns=(index + 1) * 1_000_000_000, end_ns=(index + 2) * 1_000_000_000)
    asr.push.send_multipart([b"result", b"\xffnot a protobuf"])
    wait_until(lambda: http.get("/fusions/stats").json()["counters"].get("refused", 0) == 1, what="the bad message")
    counters = http.get("/fusions/stats").json()["counters"]
    metrics = samples(http)
    assert value(metrics, "esiaf_results_total") == counters["results"] == 3
    assert value(metrics, "esiaf_fused_results_total", completion="complete") == counters["completion_complete"] == 3
    refused = {labels: count for (name, labels), count in metrics.items() if name == "esiaf_refused_messages_total"}
    assert sum(refused.values()) == 1
    assert value(metrics, "esiaf_component_results_received_total", component="asr", component_id=asr.id,
                 stream="default") == 3
    assert value(metrics, "esiaf_result_latency_seconds_count", component="asr", stream="s1") == 3
    # spans of 1970: the results arrived decades after their audio ended
    assert value(metrics, "esiaf_result_latency_seconds_bucket", component="asr", stream="s1", le="30.0") == 0
    assert value(metrics, "esiaf_fused_latency_seconds_count", fusion="speech", stream="s1", completion="complete") == 3
    assert value(metrics, "esiaf_fusion_overhead_seconds_count") == \
        http.get("/fusions/stats").json()["overhead_samples"] == 3
    assert value(metrics, "esiaf_store_queued_writes") == 0
    assert value(metrics, "esiaf_websocket_clients") == 0


def test_the_dashboard_is_served_with_its_own_files_only(http):
    page = http.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    linked = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert sorted(linked) == ["dashboard/dashboard.css", "dashboard/dashboard.js", "data:,"]
    for path in ("/dashboard/dashboard.css", "/dashboard/dashboard.js"):
        assert http.get(path).status_code == 200, path
    script = http.get("/dashboard/dashboard.js").text
    assert not re.search(r"https?://(?!www\.w3\.org/2000/svg)", script)  # the SVG namespace is a name, not a fetch
