// The operator's console of `geocal serve`: plain JavaScript over the daemon's own /v1 API
// (same origin; the login cookie when the daemon has a token). No build step.
"use strict";

const SVG = "http://www.w3.org/2000/svg";

// ---- DOM helpers: text always goes in as text, never as HTML ----
function h(tag, attrs, ...children) {
  const el = document.createElement(tag);
  setAttrs(el, attrs);
  append(el, children);
  return el;
}
function s(tag, attrs, ...children) {
  const el = document.createElementNS(SVG, tag);
  setAttrs(el, attrs);
  append(el, children);
  return el;
}
function setAttrs(el, attrs) {
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else el.setAttribute(k, v === true ? "" : String(v));
  }
}
function append(el, children) {
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
}
const $ = (id) => document.getElementById(id);

// ---- API ----
class Unauthorized extends Error {}
async function api(path, options = {}) {
  const response = await fetch(path, { credentials: "same-origin", cache: "no-store", ...options });
  if (response.status === 401) {
    showLogin();
    throw new Unauthorized("log in first");
  }
  if (!response.ok) {
    let message = response.statusText;
    try { message = (await response.json()).error || message; } catch (_) { /* not JSON */ }
    throw new Error(`${response.status}: ${message}`);
  }
  if (response.status === 204) return null;
  const type = response.headers.get("content-type") || "";
  return type.startsWith("application/json") ? response.json() : response.text();
}
const post = (path, body, type) =>
  api(path, { method: "POST", body, headers: type ? { "Content-Type": type } : {} });

// ---- Formatting ----
const fmtTime = (t) => (t ? new Date(t).toLocaleString() : "—");
function fmtDuration(seconds) {
  if (seconds === null || seconds === undefined || !isFinite(seconds)) return "—";
  const m = Math.floor(seconds / 60), sec = Math.round(seconds - 60 * m);
  return m > 0 ? `${m} min ${sec} s` : `${sec} s`;
}
function fmtNumber(v, unit) {
  if (v === null || v === undefined) return "—";
  if (typeof v !== "number") return String(v);
  const a = Math.abs(v);
  let text;
  if (unit === "m" && a < 1e-2 && a > 0) text = `${(v * 1e6).toFixed(2)} µm`;
  else if (unit === "rad" && a < 1e-2 && a > 0) text = `${(v * 1e6).toFixed(2)} µrad`;
  else text = (a !== 0 && (a < 1e-3 || a >= 1e6) ? v.toExponential(3) : +v.toPrecision(6)) + (unit ? ` ${unit}` : "");
  return text;
}
const stateBadge = (state) => h("span", { class: `state state-${state}` }, state);

// ---- Small SVG plots ----
// A live series: every sample of its window as a line; where there are more samples than
// pixels, each pixel column spans its samples' minimum to maximum, so none is left out.
function linePlot(title, unit, series) {
  const W = 320, H = 134, L = 8, R = 8, T = 22, B = 32;
  const n = series ? series.t.length : 0;
  const svg = s("svg", { class: "plot", viewBox: `0 0 ${W} ${H}`, role: "img", "aria-label": title,
    "data-samples": n, "data-received": series ? series.received : 0,
    "data-span-s": n > 1 ? series.t[n - 1] - series.t[0] : 0 });
  svg.append(s("text", { x: L, y: 14 }, title));
  if (n === 0) {
    svg.append(s("text", { x: W / 2, y: H / 2, "text-anchor": "middle" }, "no reading yet"));
    return svg;
  }
  const ts = series.t, vs = series.v;
  const t1 = ts[n - 1], t0 = Math.min(ts[0], t1 - 1);
  let v0 = Infinity, v1 = -Infinity;
  for (const v of vs) { if (v < v0) v0 = v; if (v > v1) v1 = v; }
  if (v1 - v0 < 1e-12 * Math.max(1, Math.abs(v1))) { v0 -= 0.5 * Math.abs(v0 || 1) * 1e-6 + 1e-12; v1 = 2 * vs[0] - v0; }
  const x = (t) => L + ((t - t0) / (t1 - t0)) * (W - L - R);
  const y = (v) => T + (1 - (v - v0) / (v1 - v0)) * (H - T - B);
  const columns = W - L - R;
  const points = [];
  if (n <= 2 * columns) {
    for (let i = 0; i < n; i++) points.push(`${x(ts[i]).toFixed(1)},${y(vs[i]).toFixed(1)}`);
  } else {
    let column = -1, lo = 0, hi = 0;
    const flush = () => { if (column >= 0) points.push(`${L + column},${y(lo).toFixed(1)}`, `${L + column},${y(hi).toFixed(1)}`); };
    for (let i = 0; i < n; i++) {
      const c = Math.min(columns, Math.floor(x(ts[i]) - L));
      if (c !== column) { flush(); column = c; lo = hi = vs[i]; } else { lo = Math.min(lo, vs[i]); hi = Math.max(hi, vs[i]); }
    }
    flush();
  }
  svg.append(s("line", { class: "axis", x1: L, x2: W - R, y1: H - B, y2: H - B }));
  svg.append(s("polyline", { class: "line", points: points.join(" ") }));
  svg.append(s("text", { x: W - R, y: 14, "text-anchor": "end", class: "label" }, fmtNumber(vs[n - 1], unit)));
  svg.append(s("text", { x: L, y: H - 18 }, `${fmtNumber(v0, unit)} … ${fmtNumber(v1, unit)}`));
  svg.append(s("text", { x: L, y: H - 4 }, `${n} samples in ${(t1 - t0).toFixed(1)} s`));
  return svg;
}

// A parameter over runs: values with ±2σ, the tolerance band, the trend's events.
function trendPlot(parameter, runs, events) {
  const W = 300, H = 170, L = 10, R = 10, T = 24, B = 22;
  const svg = s("svg", { class: "plot", viewBox: `0 0 ${W} ${H}`, role: "img",
    "aria-label": `${parameter.id} over ${runs.length} runs`, "data-parameter": parameter.id });
  svg.append(s("text", { x: L, y: 15, class: "label" }, `${parameter.id} (${parameter.unit || ""})`));
  const n = runs.length;
  const ys = [];
  parameter.values.forEach((v, i) => {
    if (v === null) return;
    const sg = parameter.sigmas[i] || 0;
    ys.push(v - 2 * sg, v + 2 * sg);
  });
  const band = parameter.band;
  if (band && isFinite(band.half_width)) ys.push(band.centre - band.half_width, band.centre + band.half_width);
  if (ys.length === 0) return svg;
  let v0 = Math.min(...ys), v1 = Math.max(...ys);
  if (v1 - v0 <= 0) { v0 -= 1e-9; v1 += 1e-9; }
  const x = (i) => L + (n === 1 ? 0.5 : i / (n - 1)) * (W - L - R - 10) + 5;
  const y = (v) => T + (1 - (v - v0) / (v1 - v0)) * (H - T - B);
  if (band && isFinite(band.half_width)) {
    svg.append(s("rect", { class: "band", "data-band-source": band.source, x: L, width: W - L - R, y: y(band.centre + band.half_width),
      height: Math.max(1, y(band.centre - band.half_width) - y(band.centre + band.half_width)) },
      s("title", {}, `tolerance band (${band.source}): ${fmtNumber(band.centre, parameter.unit)} ± ${fmtNumber(band.half_width, parameter.unit)}`)));
  }
  const line = [];
  parameter.values.forEach((v, i) => {
    if (v === null) return;
    const sg = parameter.sigmas[i];
    if (sg) svg.append(s("line", { class: "sigma", x1: x(i), x2: x(i), y1: y(v - 2 * sg), y2: y(v + 2 * sg) }));
    line.push(`${x(i).toFixed(1)},${y(v).toFixed(1)}`);
    svg.append(s("circle", { class: "dot", cx: x(i), cy: y(v), r: 4 },
      s("title", {}, `${runs[i].label}: ${fmtNumber(v, parameter.unit)}${sg ? ` ± ${fmtNumber(2 * sg, parameter.unit)} (2σ)` : ""}`)));
  });
  svg.prepend(s("polyline", { class: "line", points: line.join(" ") }));
  for (const e of events.filter((e) => e.parameter === parameter.id)) {
    const at = e.run ?? 0;
    svg.append(s("line", { class: "event", x1: x(at), x2: x(at), y1: T - 4, y2: H - B, "data-event": e.kind },
      s("title", {}, e.message || e.kind)));
    svg.append(s("text", { x: Math.min(x(at) + 3, W - 40), y: T + 8, class: "label" }, e.kind));
  }
  svg.append(s("text", { x: L, y: H - 5 }, `${fmtNumber(v0, parameter.unit)} … ${fmtNumber(v1, parameter.unit)}; bars ±2σ`));
  return svg;
}

// The station layout seen from above: the machine's travel (x, y) and the stations' hints.
function layoutPlot(layout, nextStation) {
  // Room beside the drawing for the stations' labels.
  const W = 460, H = 320, PX = 90, PY = 30;
  const svg = s("svg", { class: "plot", viewBox: `0 0 ${W} ${H}`, role: "img",
    "aria-label": "station layout, seen from above" });
  const axis = (name) => layout.travel.find((a) => a.axis === name);
  const ax = axis("x"), ay = axis("y");
  const xs = [], ys = [];
  if (ax && ay) { xs.push(ax.from_m, ax.to_m); ys.push(ay.from_m, ay.to_m); }
  for (const st of layout.stations) if (st.hint_m) { xs.push(st.hint_m[0]); ys.push(st.hint_m[1]); }
  if (xs.length === 0) {
    svg.append(s("text", { x: W / 2, y: H / 2, "text-anchor": "middle" }, "the plan gives no station positions"));
    return svg;
  }
  const x0 = Math.min(...xs), x1 = Math.max(...xs), y0 = Math.min(...ys), y1 = Math.max(...ys);
  const scale = Math.min((W - 2 * PX) / Math.max(x1 - x0, 1e-3), (H - 2 * PY) / Math.max(y1 - y0, 1e-3));
  const left = (W - (x1 - x0) * scale) / 2;
  const px = (v) => left + (v - x0) * scale, py = (v) => H - PY - (v - y0) * scale;
  if (ax && ay) {
    svg.append(s("rect", { class: "travel", x: px(ax.from_m), y: py(ay.to_m),
      width: (ax.to_m - ax.from_m) * scale, height: (ay.to_m - ay.from_m) * scale },
      s("title", {}, "the machine's travel in x and y")));
    // Inside the travel, clear of the stations around it.
    const cx = px((ax.from_m + ax.to_m) / 2), cy = py((ay.from_m + ay.to_m) / 2);
    svg.append(s("text", { x: cx, y: cy - 4, "text-anchor": "middle" }, `x ${ax.from_m}…${ax.to_m} m`));
    svg.append(s("text", { x: cx, y: cy + 14, "text-anchor": "middle" }, `y ${ay.from_m}…${ay.to_m} m`));
  }
  for (const st of layout.stations) {
    if (!st.hint_m) continue;
    const next = st.id === nextStation;
    svg.append(s("circle", { class: next ? "station next" : "station", cx: px(st.hint_m[0]), cy: py(st.hint_m[1]),
      r: next ? 11 : 8, "data-station": st.id },
      s("title", {}, `${st.id}: x ${st.hint_m[0]} m, y ${st.hint_m[1]} m, z ${st.hint_m[2]} m`)));
    // Labels point away from the travel's centre, so they do not cross it.
    const right = ax ? st.hint_m[0] >= (ax.from_m + ax.to_m) / 2 : true;
    svg.append(s("text", { class: "label", x: px(st.hint_m[0]) + (right ? 14 : -14), y: py(st.hint_m[1]) + 5,
      "text-anchor": right ? "start" : "end" }, `${st.id}`));
    svg.append(s("text", { x: px(st.hint_m[0]) + (right ? 14 : -14), y: py(st.hint_m[1]) + 20,
      "text-anchor": right ? "start" : "end" }, `z ${st.hint_m[2]} m`));
  }
  return svg;
}

// ---- Shared state: prompts (the banner on every page), live samples ----
const state = { prompts: [], announced: new Set(), series: new Map(), lost: 0, route: "", refreshers: [] };

// ---- Live samples: every reading of the running job's devices (/v1/devices/samples) ----
const LIVE_WINDOW_S = 30;
const LIVE_FIELDS = {
  tracer: [["length_m", "length", "m"], ["signal", "signal", ""]],
  environment: [["air_temp_k", "air temperature", "K"], ["pressure_pa", "pressure", "Pa"], ["humidity_pct", "humidity", "%"]],
};

function takeSamples(batch) {
  for (const [field, label, unit] of LIVE_FIELDS[batch.kind] || []) {
    const column = batch.fields[field];
    if (!column) continue;
    const key = `${batch.device} ${label}`;
    let series = state.series.get(key);
    // A new run's clock may start earlier than the last one's end: start the plot afresh.
    if (!series || (series.t.length && batch.t_s[0] < series.t[series.t.length - 1] - LIVE_WINDOW_S)) {
      series = { unit, t: [], v: [], received: series ? series.received : 0 };
      state.series.set(key, series);
    }
    column.forEach((v, i) => {
      if (v === null || !isFinite(v)) return;
      series.t.push(batch.t_s[i]); series.v.push(v); series.received++;
    });
    const newest = series.t[series.t.length - 1];
    let old = 0;
    while (old < series.t.length && series.t[old] < newest - LIVE_WINDOW_S) old++;
    if (old) { series.t.splice(0, old); series.v.splice(0, old); }
  }
  drawLiveSoon();
}

// The live plots are redrawn in place, at most 4 times a second, without redrawing the page.
let liveDraw = null;
function drawLiveSoon() {
  if (!liveDraw) liveDraw = setTimeout(() => { liveDraw = null; drawLive(); }, 250);
}
function drawLive(box = $("live-plots")) {
  if (!box) return;
  for (const [key, series] of state.series) {
    let card = [...box.children].find((c) => c.dataset.series === key);
    if (!card) { card = h("div", { class: "card", "data-series": key }); box.append(card); }
    card.replaceChildren(linePlot(key, series.unit, series));
  }
  const note = box.previousElementSibling;
  if (note && note.id === "live-note") note.textContent = state.series.size === 0 ? "No tracer or environment reading yet (they appear while a run records)."
    : `Every sample of the last ${LIVE_WINDOW_S} s.` + (state.lost ? ` ${state.lost} messages lost (the link was too slow).` : "");
}

let samples = null;
function followSamples(on) {
  if (on && !samples) {
    samples = new EventSource("/v1/devices/samples", { withCredentials: true });
    samples.addEventListener("samples", (e) => takeSamples(JSON.parse(e.data)));
    samples.addEventListener("lagged", (e) => { state.lost += JSON.parse(e.data).messages; drawLiveSoon(); });
    // Refused (e.g. before the login): the browser gives up; the next redraw asks again.
    samples.onerror = () => { if (samples && samples.readyState === EventSource.CLOSED) samples = null; };
  } else if (!on && samples) {
    samples.close();
    samples = null;
  }
}

async function refreshPrompts() {
  const prompts = await api("/v1/prompts");
  state.prompts = prompts;
  const count = $("prompt-count");
  count.hidden = prompts.length === 0;
  count.textContent = prompts.length;
  const banner = $("prompt-banner");
  banner.hidden = prompts.length === 0;
  if (prompts.length > 0) {
    $("banner-instruction").textContent = `job ${prompts[0].job}: ${prompts[0].instruction}`;
    const button = $("banner-continue");
    if (button.dataset.prompt !== String(prompts[0].id)) {
      button.dataset.prompt = prompts[0].id;
      button.disabled = false;
    }
  }
  for (const p of prompts) {
    if (state.announced.has(p.id)) continue;
    state.announced.add(p.id);
    announce(p);
  }
}

// A new prompt: a tone, and a notification when the operator allowed them.
function announce(prompt) {
  try {
    const audio = new (window.AudioContext || window.webkitAudioContext)();
    const tone = audio.createOscillator(), gain = audio.createGain();
    tone.frequency.value = 880; gain.gain.value = 0.2;
    tone.connect(gain).connect(audio.destination);
    tone.start(); tone.stop(audio.currentTime + 0.4);
  } catch (_) { /* no sound before the first interaction: the banner still shows */ }
  if ("Notification" in window && Notification.permission === "granted") {
    new Notification("geocal: the run waits for you", { body: prompt.instruction, tag: `prompt-${prompt.id}` });
  }
}

async function acknowledge(id, button) {
  if (button) button.disabled = true;
  try {
    await post(`/v1/prompts/${id}/ack`);
  } catch (e) {
    if (!(e instanceof Unauthorized)) alert(`Could not continue: ${e.message}`);
  }
  await refreshPrompts().catch(() => {});
  rerender();
}

// ---- Login ----
function showLogin() {
  const dialog = $("login");
  if (!dialog.open) dialog.showModal();
  $("login-token").focus();
}
async function login(event) {
  event.preventDefault();
  const body = new URLSearchParams({ token: $("login-token").value });
  const response = await fetch("/console/login", { method: "POST", body, credentials: "same-origin" });
  if (response.ok) {
    $("login-token").value = "";
    $("login-error").textContent = "";
    $("login").close();
    startEvents();
    rerender();
  } else {
    let message = response.statusText;
    try { message = (await response.json()).error; } catch (_) { /* keep the status */ }
    $("login-error").textContent = message;
  }
}

// ---- Pages ----
const pages = {
  now: renderNow, prompts: renderPrompts, jobs: renderJobs, job: renderJob,
  machines: renderMachines, machine: renderMachine, schedules: renderSchedules,
};

function route() {
  const parts = (location.hash.replace(/^#\/?/, "") || "now").split("/").map(decodeURIComponent);
  if (parts[0] === "jobs" && parts[1]) return ["job", parts[1]];
  if (parts[0] === "machines" && parts[1]) return ["machine", parts[1]];
  return [pages[parts[0]] ? parts[0] : "now"];
}

let rendering = 0;
async function rerender() {
  const [page, arg] = route();
  followSamples(page === "now");
  for (const a of document.querySelectorAll("nav a")) {
    const here = a.dataset.page === page || a.dataset.page + "s" === page || (page === "job" && a.dataset.page === "jobs")
      || (page === "machine" && a.dataset.page === "machines");
    if (here) a.setAttribute("aria-current", "page"); else a.removeAttribute("aria-current");
  }
  const ticket = ++rendering;
  const main = $("main");
  try {
    const content = await pages[page](arg);
    if (ticket !== rendering) return;
    // Updates must not take the keyboard focus away: find the focused control again.
    const focused = main.contains(document.activeElement) ? focusKey(document.activeElement) : null;
    main.replaceChildren(content);
    main.dataset.page = page;
    if (focused) { const again = main.querySelector(focused); if (again) again.focus(); }
  } catch (e) {
    if (ticket !== rendering) return;
    if (e instanceof Unauthorized) main.replaceChildren(h("p", { class: "muted" }, "Log in to see this daemon."));
    else main.replaceChildren(h("p", { class: "error", role: "alert" }, `Could not load the page: ${e.message}`));
  }
}

function focusKey(el) {
  if (el.id) return `#${CSS.escape(el.id)}`;
  for (const name of ["href", "data-ack", "data-job"]) {
    const v = el.getAttribute(name);
    if (v !== null) return `${el.tagName.toLowerCase()}[${name}="${CSS.escape(v)}"]`;
  }
  return null;
}

function table(headers, rows, attrs) {
  return h("div", { class: "table" }, h("table", attrs || {},
    h("thead", {}, h("tr", {}, headers.map((t) => h("th", { scope: "col" }, t)))),
    h("tbody", {}, rows)));
}

function progressOf(job) {
  const p = job.progress || {};
  return h("div", {},
    h("progress", { max: Math.max(p.total || 0, 1), value: p.done || 0, "aria-label": `job ${job.id} progress` }),
    h("div", { class: "actions" },
      h("span", { class: "big-number", "data-progress": `${p.done || 0}/${p.total || 0}` }, `${p.done || 0} / ${p.total || 0}`),
      h("span", {}, "points"),
      p.station ? h("span", {}, `· station ${p.station}`) : null,
      p.eta_s !== null && p.eta_s !== undefined ? h("span", {}, `· about ${fmtDuration(p.eta_s)} left`) : null));
}

async function renderNow() {
  const [jobs, devices, health] = await Promise.all([api("/v1/jobs"), api("/v1/devices"), api("/v1/health")]);
  const running = jobs.find((j) => j.state === "running");
  const queued = jobs.filter((j) => j.state === "queued");
  const last = jobs.find((j) => !["running", "queued"].includes(j.state));
  const machine = await currentMachine(running || last);
  const out = h("div", {}, h("h1", {}, machine ? `Now: ${machine}` : "Now"));
  const jobCard = h("section", { class: "card", "aria-labelledby": "now-job" });
  if (running) {
    jobCard.append(h("h2", { id: "now-job" }, "Running: ", h("a", { href: `#/jobs/${running.id}` }, `job ${running.id}`),
      ` (${running.kind} ${running.type})`), progressOf(running));
    if (running.progress.last_faults.length) {
      jobCard.append(h("h2", {}, "Last faults"), h("ul", {}, running.progress.last_faults.map((f) => h("li", { class: "error" }, f))));
    }
  } else {
    jobCard.append(h("h2", { id: "now-job" }, health.busy ? "Busy" : "No job runs"),
      last ? h("p", {}, "Last: ", h("a", { href: `#/jobs/${last.id}` }, `job ${last.id}`), ` ${last.kind} `, stateBadge(last.state),
        `, ended ${fmtTime(last.finished_at)}`) : h("p", { class: "muted" }, "No job yet: submit one on the Jobs page."));
  }
  if (queued.length) jobCard.append(h("p", {}, `${queued.length} queued: `, queued.map((j) => `job ${j.id}`).join(", ")));
  out.append(jobCard);

  const plots = h("div", { class: "plots", id: "live-plots" });
  out.append(h("h2", {}, "Live readings"), h("p", { class: "muted", id: "live-note" }), plots);
  drawLive(plots);

  out.append(h("h2", {}, "Devices"), devices.length === 0 ? h("p", { class: "muted" }, "No device seen yet.") :
    table(["device", "kind", "connected", "last reading", "age", "signal", "last fault"], devices.map((d) =>
      h("tr", {}, h("td", {}, d.id), h("td", {}, d.kind), h("td", {}, d.connected ? "yes" : "no"),
        h("td", {}, summarizeReading(d.last_reading)), h("td", { class: "num" }, d.last_reading_age_s === null ? "—" : `${d.last_reading_age_s.toFixed(1)} s`),
        h("td", { class: "num" }, d.signal_level === null ? "—" : d.signal_level.toFixed(2)),
        h("td", { class: d.last_error ? "error wrap" : "muted" }, d.last_error || "none")))));
  return out;
}

const machineNames = new Map();
async function currentMachine(job) {
  if (!job || job.type !== "run") return null;
  if (machineNames.has(job.id)) return machineNames.get(job.id);
  let name = null;
  try {
    const text = await api(`/v1/jobs/${job.id}/files/plan.toml`);
    const m = /^\s*name\s*=\s*"([^"]*)"/m.exec(text.split(/^\[machine\]\s*$/m)[1] || "");
    name = m ? m[1] : null;
  } catch (_) { /* the plan may not be stored yet */ }
  machineNames.set(job.id, name);
  return name;
}

function summarizeReading(r) {
  if (!r) return "—";
  if (typeof r.length_m === "number") return `${r.length_m.toFixed(6)} m, signal ${(r.signal ?? 0).toFixed(2)}`;
  if (typeof r.air_temp_k === "number") return `${r.air_temp_k.toFixed(2)} K, ${Math.round(r.pressure_pa)} Pa, ${r.humidity_pct.toFixed(0)} %`;
  if (Array.isArray(r.position_m)) return `${r.state || ""} ${r.position_m.map((v) => v.toFixed(4)).join(", ")} m`;
  const text = JSON.stringify(r);
  return text.length > 80 ? text.slice(0, 77) + "…" : text;
}

async function renderPrompts() {
  await refreshPrompts();
  const out = h("div", {}, h("h1", {}, "Prompts"));
  if (state.prompts.length === 0) {
    out.append(h("p", { class: "muted" }, "Nothing waits for you. A prompt appears here, and as a banner on every page, when a run needs the operator."),
      h("p", {}, "Sound plays when a prompt comes. ",
        "Notification" in window && Notification.permission === "default"
          ? h("button", { class: "button secondary", onclick: () => Notification.requestPermission() }, "Also notify me")
          : null));
    return out;
  }
  for (const p of state.prompts) {
    const station = (/station (\S+)/.exec(p.instruction) || [])[1];
    let layout = null;
    try { layout = await api(`/v1/jobs/${p.job}/layout`); } catch (e) { if (e instanceof Unauthorized) throw e; }
    const card = h("section", { class: "card", "data-prompt": p.id },
      h("p", { class: "muted" }, `Job ${p.job}, asked ${fmtTime(p.prompted_at)}`),
      h("p", { class: "instruction" }, p.instruction),
      layout && (layout.stations.length || layout.travel.length) ? h("figure", { class: "layout" }, layoutPlot(layout, station),
        h("figcaption", { class: "muted" }, "Seen from above: the machine's travel (green) and the stations' hint positions; the next one in red.")) : null,
      h("button", { class: "button huge", "data-ack": p.id, onclick: (e) => acknowledge(p.id, e.currentTarget) }, "Continue"));
    out.append(card);
  }
  return out;
}

async function renderJobs() {
  const [jobs, plans] = await Promise.all([api("/v1/jobs"), api("/v1/plans")]);
  const out = h("div", {}, h("h1", {}, "Jobs"));
  const message = h("p", { role: "status", id: "submit-message" });
  // A redraw (a job queued or ended) keeps the operator's choice of plan.
  const chosen = document.getElementById("plan-select")?.value;
  const choose = h("select", { id: "plan-select", "aria-label": "plan from the library" },
    plans.map((p) => h("option", { value: p.name, selected: p.name === chosen }, `${p.name}${p.kind ? ` (${p.kind}${p.machine ? `, ${p.machine}` : ""})` : ""}`)));
  const submitted = (id) => { message.textContent = `Submitted as job ${id}.`; location.hash = `#/jobs/${id}`; };
  const fail = (e) => { if (!(e instanceof Unauthorized)) message.textContent = `Not submitted: ${e.message}`; };
  const upload = h("input", { type: "file", id: "plan-file", accept: ".toml,application/toml" });
  out.append(h("section", { class: "card" }, h("h2", {}, "Run a plan"),
    plans.length ? h("div", {}, h("label", { for: "plan-select" }, "From the plan library"),
      h("div", { class: "actions" }, choose, h("button", { class: "button big", id: "submit-library",
        onclick: () => post(`/v1/plans/${encodeURIComponent(choose.value)}/submit`).then((r) => submitted(r.id), fail) }, "Run")))
      : h("p", { class: "muted" }, "The daemon names no plan library (plan_library in its configuration)."),
    h("label", { for: "plan-file" }, "Or upload a plan (TOML)"),
    h("div", { class: "actions" }, upload, h("button", { class: "button secondary", id: "submit-upload", onclick: async () => {
      if (!upload.files.length) { message.textContent = "Choose a file first."; return; }
      post("/v1/jobs", await upload.files[0].text(), "application/toml").then((r) => submitted(r.id), fail);
    } }, "Upload and run")),
    message));
  out.append(h("h2", {}, "Catalog"), jobs.length === 0 ? h("p", { class: "muted" }, "No job yet.") :
    table(["job", "state", "kind", "type", "progress", "submitted", "started", "ended", "by", ""], jobs.map((j) =>
      h("tr", { "data-job": j.id }, h("td", {}, h("a", { href: `#/jobs/${j.id}` }, `${j.id}`)), h("td", {}, stateBadge(j.state)),
        h("td", {}, j.kind), h("td", {}, j.type), h("td", { class: "num" }, `${j.progress.done}/${j.progress.total}`),
        h("td", {}, fmtTime(j.submitted_at)), h("td", {}, fmtTime(j.started_at)), h("td", {}, fmtTime(j.finished_at)),
        h("td", {}, j.submitted_by), h("td", {}, jobActions(j))))));
  return out;
}

function jobActions(job) {
  const act = (what) => post(`/v1/jobs/${job.id}/${what}`).then(rerender, (e) => { if (!(e instanceof Unauthorized)) alert(e.message); });
  const resumable = job.type === "run" && (["interrupted", "cancelled"].includes(job.state)
    || (job.state === "failed" && job.files.some((f) => f.name === "session.mcap")));
  return h("div", { class: "actions" },
    ["queued", "running"].includes(job.state) ? h("button", { class: "button danger", onclick: () => act("cancel") }, "Cancel") : null,
    resumable ? h("button", { class: "button secondary", onclick: () => act("resume") }, "Resume") : null);
}

async function renderJob(id) {
  const job = await api(`/v1/jobs/${encodeURIComponent(id)}`);
  const has = (name) => job.files.some((f) => f.name === name);
  const out = h("div", {}, h("h1", {}, `Job ${job.id}: `, stateBadge(job.state)));
  out.append(h("section", { class: "card" },
    h("dl", { class: "kv" },
      h("dt", {}, "kind"), h("dd", {}, `${job.kind} ${job.type}${job.source_job ? ` of job ${job.source_job}` : ""}`),
      h("dt", {}, "submitted"), h("dd", {}, `${fmtTime(job.submitted_at)} by ${job.submitted_by}`),
      h("dt", {}, "started"), h("dd", {}, fmtTime(job.started_at)),
      h("dt", {}, "ended"), h("dd", {}, fmtTime(job.finished_at)),
      job.error ? [h("dt", {}, "error"), h("dd", { class: "error" }, job.error)] : null),
    progressOf(job), jobActions(job),
    job.type === "run" && has("session.mcap") && !["queued", "running"].includes(job.state)
      ? h("div", { class: "actions" },
        h("button", { class: "button secondary", onclick: () => post("/v1/jobs", JSON.stringify({ type: "diagnose", session_of: job.id }), "application/json")
          .then((r) => { location.hash = `#/jobs/${r.id}`; }, (e) => alert(e.message)) }, "Diagnose its session"))
      : null));
  if (has("results.json")) {
    try { out.append(resultsSummary(await api(`/v1/jobs/${job.id}/results`))); } catch (e) { if (e instanceof Unauthorized) throw e; }
  }
  if (has("diagnosis.json")) {
    try { out.append(diagnosisSummary(await api(`/v1/jobs/${job.id}/files/diagnosis.json`))); } catch (e) { if (e instanceof Unauthorized) throw e; }
  }
  out.append(h("h2", {}, "Files"), table(["file", "bytes"], job.files.map((f) =>
    h("tr", {}, h("td", {}, h("a", { href: `/v1/jobs/${job.id}/files/${encodeURIComponent(f.name)}`, download: f.name }, f.name)),
      h("td", { class: "num" }, f.bytes)))));
  if (has("report.html")) {
    out.append(h("h2", {}, "Report ", h("a", { href: `/v1/jobs/${job.id}/report`, target: "_blank", rel: "noopener" }, "(open alone)")),
      h("iframe", { class: "report", id: "report-frame", title: `report of job ${job.id}`, src: `/v1/jobs/${job.id}/report`,
        sandbox: "allow-scripts allow-popups" }));
  }
  return out;
}

function resultsSummary(r) {
  const rows = [];
  const add = (k, v) => rows.push(h("tr", {}, h("th", { scope: "row" }, k), h("td", {}, v)));
  add("format", `${r.format || "—"} (${r.kind || ""})`);
  for (const [k, v] of Object.entries(r)) {
    if (typeof v === "number") add(k, fmtNumber(v, k.endsWith("_m") ? "m" : k.endsWith("_rad") ? "rad" : ""));
    else if (Array.isArray(v)) add(k, `${v.length} entries`);
  }
  if (Array.isArray(r.points) && r.points.length && Array.isArray(r.points[0].error_m)) {
    const worst = r.points.reduce((a, p) => (Math.hypot(...p.error_m) > Math.hypot(...a.error_m) ? p : a));
    add("largest point error", `${fmtNumber(Math.hypot(...worst.error_m), "m")} at point ${worst.point}`);
  }
  if (r.geometric_errors && typeof r.geometric_errors === "object") add("geometric errors", Object.keys(r.geometric_errors).join(", "));
  return h("section", { class: "card", id: "results-summary" }, h("h2", {}, "Results"), table(["", ""], rows));
}

function diagnosisSummary(d) {
  const rows = (d.where || []).slice(0, 5).map((w) => h("tr", {}, h("td", {}, `${w.level} ${w.group} ${w.key}`),
    h("td", { class: "num" }, `${(100 * w.share).toFixed(0)} %`), h("td", { class: "num" }, fmtNumber(w.rms_m, "m"))));
  return h("section", { class: "card", id: "diagnosis-summary" }, h("h2", {}, "Diagnosis"),
    h("p", {}, `Residual RMS ${fmtNumber(d.gap?.rms_m, "m")} against a noise floor of ${fmtNumber(d.noise_floor_m, "m")}; `,
      d.selected && d.selected.length ? `explained by ${d.selected.join(", ")}` : "no effect selected",
      d.unexplained ? "; structure remains that no candidate explains." : "."),
    rows.length ? table(["where", "share", "RMS"], rows) : null);
}

async function renderMachines() {
  const machines = await api("/v1/machines");
  const out = h("div", {}, h("h1", {}, "Machines"));
  if (machines.length === 0) {
    out.append(h("p", { class: "muted" }, "No machine has a succeeded run yet."));
    return out;
  }
  out.append(table(["machine", "serial", "kinds", "runs", "last run", "last change"], machines.map((m) =>
    h("tr", {}, h("td", {}, h("a", { href: `#/machines/${encodeURIComponent(m.key || m.name)}` }, m.name)), h("td", {}, m.serial || "—"),
      h("td", {}, m.kinds.join(", ")), h("td", { class: "num" }, m.runs), h("td", {}, `job ${m.last_job}, ${fmtTime(m.last_started_at)}`),
      h("td", {}, m.last_changed === undefined ? "—" : m.last_changed ? "changed at its last run" : "no change")))));
  return out;
}

async function renderMachine(key) {
  const path = `/v1/machines/${encodeURIComponent(key)}`;
  const history = await api(`${path}/history`);
  const out = h("div", {}, h("h1", {}, `Machine: ${history.machine}`));
  out.append(h("h2", {}, "Runs"), table(["job", "kind", "started", "by", "against the run before"], history.runs.map((r) =>
    h("tr", {}, h("td", {}, h("a", { href: `#/jobs/${r.job}` }, r.job)), h("td", {}, r.kind), h("td", {}, fmtTime(r.started_at)),
      h("td", {}, r.submitted_by), h("td", {}, r.comparison ? (r.comparison.changed
        ? `changed: ${r.comparison.significant.length} significant, ${r.comparison.exceeding_tolerance.length} beyond tolerance`
        : `no change (${r.comparison.compared} compared)`) : "—")))));
  let trend;
  try { trend = await api(`${path}/trend`); } catch (e) {
    if (e instanceof Unauthorized) throw e;
    out.append(h("p", { class: "muted" }, `No trend: ${e.message}`));
    return out;
  }
  const events = trend.events || [];
  out.append(h("h2", {}, `Trend over ${trend.runs.length} ${trend.kind} runs`),
    h("p", {}, events.length ? `${events.length} event(s): ` : "No step, drift or value beyond its band was found ",
      events.length ? events.map((e) => `${e.kind} of ${e.parameter} at ${e.run_label || `run ${e.run}`}`).join("; ")
        : `(α = ${trend.alpha}, ${trend.tests} tests).`));
  const named = new Set(events.map((e) => e.parameter));
  const params = [...trend.parameters].sort((a, b) => (named.has(b.id) - named.has(a.id)));
  const shown = h("div", { class: "plots", id: "trend-plots" });
  const draw = (count) => shown.replaceChildren(...params.slice(0, count).map((p) => h("div", { class: "card" }, trendPlot(p, trend.runs, events))));
  draw(12);
  out.append(shown);
  if (params.length > 12) out.append(h("button", { class: "button secondary", onclick: (e) => { draw(params.length); e.currentTarget.remove(); } },
    `Show all ${params.length} parameters`));
  out.append(compareRuns(trend));
  return out;
}

// Two runs side by side: each parameter's change against its two σ combined.
function compareRuns(trend) {
  const pick = (id, at) => h("select", { id, "aria-label": id === "run-a" ? "first run" : "second run" },
    trend.runs.map((r, i) => h("option", { value: i, selected: i === at }, `${r.label} (${fmtTime(r.started_at)})`)));
  const a = pick("run-a", Math.max(trend.runs.length - 2, 0)), b = pick("run-b", trend.runs.length - 1);
  const result = h("div", { id: "compare-result" });
  const show = () => {
    const i = +a.value, j = +b.value;
    const rows = trend.parameters.map((p) => {
      const va = p.values[i], vb = p.values[j], sa = p.sigmas[i], sb = p.sigmas[j];
      const diff = va !== null && vb !== null ? vb - va : null;
      const sigma = sa && sb ? Math.hypot(sa, sb) : null;
      return { p, diff, sigma, z: diff !== null && sigma ? diff / sigma : null };
    }).sort((x, y) => Math.abs(y.z ?? 0) - Math.abs(x.z ?? 0));
    result.replaceChildren(table(["parameter", "change", "σ of the change", "z"], rows.slice(0, 30).map((r) =>
      h("tr", { class: r.z !== null && Math.abs(r.z) > 3 ? "error" : "" }, h("td", {}, r.p.id), h("td", { class: "num" }, fmtNumber(r.diff, r.p.unit)),
        h("td", { class: "num" }, fmtNumber(r.sigma, r.p.unit)), h("td", { class: "num" }, r.z === null ? "—" : r.z.toFixed(2))))),
      h("p", { class: "muted" }, "The 30 largest changes by z; the trend's own tests (above) correct for the number of parameters, this table does not."));
  };
  a.addEventListener("change", show); b.addEventListener("change", show);
  show();
  return h("section", { class: "card" }, h("h2", {}, "Compare two runs"), h("div", { class: "actions" }, a, h("span", {}, "→"), b), result);
}

async function renderSchedules() {
  const schedules = await api("/v1/schedules");
  const out = h("div", {}, h("h1", {}, "Schedules"));
  if (schedules.length === 0) {
    out.append(h("p", { class: "muted" }, "No schedule ([[schedule]] in the daemon's configuration)."));
    return out;
  }
  out.append(table(["schedule", "when", "plan", "next run", "if busy", "last result"], schedules.map((sc) =>
    h("tr", {}, h("td", {}, sc.name), h("td", {}, `${sc.cron} (${sc.time_zone})`), h("td", {}, sc.plan),
      h("td", {}, fmtTime(sc.next_run)), h("td", {}, sc.when_busy),
      h("td", {}, sc.last_job ? [h("a", { href: `#/jobs/${sc.last_job.id}` }, `job ${sc.last_job.id}`), " ", stateBadge(sc.last_job.state),
        sc.last_job.error ? h("span", { class: "error" }, ` ${sc.last_job.error}`) : null] : "none yet")))));
  return out;
}

// ---- Updates: the daemon's event stream, and a slow poll for what it does not announce ----
let events = null;
function startEvents() {
  if (events) events.close();
  events = new EventSource("/v1/events", { withCredentials: true });
  events.onopen = () => { $("link-state").textContent = "live"; };
  events.onerror = () => { $("link-state").textContent = "reconnecting…"; };
  // The catalog and schedules change with job states; a job's page and Now with its progress too
  // (not the catalog: a redraw per point would reset a half-made choice of plan or file).
  const follows = { job: ["now", "jobs", "job", "schedules"], progress: ["now", "job"], station: ["now", "job"], fault: ["now", "job"] };
  for (const [name, pagesShown] of Object.entries(follows)) {
    events.addEventListener(name, () => { if (pagesShown.includes(route()[0])) soon(); });
  }
  events.addEventListener("prompt", () => refreshPrompts().then(() => { if (route()[0] === "prompts") rerender(); }).catch(() => {}));
  events.addEventListener("machine_change", () => { if (route()[0].startsWith("machine")) rerender(); });
}

// At most one redraw per half second, however fast the events come.
let pending = null;
function soon() {
  if (pending) return;
  pending = setTimeout(() => { pending = null; rerender(); }, 500);
}

async function tick() {
  try {
    await refreshPrompts();
    if (route()[0] === "now") soon();
  } catch (_) { /* shown by the page */ }
}

document.addEventListener("DOMContentLoaded", () => {
  $("login-form").addEventListener("submit", login);
  $("banner-continue").addEventListener("click", (e) => acknowledge(e.currentTarget.dataset.prompt, e.currentTarget));
  window.addEventListener("hashchange", () => { rerender(); $("main").focus(); });
  $("banner-continue").disabled = false;
  api("/v1/health").then(() => { startEvents(); refreshPrompts(); }, () => {});
  rerender();
  setInterval(tick, 1000);
});
