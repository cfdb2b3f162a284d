// The ESIAF dashboard: fused results live over /ws/fused, components, directions and a timeline
// polled from the REST API. Plain JavaScript, no build step, nothing loaded from elsewhere.
"use strict";

const TOKEN = new URLSearchParams(location.search).get("token") || "";
const COMPONENTS_EVERY_MS = 500;
const LATENCY_EVERY_MS = 2000;
const RESULTS_EVERY_MS = 500;
const STREAMS_EVERY_MS = 5000;
const RECONNECT_MAX_MS = 5000;
const MAX_FUSED = 500;  // fused results kept (the newest)
const SHOWN_FUSED = 100;
const TIMELINE_NS = 60e9;
const TRACK_RECENT_NS = 3e9;  // a track is drawn while it has directions this recent

const state = {
  fused: new Map(),  // fused id -> its newest revision
  partials: new Map(),  // stream id -> what its recogniser has heard of the utterance going on
  lastSeq: 0,  // the newest publication received: a reconnection resumes after it
  streams: new Set(),
  streamEnd: new Map(),  // stream id -> latest capture time seen (ns)
  components: [],
  latency: new Map(),  // component name -> {p50_ms, p95_ms}
  ssl: [],  // {stream, start_ns, end_ns, directions}
  vad: [],  // {stream, start_ns, end_ns}
  cursors: {ssl: null, vad: null},  // the last result id read of each type
  sinceNs: (Date.now() - TIMELINE_NS / 1e6) * 1e6,
};

const $ = (id) => document.getElementById(id);
const el = (tag, attrs = {}, text = "") => {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) node.setAttribute(key, value);
  if (text) node.textContent = text;
  return node;
};
const svg = (tag, attrs = {}) => {
  const node = document.createElementNS("http://www.w3.org/2000/svg", tag);
  for (const [key, value] of Object.entries(attrs)) node.setAttribute(key, value);
  return node;
};

function withToken(path) {
  return TOKEN ? path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(TOKEN) : path;
}

function showProblem(text) {
  $("problem").hidden = !text;
  $("problem").textContent = text || "";
}

async function api(path) {
  const response = await fetch(path, {headers: TOKEN ? {Authorization: "Bearer " + TOKEN} : {}});
  if (response.status === 401) {
    unauthorised = true;  // no reconnecting and no polling: a reload with the right token starts again
    if (socket) socket.close();
    $("connection").dataset.state = "closed";
    $("connection").textContent = "no token";
    showProblem("This orchestrator needs its token: open this page as /?token=TOKEN (esiaf run prints that URL).");
    throw new Error("401");
  }
  if (!response.ok) throw new Error(path + ": HTTP " + response.status);
  if (socket === null) connect();  // the token is good: open the websocket (not before, or it is refused)
  return response.json();
}

function selectedStream() { return $("stream-filter").value; }
function shown(stream) { return !selectedStream() || selectedStream() === stream; }

function noteStream(stream, endNs) {
  if (!state.streams.has(stream)) {
    state.streams.add(stream);
    $("stream-filter").append(el("option", {value: stream}, stream));
  }
  if (endNs && endNs > (state.streamEnd.get(stream) || 0)) state.streamEnd.set(stream, endNs);
}

// --- fused results over the websocket ------------------------------------------------------
let socket = null;
let reconnectMs = 250;
let unauthorised = false;  // the API said 401: the page's token is missing or wrong

function connect() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  socket = new WebSocket(scheme + "//" + location.host + withToken("/ws/fused?partials=1&after_seq=" + state.lastSeq));
  socket.onopen = () => {
    reconnectMs = 250;
    $("connection").dataset.state = "live";
    $("connection").textContent = "live";
  };
  socket.onmessage = (event) => onMessage(JSON.parse(event.data));
  socket.onclose = () => {
    if (unauthorised) return;  // api() said why
    $("connection").dataset.state = "reconnecting";
    $("connection").textContent = "reconnecting…";
    setTimeout(connect, reconnectMs);
    reconnectMs = Math.min(reconnectMs * 2, RECONNECT_MAX_MS);
  };
}

function onMessage(message) {
  if (message.type === "partial") {  // the line grows while the person speaks; closed: the fused result follows
    if (message.closed) state.partials.delete(message.stream_id);
    else state.partials.set(message.stream_id, message);
    schedule();
    return;
  }
  if (message.type === "stream_end") {
    state.partials.delete(message.stream_id);
    return;
  }
  if (message.type !== "fused_result") return;
  if (message.seq > state.lastSeq) state.lastSeq = message.seq;
  const known = state.fused.get(message.id);
  if (known && known.revision >= message.revision) return;
  state.fused.set(message.id, message);
  noteStream(message.stream_id, message.anchor.span.end_ns);
  if (state.fused.size > MAX_FUSED) state.fused.delete(Math.min(...state.fused.keys()));
  schedule();
}

// --- polled state ------------------------------------------------------------------------------
async function pollComponents() {
  state.components = (await api("/components?include_dead=true")).items;
}

async function pollLatency() {
  state.latency = new Map((await api("/latency")).items.map((item) => [item.component, item]));
}

async function pollStreams() {
  for (const stream of (await api("/streams")).items) noteStream(stream.stream_id, 0);
}

async function pollResults(type) {
  for (;;) {
    const cursor = state.cursors[type];
    const query = "start_ns=" + Math.round(state.sinceNs) + (cursor === null ? "" : "&after_id=" + cursor);
    const page = await api("/results?type=" + type + "&limit=1000&" + query);
    for (const result of page.items) {
      noteStream(result.stream_id, result.span.end_ns);
      if (!result[type]) continue;  // covered, nothing found ("nothing": its reason)
      state[type].push({stream: result.stream_id, start_ns: result.span.start_ns, end_ns: result.span.end_ns,
                        directions: type === "ssl" ? result.ssl.directions : []});
    }
    if (page.next_after_id !== null) state.cursors[type] = page.next_after_id;
    if (page.items.length < 1000) break;
  }
  for (const type_ of ["ssl", "vad"]) {  // keep the last minute of each stream
    state[type_] = state[type_].filter((r) => r.end_ns > (state.streamEnd.get(r.stream) || 0) - TIMELINE_NS);
  }
}

function every(ms, task) {
  const run = async () => {
    try {
      await task();
      schedule();
    } catch (error) {
      if (error.message === "401") return;  // stopped: see api()
      console.warn(error);
    }
    setTimeout(run, ms);
  };
  run();
}

// --- drawing -----------------------------------------------------------------------------------
let pending = false;
function schedule() {
  if (!pending) {
    pending = true;
    requestAnimationFrame(() => { pending = false; draw(); });
  }
}

function draw() {
  drawFused();
  drawPolar();
  drawComponents();
  drawTimeline();
}

const degrees = (value) => (value === undefined || value === null ? "–" : Math.round(value) + "°");
const clock = (ns) => new Date(ns / 1e6).toLocaleTimeString();

function bestText(fused) {
  const speech = fused.anchor.speech;
  return speech && speech.hypotheses.length ? speech.hypotheses[0] : {text: "", probability: 0};
}

function visibleFused() {
  return [...state.fused.values()].filter((f) => shown(f.stream_id))
    .sort((a, b) => b.anchor.span.start_ns - a.anchor.span.start_ns).slice(0, SHOWN_FUSED);
}

function drawFused() {
  const list = $("fused");
  const growing = [...state.partials.values()].filter((p) => shown(p.stream_id)).map((partial) => {
    const item = el("li", {"class": "partial", "data-stream": partial.stream_id});
    item.append(el("div", {"class": "text"}, partial.text + " …"),
                el("div", {"class": "meta"}, "hearing · " + partial.stream_id));
    return item;
  });
  list.replaceChildren(...growing, ...visibleFused().map((fused) => {
    const best = bestText(fused);
    const aggregates = fused.aggregates || {};
    const ssl = aggregates.ssl;
    const item = el("li", {"class": "fused", "data-id": fused.id, "data-revision": fused.revision,
                           "data-stream": fused.stream_id});
    if (ssl) item.dataset.azimuth = ssl.azimuth_deg;
    item.append(el("div", {"class": "text"}, best.text || best.raw_text || "(speech not understood)"));
    const meta = el("div", {"class": "meta"});
    meta.append(el("span", {"class": "when"}, clock(fused.anchor.span.start_ns)),
                el("span", {"class": "confidence"}, "confidence " + best.probability.toFixed(2)),
                el("span", {"class": "direction"}, "direction " + degrees(ssl && ssl.azimuth_deg)));
    for (const kind of ["emotion", "gender", "voice_id"]) {
      if (aggregates[kind]) meta.append(el("span", {"class": kind}, kind + " " + aggregates[kind].label));
    }
    meta.append(el("span", {"class": "completion", "data-completion": fused.completion}, fused.completion));
    if (fused.revision > 1) meta.append(el("span", {"class": "revision"}, "revision " + fused.revision));
    meta.append(el("span", {"class": "stream"}, fused.stream_id));
    item.append(meta);
    return item;
  }));
}

function polarPoint(azimuthDeg, radius) {
  const angle = azimuthDeg * Math.PI / 180;  // 0° to the right (the array's front), counter-clockwise
  return [radius * Math.cos(angle), -radius * Math.sin(angle)];
}

function drawPolar() {
  const utterances = visibleFused().filter((f) => f.aggregates && f.aggregates.ssl).slice(0, 20);
  $("utterance-markers").replaceChildren(...utterances.map((fused, index) => {
    const [x, y] = polarPoint(fused.aggregates.ssl.azimuth_deg, 100);
    const group = svg("g", {"class": "utterance", "data-id": fused.id,
                            "data-azimuth": fused.aggregates.ssl.azimuth_deg, "opacity": 1 - index / 25});
    group.append(svg("circle", {cx: x, cy: y, r: 8}));
    const label = svg("text", {x: x, y: y});
    label.textContent = String(fused.id);
    const title = svg("title");
    title.textContent = bestText(fused).text + " (" + degrees(fused.aggregates.ssl.azimuth_deg) + ")";
    group.append(label, title);
    return group;
  }));
  const tracks = new Map();  // source id -> its newest direction
  for (const result of state.ssl) {
    if (!shown(result.stream) || result.end_ns < (state.streamEnd.get(result.stream) || 0) - TRACK_RECENT_NS) continue;
    for (const direction of result.directions) tracks.set(direction.source_id, direction);
  }
  $("track-markers").replaceChildren(...[...tracks.entries()].map(([sourceId, direction]) => {
    const azimuth = direction.track_azimuth_deg || direction.azimuth_deg;
    const [x, y] = polarPoint(azimuth, 60);
    const group = svg("g", {"class": "track" + (direction.background ? " background" : ""),
                            "data-source": sourceId, "data-azimuth": azimuth});
    group.append(svg("circle", {cx: x, cy: y, r: 5}));
    const label = svg("text", {x: x + 7, y: y + 3});
    label.textContent = sourceId;
    group.append(label);
    return group;
  }));
}

function formatText(format) {
  return (format.sample_rate_hz / 1000) + " kHz " + format.sample_type + " ×" + format.channels;
}

function sum(values) { return values.reduce((total, value) => total + (Number(value) || 0), 0); }

// every live instance (replicas of a service each get a row), and for a service with none live
// its latest instance (dead or replaced)
function rowsPerInstance(components) {
  const live = components.filter((c) => c.status === "alive");
  const latest = new Map();
  for (const component of components) {
    if (live.some((c) => c.name === component.name)) continue;
    const known = latest.get(component.name);
    if (!known || component.registered_ns > known.registered_ns) latest.set(component.name, component);
  }
  return [...live, ...latest.values()].sort((a, b) => a.name.localeCompare(b.name) || a.registered_ns - b.registered_ns);
}

function drawComponents() {
  const nowNs = Date.now() * 1e6;
  const rows = rowsPerInstance(state.components);
  const replicated = new Set(rows.filter((c, i) => rows.findIndex((d) => d.name === c.name) !== i).map((c) => c.name));
  $("components").tBodies[0].replaceChildren(...rows.map((component) => {
    const stats = component.stats || {};
    const inputs = Object.values(stats.inputs || {});
    const outputs = Object.values(stats.outputs || {});
    const lost = sum(inputs.map((i) => i.lost)) + sum(outputs.map((o) => o.dropped)) + (stats.results_dropped || 0);
    // bad: audio it could not use, and results it made that the orchestrator would refuse (not sent)
    const bad = sum(inputs.map((i) => i.bad)) + (stats.results_invalid || 0);
    const queued = Math.max(0, ...inputs.map((i) => i.queued || 0));
    const refused = sum(Object.values(stats.refused || {}));
    const latency = state.latency.get(component.name);
    const row = el("tr", {"data-component": component.name, "data-component-id": component.component_id,
                          "data-status": component.status});
    const name = el("td", {}, component.name);
    if (replicated.has(component.name)) name.append(el("div", {"class": "instance"}, component.component_id));
    row.append(name,
               el("td", {"class": "status", "data-status": component.status}, component.status),
               el("td", {"class": "heartbeat"}, Math.max(0, (nowNs - component.last_seen_ns) / 1e9).toFixed(1) + " s"),
               el("td", {"class": "counters", "title": stats.results_invalid_reason
                 ? "last result not sent: " + stats.results_invalid_reason : ""}, lost + " / " + bad + " / " + refused),
               el("td", {"class": "queued", "title": "audio messages found waiting at once, last heartbeat"},
                  inputs.length ? String(queued) : "–"),
               el("td", {"class": "latency"}, latency && latency.p50_ms !== null
                 ? Math.round(latency.p50_ms) + " / " + Math.round(latency.p95_ms) + " ms" : "–"));
    const topics = el("td", {"class": "topics"});
    for (const input of component.inputs) topics.append(el("div", {}, "← " + input.topic + " " + formatText(input.format)));
    for (const output of component.outputs) topics.append(el("div", {}, "→ " + output.topic + " " + formatText(output.format)));
    row.append(topics);
    return row;
  }));
}

function bar(lane, startNs, endNs, fromNs, text) {
  const left = Math.max(0, (startNs - fromNs) / TIMELINE_NS * 100);
  const width = Math.max(0.3, (endNs - Math.max(startNs, fromNs)) / TIMELINE_NS * 100);
  const node = el("div", {"class": "bar", style: "left:" + left + "%;width:" + width + "%"}, text);
  if (text) node.title = text;
  lane.append(node);
}

function drawTimeline() {
  const streams = [...state.streamEnd.keys()].filter(shown).sort();
  $("timeline").replaceChildren(...streams.map((stream) => {
    const toNs = state.streamEnd.get(stream);
    const fromNs = toNs - TIMELINE_NS;
    const box = el("div", {"class": "stream", "data-stream": stream});
    box.append(el("div", {"class": "name"}, stream + " (until " + clock(toNs) + ")"));
    const vad = el("div", {"class": "lane vad", "data-lane": "VAD"});
    const utterances = el("div", {"class": "lane utterances", "data-lane": "utterances"});
    const directions = el("div", {"class": "lane directions", "data-lane": "directions"});
    for (const segment of state.vad) {
      if (segment.stream === stream && segment.end_ns > fromNs) bar(vad, segment.start_ns, segment.end_ns, fromNs, "");
    }
    for (const fused of state.fused.values()) {
      const span = fused.anchor.span;
      if (fused.stream_id === stream && span.end_ns > fromNs) bar(utterances, span.start_ns, span.end_ns, fromNs, bestText(fused).text);
    }
    for (const result of state.ssl) {
      if (result.stream !== stream || result.end_ns <= fromNs) continue;
      for (const direction of result.directions) {
        const top = (1 - ((direction.azimuth_deg % 360) + 360) % 360 / 360) * 100;
        directions.append(el("div", {"class": "dot" + (direction.background ? " background" : ""),
          style: "left:" + ((result.end_ns - fromNs) / TIMELINE_NS * 100) + "%;top:calc(" + top + "% - 1.5px)"}));
      }
    }
    box.append(vad, utterances, directions);
    return box;
  }));
}

$("stream-filter").addEventListener("change", schedule);
// the websocket opens once the first API call has shown the token good (api())
every(COMPONENTS_EVERY_MS, pollComponents);
every(LATENCY_EVERY_MS, pollLatency);
every(STREAMS_EVERY_MS, pollStreams);
every(RESULTS_EVERY_MS, () => pollResults("ssl"));
every(RESULTS_EVERY_MS, () => pollResults("vad"));
setInterval(drawComponents, 1000);  // heartbeat ages grow between polls
