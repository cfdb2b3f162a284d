"""The dashboard in a real browser: Debian's headless chromium, driven by Selenium and
Debian's chromedriver, reads the page's DOM while the demo scene plays; /metrics agrees with the
JSON API. Skipped with the reason where chromium, chromedriver or selenium is absent."""
from __future__ import annotations

import base64
import itertools
import json
import math
import os
import shutil
import signal
import time
from pathlib import Path

import httpx
import pytest
from prometheus_client.parser import text_string_to_metric_families

from esiaf.tools.testing import REPO, normalise, poll
from esiaf_services.ssl.tracker import angle_difference_deg

SCENE = REPO / "examples" / "robocup_scene.flac"
ARTEFACTS = REPO / "tests" / "artefacts"  # gitignored: screenshots of the last run
# from its kill to "dead" on the page: the launcher reports the death (or the orchestrator sees its
# connection close), not its silence (dead_after_s, 8 s by default); the page polls every 0.5 s
DEAD_WITHIN_S = 3.0


@pytest.fixture
def browser():
    missing = [name for name in ("chromium", "chromedriver") if not shutil.which(name)]
    if missing:
        pytest.skip(f"Debian's {' and '.join(missing)} not installed (setup.sh installs chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     "--window-size=1280,900", "--no-first-run", "--disable-background-networking"):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(options=options, service=webdriver.ChromeService(shutil.which("chromedriver")))
    yield driver
    driver.quit()


def requested_urls(driver) -> list[str]:
    """Every URL the page asked for (HTTP and websocket), from the DevTools protocol's network events."""
    urls = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            urls.append(message["params"]["request"]["url"])
        elif message["method"] == "Network.webSocketCreated":
            urls.append(message["params"]["url"])
    return urls


def screenshot(driver, path: Path, scale: float = 0.625) -> None:
    """The page as the window shows it, scaled down (DevTools' Page.captureScreenshot): small enough for
    the docs (docs/dashboard.png is a copy of tests/artefacts/dashboard.png)."""
    size = driver.execute_script("return [window.innerWidth, window.innerHeight]")
    shot = driver.execute_cdp_cmd("Page.captureScreenshot", {"format": "png", "clip": {
        "x": 0, "y": 0, "width": size[0], "height": size[1], "scale": scale}})
    path.parent.mkdir(exist_ok=True)
    path.write_bytes(base64.b64decode(shot["data"]))


def page_state(driver) -> dict:
    return driver.execute_script("""
        const fused = [...document.querySelectorAll('#fused li.fused')].map(li => ({
            id: li.dataset.id, text: li.querySelector('.text').textContent, revision: +li.dataset.revision,
            azimuth: li.dataset.azimuth === undefined ? null : +li.dataset.azimuth}));
        const markers = [...document.querySelectorAll('#utterance-markers g.utterance')].map(g => {
            const c = g.querySelector('circle');
            return {id: g.dataset.id, cx: +c.getAttribute('cx'), cy: +c.getAttribute('cy')};
        });
        const components = Object.fromEntries([...document.querySelectorAll('#components tbody tr')].map(
            tr => [tr.dataset.component, {id: tr.dataset.componentId,
                                          status: tr.querySelector('.status').textContent,
                                          queued: tr.querySelector('.queued').textContent}]));
        return {fused, markers, components, connection: document.getElementById('connection').dataset.state,
                tracks: document.querySelectorAll('#track-markers g.track').length,
                directions: document.querySelectorAll('#timeline .directions .dot').length};
    """)


def metric_samples(text: str) -> dict[str, list]:
    samples: dict[str, list] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            samples.setdefault(sample.name, []).append(sample)
    return samples


@pytest.mark.e2e
def test_the_demo_scene_on_the_dashboard(launch, browser):
    truth = json.loads(SCENE.with_suffix(".json").read_text())["utterances"]
    run = launch("--input", str(SCENE), "--array", "respeaker4", "--grammar", "robocup", "--fast", "--json", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=120)
    printed = poll(lambda: next((line for line in run.stderr if "esiaf: dashboard at " in line), None), timeout_s=10)
    assert printed.split("dashboard at ")[1].strip() == f"{run.url}/?token={run.token}"
    browser.get(f"{run.url}/")  # without the token: the page loads and says what it needs
    problem = poll(lambda: browser.find_element("id", "problem").is_displayed()
                   and browser.find_element("id", "problem").text, timeout_s=10)
    assert "?token=" in problem
    assert browser.find_element("id", "connection").text == "no token"  # no websocket tried: it would be refused
    browser.get("about:blank")  # the tokenless page's requests end here
    refused = browser.get_log("browser")  # its refused requests, logged by the browser: not errors of the page
    assert all("401" in entry["message"] for entry in refused), refused
    browser.get(f"{run.url}/?token={run.token}")
    run.wait_for_line(lambda line: line.get("type") == "stream_end", timeout_s=180)

    state = poll(lambda: (s := page_state(browser)) and len(s["fused"]) >= len(truth) and s, timeout_s=15)
    assert state["connection"] == "live"
    assert sorted(normalise(f["text"]) for f in state["fused"]) == sorted(normalise(t["text"]) for t in truth)
    markers = {m["id"]: m for m in state["markers"]}
    for t in truth:
        shown = next(f for f in state["fused"] if normalise(f["text"]) == normalise(t["text"]))
        marker = markers[shown["id"]]  # drawn where the azimuth points: 0° right, counter-clockwise
        azimuth = math.degrees(math.atan2(-marker["cy"], marker["cx"]))
        assert angle_difference_deg(azimuth, t["azimuth_deg"]) <= 15, (t, marker)

    live = {c["name"]: c for c in httpx.get(f"{run.url}/components", headers=run.headers).json()["items"]}
    assert {"asr", "vad", "ssl", "emotion", "gender", "voiceid"} <= set(live)
    state = poll(lambda: (s := page_state(browser)) and set(live) <= set(s["components"]) and s, timeout_s=5)
    for name in live:
        assert state["components"][name]["status"] == "alive", (name, state["components"])
        # the queue depth of a component with inputs: a count (the --fast replay is over: 0 once caught up)
        assert state["components"][name]["queued"].isdigit() == bool(live[name]["inputs"]), state["components"][name]

    screenshot(browser, ARTEFACTS / "dashboard.png")

    state = page_state(browser)
    assert state["tracks"] or state["directions"], "no direction of the ssl service drawn"
    errors = [entry for entry in browser.get_log("browser") if entry["level"] == "SEVERE"]
    assert not errors, errors

    orchestrator = (run.url.replace("http", "ws", 1), run.url)
    outside = [url for url in requested_urls(browser)
               if not url.startswith(orchestrator) and not url.startswith("data:")]
    assert not outside, outside

    assert_metrics_agree(run)

    # the asr is killed: esiaf run sees its process die and reports it dead at once (not only after
    # dead_after_s of silence); the page shows it dead until the restarted instance registers
    asr = live["asr"]
    os.kill(asr["pid"], signal.SIGKILL)
    killed_at = time.monotonic()
    poll(lambda: (row := page_state(browser)["components"]["asr"])["id"] == asr["component_id"]
         and row["status"] == "dead", timeout_s=DEAD_WITHIN_S + 2)
    assert time.monotonic() - killed_at <= DEAD_WITHIN_S
    screenshot(browser, ARTEFACTS / "dashboard-asr-dead.png")
    # restarted: the page shows the new instance alive
    restarted = poll(lambda: (row := page_state(browser)["components"]["asr"])["id"] != asr["component_id"] and row,
                     timeout_s=60)
    assert restarted["status"] == "alive"


def assert_metrics_agree(run) -> None:
    """/metrics (parsed by prometheus_client) says what GET /components and GET /fusions/stats say."""
    stats = httpx.get(f"{run.url}/fusions/stats", headers=run.headers).json()
    components = httpx.get(f"{run.url}/components", params={"include_dead": True}, headers=run.headers).json()["items"]
    response = httpx.get(f"{run.url}/metrics", headers=run.headers)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    samples = metric_samples(response.text)

    counters = stats["counters"]
    assert samples["esiaf_results_total"][0].value == counters["results"]
    by_completion = {s.labels["completion"]: s.value for s in samples["esiaf_fused_results_total"]}
    assert by_completion == {key.removeprefix("completion_"): value for key, value in counters.items()
                             if key.startswith("completion_")}
    assert sum(by_completion.values()) >= 5
    received = {s.labels["component_id"]: s.value for s in samples["esiaf_component_results_received_total"]}
    assert received == {c["component_id"]: c["results_received"] for c in components}
    up = {s.labels["component_id"]: s.value for s in samples["esiaf_component_up"]}
    assert up == {c["component_id"]: float(c["status"] == "alive") for c in components}
    # every stored result was timed once, by the component that sent it
    latency_counts: dict[str, float] = {}
    for sample in samples["esiaf_result_latency_seconds_count"]:
        latency_counts[sample.labels["component"]] = latency_counts.get(sample.labels["component"], 0) + sample.value
    assert sum(latency_counts.values()) == counters["results"]
    for component in components:
        if component["results_received"]:
            assert latency_counts[component["name"]] >= component["results_received"]
    fused_count = sum(s.value for s in samples["esiaf_fused_latency_seconds_count"])
    assert fused_count == sum(by_completion.values())
    assert samples["esiaf_fusion_overhead_seconds_count"][0].value == stats["overhead_samples"]
    lost = {(s.labels["component_id"], s.labels["topic"]): s.value
            for s in samples["esiaf_component_input_messages_total"] if s.labels["outcome"] == "lost"}
    assert lost == {(c["component_id"], topic): float(counts["lost"]) for c in components
                    for topic, counts in ((c["stats"] or {}).get("inputs") or {}).items()}
    queued = {(s.labels["component_id"], s.labels["topic"]) for s in samples["esiaf_component_input_queue_depth"]}
    assert queued == set(lost)  # every input's queue depth


NETWORK = {"offline": False, "latency": 0, "downloadThroughput": -1, "uploadThroughput": -1}


def test_after_an_orchestrator_restart_the_page_reconnects_and_replays_what_it_missed(orchestrator, browser):
    import zmq

    from esiaf_services.orchestrator.tests.helpers import FakeComponent, component_body
    context = zmq.Context()
    try:
        asr = FakeComponent(context, orchestrator.http, component_body("asr", kind="speech"))
        browser.get(f"{orchestrator.url}/")
        poll(lambda: page_state(browser)["connection"] == "live", timeout_s=10)
        asr.send_result(stream_id="s1", text="go forward")
        poll(lambda: [f["text"] for f in page_state(browser)["fused"]] == ["go forward"], timeout_s=10)
        first_seq = orchestrator.http.get("/fused").json()["items"][0]["seq"]
        asr.close()

        orchestrator.kill()
        poll(lambda: page_state(browser)["connection"] == "reconnecting", timeout_s=5)
        browser.execute_cdp_cmd("Network.enable", {})
        # the page cannot come back yet (Network.setBlockedURLs let a websocket through now and then)
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", dict(NETWORK, offline=True))
        orchestrator.start()
        asr = FakeComponent(context, orchestrator.http, component_body("asr", kind="speech"))
        asr.send_result(stream_id="s1", start_ns=3_000_000_000, end_ns=4_000_000_000, text="turn left")
        poll(lambda: len(orchestrator.http.get("/fused").json()["items"]) == 2, timeout_s=10)
        assert page_state(browser)["connection"] == "reconnecting"  # published while the page was away
        browser.execute_cdp_cmd("Network.emulateNetworkConditions", NETWORK)
        poll(lambda: [f["text"] for f in page_state(browser)["fused"]] == ["turn left", "go forward"], timeout_s=15)
        assert page_state(browser)["connection"] == "live"
        sockets = [url for url in requested_urls(browser) if url.startswith("ws:")]
        assert "/ws/fused?" in sockets[0] and sockets[0].endswith("after_seq=0")  # with partials=1 before it
        assert "/ws/fused?" in sockets[-1] and sockets[-1].endswith(f"after_seq={first_seq}")
        asr.close()
    finally:
        context.destroy(linger=0)


def test_a_revision_replaces_its_older_version_and_the_stream_filter_filters(tmp_path, browser):
    import zmq
    from selenium.webdriver.support.ui import Select

    from esiaf.tools.testing import Orchestrator
    from esiaf_services.orchestrator.tests.helpers import FakeComponent, Heartbeater, component_body
    orchestrator = Orchestrator(tmp_path, config={"timeouts": {"initial_s": 0.3}})
    context = zmq.Context()
    try:
        asr, ssl = (FakeComponent(context, orchestrator.http, component_body(name, kind=kind))
                    for name, kind in (("asr", "speech"), ("ssl", "ssl")))
        beating = Heartbeater([asr, ssl])
        browser.get(f"{orchestrator.url}/")
        poll(lambda: page_state(browser)["connection"] == "live", timeout_s=10)
        end_ns = time.time_ns()
        span = (end_ns - 1_000_000_000, end_ns)
        said = {"hypotheses": [{"text": "go forward", "probability": 0.9, "words": []}]}
        asr.emit("speech", span, stream_id="s1", speech=said)
        first = poll(lambda: page_state(browser)["fused"], timeout_s=10)
        assert [(f["text"], f["revision"], f["azimuth"]) for f in first] == [("go forward", 1, None)]  # ssl timed out
        ssl.emit("ssl", span, stream_id="s1",
                 ssl={"directions": [{"source_id": "t1", "azimuth_deg": 270, "elevation_deg": 0, "probability": 0.9}]})
        second = poll(lambda: (f := page_state(browser)["fused"]) and f[0]["revision"] == 2 and f, timeout_s=10)
        assert [(f["id"], f["text"], f["azimuth"]) for f in second] == [(first[0]["id"], "go forward", 270)]

        asr.emit("speech", (span[0] + 2_000_000_000, span[1] + 2_000_000_000), stream_id="s2",
                 speech={"hypotheses": [{"text": "turn left", "probability": 0.8, "words": []}]})
        poll(lambda: [f["text"] for f in page_state(browser)["fused"]] == ["turn left", "go forward"], timeout_s=10)
        streams = Select(browser.find_element("id", "stream-filter"))
        for stream, texts in (("s2", ["turn left"]), ("s1", ["go forward"]), ("", ["turn left", "go forward"])):
            streams.select_by_value(stream)
            poll(lambda texts=texts: [f["text"] for f in page_state(browser)["fused"]] == texts, timeout_s=5)
        beating.stop()
        asr.close()
        ssl.close()
    finally:
        context.destroy(linger=0)
        orchestrator.close()


def test_the_line_grows_while_a_person_speaks_and_the_fused_result_replaces_it(launch, browser):
    """Partial results on the page: in real time, the recogniser's partials show as a growing line
    above the fused results, and each is gone once its utterance is fused."""
    run = launch("--input", str(REPO / "examples" / "robocup_questions.wav"), "--grammar", "robocup", "--json",
                 "--without", "emotion,gender,voiceid,ssl", "--serve")
    run.wait_for_line(lambda line: line.get("type") == "stream_start", timeout_s=120)
    browser.get(f"{run.url}/?token={run.token}")
    seen: list[str] = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not any(line.get("type") == "stream_end" for line in run.lines):
        texts = browser.execute_script(
            "return [...document.querySelectorAll('#fused li.partial .text')].map((e) => e.textContent);")
        seen.extend(text for text in texts if not seen or seen[-1] != text)
        time.sleep(0.05)
    assert len(seen) >= 3, seen  # several partials shown
    assert any(len(b.split()) > len(a.split()) for a, b in itertools.pairwise(seen)), seen  # a line that grew
    state = poll(lambda: (s := page_state(browser)) and len(s["fused"]) >= 5 and s, timeout_s=15)
    assert not browser.find_elements("css selector", "#fused li.partial")  # every one replaced
    assert len(state["fused"]) == 5
