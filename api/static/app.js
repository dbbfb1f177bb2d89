// Convoy job service dashboard: plain ES2020, no dependencies, no build step.
"use strict";

const METRICS = ["eval_return", "return", "env_steps_per_s", "loss", "policy_lag"];
const ACTIVE = new Set(["queued", "starting", "running"]);
const TERMINAL = new Set(["stopped", "completed", "failed"]);
const TOKEN_KEY = "convoy-token";
const JOBS_EVERY_MS = 2000;
const METRICS_EVERY_MS = 1000;

const $ = (id) => document.getElementById(id);

const state = {
  jobs: [],
  selected: null,        // job id
  job: null,             // latest JobView of the selected job
  series: {},            // metric -> [[env_steps, value], ...]
  lastStep: null,        // last env_steps received for the selected job
  metricsBusy: false,
  gen: 0,                // bumped on every selection change
  metricsDrained: false, // terminal job and nothing new came back
  requestedShown: null,  // requested actors last written into #actors-input
  offline: false,
};

window.convoy = { points: Object.fromEntries(METRICS.map((m) => [m, 0])), selected: null };

// ---------------------------------------------------------------- formatting

function fmtCount(v) {
  if (v == null || !Number.isFinite(v)) return "–";
  const a = Math.abs(v);
  if (a >= 1e9) return (v / 1e9).toFixed(a >= 1e10 ? 1 : 2).replace(/\.?0+$/, "") + "G";
  if (a >= 1e6) return (v / 1e6).toFixed(a >= 1e7 ? 1 : 2).replace(/\.?0+$/, "") + "M";
  if (a >= 1e4) return (v / 1e3).toFixed(a >= 1e5 ? 0 : 1).replace(/\.0$/, "") + "k";
  return Math.round(v).toLocaleString("en-US");
}

function fmtValue(v) {
  if (v == null || !Number.isFinite(v)) return "–";
  const a = Math.abs(v);
  if (a >= 1e4) return fmtCount(v);
  if (a >= 100) return v.toFixed(0);
  if (a >= 1) return v.toFixed(2);
  if (a === 0) return "0";
  return v.toPrecision(3);
}

// ---------------------------------------------------------------- messages

let messageTimer = null;
function showMessage(text, kind = "error") {
  const el = $("message");
  clearTimeout(messageTimer);
  el.textContent = text;
  el.className = "message " + kind;
  el.hidden = false;
  if (kind === "info") messageTimer = setTimeout(clearMessage, 4000);
}
function clearMessage() {
  const el = $("message");
  el.hidden = true;
  el.textContent = "";
  el.className = "message";
}

// Turns an error response body into "problem — fix" text.
function describeError(status, body) {
  if (body && typeof body === "object") {
    if (body.problem) {
      const field = body.field ? `${body.field}: ` : "";
      return `${field}${body.problem}${body.fix ? `\nFix: ${body.fix}` : ""}`;
    }
    if (body.detail) {
      const d = body.detail;
      if (typeof d === "object" && !Array.isArray(d)) return describeError(status, d);
      return typeof d === "string" ? d : JSON.stringify(d);
    }
  }
  return `request failed with HTTP ${status}`;
}

// ---------------------------------------------------------------- HTTP

class ApiError extends Error {
  constructor(status, body) {
    super(describeError(status, body));
    this.status = status;
    this.body = body;
  }
}

async function api(path, { method = "GET", body, auth = false } = {}) {
  const headers = { Accept: "application/json" };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (auth) headers.Authorization = `Bearer ${$("token").value.trim()}`;
  const resp = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body), cache: "no-store" });
  let data = null;
  const text = await resp.text();
  if (text) {
    try { data = JSON.parse(text); } catch { data = { problem: text.slice(0, 300) }; }
  }
  if (!resp.ok) throw new ApiError(resp.status, data);
  return data;
}

const jobPath = (id) => `jobs/${encodeURIComponent(id)}`;

function setOffline(offline, err) {
  if (offline && !state.offline) showMessage(`Cannot reach the job service (${err && err.message ? err.message : err}). Retrying…`);
  if (!offline && state.offline) clearMessage();
  state.offline = offline;
}

// ---------------------------------------------------------------- charts

const COLORS = { eval_return: "#1d3f8f", return: "#8fb0ef", env_steps_per_s: "#2e9d5b", loss: "#d9822b", policy_lag: "#8b5cf6" };

function niceTicks(lo, hi, count) {
  if (!(hi > lo)) { const d = Math.abs(lo) * 0.1 || 1; lo -= d; hi += d; }
  const raw = (hi - lo) / count;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const r = raw / mag;
  const step = (r < 1.5 ? 1 : r < 3 ? 2 : r < 7 ? 5 : 10) * mag;
  const start = Math.floor(lo / step) * step, end = Math.ceil(hi / step) * step;
  const ticks = [];
  for (let v = start; v <= end + step * 1e-6; v += step) ticks.push(Math.abs(v) < step * 1e-9 ? 0 : v);
  return { lo: start, hi: end, step, ticks };
}

function tickLabel(v, step) {
  if (Math.abs(step) >= 1e4 || Math.abs(v) >= 1e4) return fmtCount(v);
  const decimals = Math.max(0, Math.min(6, -Math.floor(Math.log10(step) + 1e-9)));
  return v.toFixed(decimals);
}

// Draws one learning curve (points: [[x, y], ...], nulls already skipped). Returns the number of points drawn.
function drawChart(canvas, points, color) {
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth || 300, h = canvas.clientHeight || 180;
  if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
    canvas.width = Math.round(w * dpr);
    canvas.height = Math.round(h * dpr);
  }
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, w, h);
  ctx.font = "11px system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif";

  if (points.length === 0) {
    ctx.fillStyle = "#9aa5b1";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    ctx.fillText("no data yet", w / 2, h / 2);
    return 0;
  }

  let xmin = Infinity, xmax = -Infinity, ymin = Infinity, ymax = -Infinity;
  for (const [x, y] of points) {
    if (x < xmin) xmin = x; if (x > xmax) xmax = x;
    if (y < ymin) ymin = y; if (y > ymax) ymax = y;
  }
  const yt = niceTicks(ymin, ymax, 4);
  const xt = niceTicks(xmin, xmax, Math.max(2, Math.floor(w / 110)));
  const yLabels = yt.ticks.map((v) => tickLabel(v, yt.step));
  const left = 10 + Math.max(...yLabels.map((s) => ctx.measureText(s).width));
  const right = 12, top = 8, bottom = 22;
  const pw = Math.max(10, w - left - right), ph = Math.max(10, h - top - bottom);
  const sx = (x) => left + ((x - xt.lo) / (xt.hi - xt.lo)) * pw;
  const sy = (y) => top + ph - ((y - yt.lo) / (yt.hi - yt.lo)) * ph;

  // grid and y tick labels
  ctx.strokeStyle = "#edf0f4";
  ctx.lineWidth = 1;
  ctx.fillStyle = "#6b7785";
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  yt.ticks.forEach((v, i) => {
    const y = Math.round(sy(v)) + 0.5;
    ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + pw, y); ctx.stroke();
    ctx.fillText(yLabels[i], left - 6, y);
  });
  // x tick labels
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  for (const v of xt.ticks) {
    const x = Math.round(sx(v)) + 0.5;
    ctx.beginPath(); ctx.moveTo(x, top + ph); ctx.lineTo(x, top + ph + 4); ctx.strokeStyle = "#c5ccd6"; ctx.stroke();
    const label = tickLabel(v, xt.step), half = ctx.measureText(label).width / 2;
    ctx.fillText(label, Math.min(Math.max(x, half + 1), w - half - 1), top + ph + 7);
  }
  // axes
  ctx.strokeStyle = "#c5ccd6";
  ctx.beginPath(); ctx.moveTo(left + 0.5, top); ctx.lineTo(left + 0.5, top + ph + 0.5); ctx.lineTo(left + pw, top + ph + 0.5); ctx.stroke();

  // the curve: soft area fill then line
  ctx.beginPath();
  points.forEach(([x, y], i) => (i ? ctx.lineTo(sx(x), sy(y)) : ctx.moveTo(sx(x), sy(y))));
  ctx.lineWidth = 1.8;
  ctx.lineJoin = "round";
  ctx.strokeStyle = color;
  ctx.stroke();
  ctx.lineTo(sx(points[points.length - 1][0]), top + ph);
  ctx.lineTo(sx(points[0][0]), top + ph);
  ctx.closePath();
  ctx.globalAlpha = 0.08;
  ctx.fillStyle = color;
  ctx.fill();
  ctx.globalAlpha = 1;
  // mark the latest point
  const [lx, ly] = points[points.length - 1];
  ctx.beginPath(); ctx.arc(sx(lx), sy(ly), 3, 0, Math.PI * 2); ctx.fillStyle = color; ctx.fill();
  return points.length;
}

function redrawCharts() {
  for (const m of METRICS) {
    window.convoy.points[m] = drawChart($(`chart-${m}`), state.series[m] || [], COLORS[m]);
  }
  window.convoy.selected = state.selected;
}

// ---------------------------------------------------------------- jobs table

function cell(text, cls) {
  const td = document.createElement("td");
  if (cls) td.className = cls;
  if (text instanceof Node) td.appendChild(text); else td.textContent = text;
  return td;
}

function badge(job) {
  const span = document.createElement("span");
  span.className = `badge ${job.state}`;
  span.textContent = job.state === "queued" && job.queue_position != null ? `queued #${job.queue_position}` : job.state;
  return span;
}

function progressCell(job) {
  const p = job.progress || {};
  const done = p.env_steps ?? 0;
  const frac = Math.max(0, Math.min(1, p.fraction ?? (job.steps ? done / job.steps : 0)));
  const wrap = document.createElement("div");
  wrap.className = "progress";
  const bar = document.createElement("div");
  bar.className = "bar" + (job.state === "completed" ? " done" : job.state === "failed" ? " failed" : "");
  const fill = document.createElement("span");
  fill.style.width = `${(frac * 100).toFixed(1)}%`;
  bar.appendChild(fill);
  const label = document.createElement("span");
  label.className = "label";
  label.textContent = `${fmtCount(done)} / ${fmtCount(job.steps)}`;
  label.title = `${Math.round(frac * 100)}%`;
  wrap.append(bar, label);
  return wrap;
}

function renderJobs() {
  const tbody = $("jobs");
  const rows = state.jobs.map((job) => {
    const tr = document.createElement("tr");
    tr.dataset.jobId = job.id;
    if (job.id === state.selected) tr.className = "selected";
    const p = job.progress || {};
    tr.append(
      cell(job.id, "id"),
      cell(`${job.algo} on ${job.env}`),
      cell(badge(job)),
      cell(progressCell(job)),
      cell(`${job.actors_alive} / ${job.actors}`, "num"),
      cell(fmtValue(p.return), "num"),
      cell(fmtCount(p.env_steps_per_s), "num"),
    );
    tr.addEventListener("click", () => selectJob(job.id));
    return tr;
  });
  if (rows.length === 0) {
    const tr = document.createElement("tr");
    tr.className = "empty";
    tr.appendChild(cell("no jobs yet"));
    tr.firstChild.colSpan = 7;
    rows.push(tr);
  }
  tbody.replaceChildren(...rows);
  $("jobs-updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
}

async function refreshJobs() {
  try {
    const data = await api("jobs");
    state.jobs = (data.jobs || []).slice().sort((a, b) => (b.created_at ?? 0) - (a.created_at ?? 0));
    setOffline(false);
    if (state.selected == null && state.jobs.length) {
      const running = state.jobs.find((j) => j.state === "running");
      selectJob((running || state.jobs[0]).id);
    } else {
      const sel = state.jobs.find((j) => j.id === state.selected);
      if (sel) updatePanel(sel);
    }
    renderJobs();
  } catch (err) {
    setOffline(true, err);
  }
}

// ---------------------------------------------------------------- selected job panel

function updatePanel(job) {
  if (!job || job.id !== state.selected) return;
  const wasTerminal = state.job && TERMINAL.has(state.job.state);
  state.job = job;
  if (!TERMINAL.has(job.state) || !wasTerminal) state.metricsDrained = false;
  const p = job.progress || {};
  $("job-title").textContent = `${job.id} · ${job.algo} on ${job.env}`;
  const st = $("job-state");
  st.className = `badge ${job.state}`;
  st.textContent = job.state === "queued" && job.queue_position != null ? `queued #${job.queue_position}` : job.state;
  $("actors-alive").textContent = String(job.actors_alive);
  $("actors-requested").textContent = String(job.actors);
  $("job-steps").textContent = `${fmtCount(p.env_steps)} / ${fmtCount(job.steps)}`;
  $("job-return").textContent = fmtValue(p.return);
  $("job-sps").textContent = fmtCount(p.env_steps_per_s);
  $("job-ups").textContent = fmtValue(p.updates_per_s);
  $("job-lag").textContent = fmtValue(p.policy_lag);
  $("job-checkpoint").textContent = job.last_checkpoint || "–";
  $("job-checkpoint").title = job.last_checkpoint || "";
  const errEl = $("job-error");
  errEl.hidden = !job.error;
  errEl.textContent = job.error || "";
  // Prefill the scale input with the requested actors, unless the user is editing it.
  const input = $("actors-input");
  if (state.requestedShown !== job.actors && document.activeElement !== input) {
    input.value = String(job.actors);
    state.requestedShown = job.actors;
  }
  const active = ACTIVE.has(job.state);
  $("scale-btn").disabled = !active;
  $("stop-btn").disabled = !active;
}

function resetPanel() {
  state.series = Object.fromEntries(METRICS.map((m) => [m, []]));
  state.lastStep = null;
  state.metricsDrained = false;
  state.requestedShown = null;
  state.job = null;
}

function selectJob(id) {
  if (id === state.selected) return;
  state.selected = id;
  state.gen += 1;
  resetPanel();
  const job = state.jobs.find((j) => j.id === id);
  if (job) updatePanel(job);
  else $("job-title").textContent = id;
  renderJobs();
  redrawCharts();
  api(jobPath(id)).then(updatePanel).catch((err) => showMessage(`Could not load job ${id}: ${err.message}`));
  pollMetrics();
}

// ---------------------------------------------------------------- metrics polling (incremental)

async function pollMetrics() {
  const id = state.selected, gen = state.gen;
  if (id == null || state.metricsBusy || state.metricsDrained) return;
  state.metricsBusy = true;
  try {
    const since = state.lastStep;
    const data = await api(`${jobPath(id)}/metrics` + (since == null ? "" : `?since=${encodeURIComponent(since)}`));
    if (gen !== state.gen) return; // selection changed while in flight
    let added = 0;
    for (const row of data.rows || []) {
      const x = row.env_steps;
      if (typeof x !== "number" || (state.lastStep != null && x <= state.lastStep)) continue;
      state.lastStep = x;
      added += 1;
      for (const m of METRICS) {
        const v = row[m];
        if (typeof v === "number" && Number.isFinite(v)) state.series[m].push([x, v]);
      }
    }
    if (added === 0 && state.job && TERMINAL.has(state.job.state)) state.metricsDrained = true;
    redrawCharts();
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
  } finally {
    state.metricsBusy = false;
  }
}

// ---------------------------------------------------------------- actions

async function scaleJob() {
  const id = state.selected;
  if (id == null) return;
  const n = Number($("actors-input").value);
  if (!Number.isInteger(n) || n < 1 || n > 64) {
    showMessage("actors: must be a whole number between 1 and 64\nFix: enter a value from 1 to 64 and press Scale again.");
    return;
  }
  const btn = $("scale-btn");
  btn.disabled = true;
  try {
    const job = await api(jobPath(id), { method: "PATCH", body: { actors: n }, auth: true });
    state.requestedShown = null;
    replaceJob(job);
    showMessage(`Job ${id}: scaling to ${job.actors} actor${job.actors === 1 ? "" : "s"}.`, "info");
  } catch (err) {
    showMessage(`Scale failed — ${err.message}`);
  } finally {
    if (state.job) btn.disabled = !ACTIVE.has(state.job.state);
  }
}

async function stopJob() {
  const id = state.selected;
  if (id == null) return;
  const btn = $("stop-btn");
  btn.disabled = true;
  try {
    const job = await api(`${jobPath(id)}/stop`, { method: "POST", auth: true });
    replaceJob(job);
    showMessage(`Job ${id}: stop requested (${job.state}).`, "info");
  } catch (err) {
    showMessage(`Stop failed — ${err.message}`);
  } finally {
    if (state.job) btn.disabled = !ACTIVE.has(state.job.state);
  }
}

function replaceJob(job) {
  if (!job || !job.id) return;
  const i = state.jobs.findIndex((j) => j.id === job.id);
  if (i >= 0) state.jobs[i] = job; else state.jobs.unshift(job);
  updatePanel(job);
  renderJobs();
}

// ---------------------------------------------------------------- boot

function boot() {
  const token = $("token");
  try { token.value = localStorage.getItem(TOKEN_KEY) || ""; } catch { /* storage unavailable */ }
  token.addEventListener("input", () => {
    try { localStorage.setItem(TOKEN_KEY, token.value.trim()); } catch { /* storage unavailable */ }
  });
  $("scale-btn").addEventListener("click", scaleJob);
  $("stop-btn").addEventListener("click", stopJob);
  $("actors-input").addEventListener("keydown", (e) => { if (e.key === "Enter") scaleJob(); });
  $("scale-btn").disabled = true;
  $("stop-btn").disabled = true;
  resetPanel();
  redrawCharts();
  let resizeTimer = null;
  window.addEventListener("resize", () => { clearTimeout(resizeTimer); resizeTimer = setTimeout(redrawCharts, 100); });
  refreshJobs();
  setInterval(refreshJobs, JOBS_EVERY_MS);
  setInterval(pollMetrics, METRICS_EVERY_MS);
}

if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", boot);
else boot();
