// Convoy job service dashboard: plain ES2020, no dependencies, no build step.
"use strict";

const METRICS = ["eval_return", "return", "env_steps_per_s", "loss", "policy_lag"];
const BAND = "eval_ci95"; // the greedy return's 95 % CI half-width, drawn as a band around it
const ACTIVE = new Set(["queued", "starting", "running"]);
const TERMINAL = new Set(["stopped", "completed", "failed"]);
const TOKEN_KEY = "convoy-token";
const JOBS_EVERY_MS = 2000;
const METRICS_EVERY_MS = 1000;
const SWEEPS_EVERY_MS = 3000;
const LOGS_EVERY_MS = 5000;

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
  sweeps: [],
  sweep: null,           // selected sweep id
  summary: null,         // its latest summary
  compare: new Set(),    // job ids ticked for the comparison chart
  compareSeries: {},     // job id -> [[env_steps, eval_return], ...]
  evaluation: null,      // [job id, evaluation id] being followed
  checkpointShown: null, // last_checkpoint the download links were made for
  openFirstJob: true,    // select the running (else the newest) job once the jobs arrive; not for a #sweep= link
  revealSweep: null,     // a sweep a link named: its chart is scrolled into view once drawn
  jobsShown: false,      // the jobs table has had its first answer
};

window.convoy = {
  points: Object.fromEntries(METRICS.map((m) => [m, 0])),
  selected: null,
  sweep: { id: null, groups: 0, bands: 0, overlays: 0 },
  evaluation: null,
  logs: 0,
  revealed: null, // the sweep a #sweep= link scrolled into view
};

// ---------------------------------------------------------------- formatting

function fmtCount(v) {
  if (v == null || !Number.isFinite(v)) return "–";
  const a = Math.abs(v);
  if (a >= 1e9) return (v / 1e9).toFixed(a >= 1e10 ? 1 : 2).replace(/\.?0+$/, "") + "G";
  if (a >= 1e6) return (v / 1e6).toFixed(a >= 1e7 ? 1 : 2).replace(/\.?0+$/, "") + "M";
  if (a >= 1e4) return (v / 1e3).toFixed(a >= 1e5 ? 0 : 1).replace(/\.0$/, "") + "k";
  return Math.round(v).toLocaleString("en-US");
}

// a file's size as people write it: 1.3 MB, 842 kB, 512 B (SI units, as the byte counts the API gives)
function fmtBytes(v) {
  if (v == null || !Number.isFinite(v) || v < 0) return "–";
  const units = ["B", "kB", "MB", "GB", "TB"];
  let i = 0;
  while (i < units.length - 1 && Math.round(v) >= 1000) {
    v /= 1000;
    i += 1;
  }
  return `${v.toFixed(i === 0 || v >= 9.95 ? 0 : 1)} ${units[i]}`;
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
const REF_COLORS = ["#7b8794", "#d9822b", "#2e9d5b", "#c0392b", "#8b5cf6", "#a16207"];

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

// A curve's y-axis beside reference returns: it fits the curve and its band (bandPts: [[x, low, high]]); a
// reference ([name, y]) widens it, the nearest first, only while the curve and band keep at least 1 / REF_ZOOM of
// its height, so a return of 17 stays readable beside a scripted 174. Returns the axis's niceTicks and the
// references on it (shown, as lines) and beyond it (above, below: arrows at that edge), each in the refs' order.
const REF_ZOOM = 2.5;
function yAxis(points, bandPts, refs) {
  let lo = Infinity, hi = -Infinity;
  for (const [, y] of points) { lo = Math.min(lo, y); hi = Math.max(hi, y); }
  for (const [, l, h] of bandPts) { lo = Math.min(lo, l); hi = Math.max(hi, h); }
  // no zoom into noise: the axis spans at least 10 % of the values' size (23.47 → 23.22 is a flat line)
  const minSpan = 0.1 * Math.max(Math.abs(lo), Math.abs(hi), 1e-9);
  if (hi - lo < minSpan) { const mid = (hi + lo) / 2; lo = mid - minSpan / 2; hi = mid + minSpan / 2; }
  const limit = REF_ZOOM * (hi - lo), curve = [lo, hi];
  const away = (v) => Math.max(curve[0] - v, v - curve[1], 0);
  const joins = new Set();
  for (const [name, v] of [...refs].sort((a, b) => away(a[1]) - away(b[1]))) {
    if (Math.max(hi, v) - Math.min(lo, v) <= limit) { joins.add(name); lo = Math.min(lo, v); hi = Math.max(hi, v); }
  }
  const ticks = niceTicks(lo, hi, 4);
  return { ticks, shown: refs.filter(([, v]) => v >= ticks.lo && v <= ticks.hi),
           above: refs.filter(([, v]) => v > ticks.hi), below: refs.filter(([, v]) => v < ticks.lo) };
}

// Draws one learning curve (points: [[x, y], ...], nulls already skipped), with an optional band ([[x, half]]:
// y ± half at the points' steps) and reference lines ({name: y}): those within yAxis's range as dashed lines,
// the others as arrows with their value at the top or bottom edge. Returns the axis and the points drawn.
function drawChart(canvas, points, color, band = [], refs = {}) {
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
    return { points: 0 };
  }

  const half = new Map(band);
  const bandPts = points.filter(([x]) => half.has(x)).map(([x, y]) => [x, y - half.get(x), y + half.get(x)]);
  const refList = Object.entries(refs).filter(([, v]) => Number.isFinite(v));
  const refColor = new Map(refList.map(([name], i) => [name, REF_COLORS[i % REF_COLORS.length]]));
  let xmin = Infinity, xmax = -Infinity;
  for (const [x] of points) { if (x < xmin) xmin = x; if (x > xmax) xmax = x; }
  const axis = yAxis(points, bandPts, refList), yt = axis.ticks;
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

  // the CI band, then the reference lines within the axis (dashed, labelled at the right)
  if (bandPts.length > 1) {
    ctx.beginPath();
    bandPts.forEach(([x, , hi], i) => (i ? ctx.lineTo(sx(x), sy(hi)) : ctx.moveTo(sx(x), sy(hi))));
    for (const [x, lo] of [...bandPts].reverse()) ctx.lineTo(sx(x), sy(lo));
    ctx.closePath();
    ctx.globalAlpha = 0.18;
    ctx.fillStyle = color;
    ctx.fill();
    ctx.globalAlpha = 1;
  }
  ctx.setLineDash([4, 3]);
  ctx.textAlign = "right";
  ctx.textBaseline = "bottom";
  for (const [name, v] of axis.shown) {
    const y = Math.round(sy(v)) + 0.5, c = refColor.get(name);
    ctx.strokeStyle = c; ctx.lineWidth = 1;
    ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + pw, y); ctx.stroke();
    ctx.fillStyle = c; ctx.fillText(name, left + pw - 2, y - 1);
  }
  ctx.setLineDash([]);
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
  // over it, the references beyond the axis, where a rising curve leaves room and no reference line has its
  // label: "▲ scripted 174" down from the top left corner, highest first; "▼ …" up from the bottom right, lowest
  ctx.textBaseline = "middle";
  const edge = (list, x0, y0, dy, arrow) => [...list].sort((a, b) => dy * (b[1] - a[1])).forEach(([name, v], i) => {
    const text = `${arrow} ${name} ${fmtValue(v)}`, tw = ctx.measureText(text).width, y = y0 + dy * i * 14;
    const x = dy > 0 ? x0 : x0 - tw;
    ctx.fillStyle = "rgba(255, 255, 255, 0.85)";
    ctx.fillRect(x - 2, y - 7, tw + 4, 14);
    ctx.fillStyle = refColor.get(name);
    ctx.textAlign = "left";
    ctx.fillText(text, x, y);
  });
  edge(axis.above, left + 6, top + 7, 1, "▲");
  edge(axis.below, left + pw - 4, top + ph - 7, -1, "▼");
  return { points: points.length, lo: yt.lo, hi: yt.hi, offscale: axis.above.length + axis.below.length };
}

function redrawCharts() {
  for (const m of METRICS) {
    const greedy = m === "eval_return";
    const band = greedy ? state.series[BAND] || [] : [];
    const refs = greedy ? references(state.job) : {};
    const drawn = drawChart($(`chart-${m}`), state.series[m] || [], COLORS[m], band, refs);
    window.convoy.points[m] = drawn.points;
    if (greedy) {
      window.convoy.greedy = { band: band.length, references: Object.keys(refs).length, offscale: drawn.offscale ?? 0,
                               axis: [drawn.lo, drawn.hi] };
    }
  }
  window.convoy.selected = state.selected;
}

// The reference returns a finished job was scored beside (random, and on the treadmill its drivers and bounds).
function references(job) {
  const refs = (job && job.final && job.final.references) || {};
  return Object.fromEntries(Object.entries(refs).filter(([, v]) => Array.isArray(v) && Number.isFinite(v[0])).map(([k, v]) => [k, v[0]]));
}

// ---------------------------------------------------------------- jobs table

function cell(text, cls) {
  const td = document.createElement("td");
  if (cls) td.className = cls;
  if (text instanceof Node) td.appendChild(text); else td.textContent = text;
  return td;
}

// The one row of an empty table: what would be there, across all its columns.
function emptyRow(text, columns) {
  const tr = document.createElement("tr");
  tr.className = "empty";
  const td = cell(text);
  td.colSpan = columns;
  tr.appendChild(td);
  return tr;
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
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = state.compare.has(job.id);
    box.title = "overlay this job's greedy curve on the sweep chart";
    box.addEventListener("click", (e) => { e.stopPropagation(); toggleCompare(job.id, box.checked); });
    tr.append(
      cell(box),
      cell(job.id, "id"),
      cell(`${job.algo} on ${job.env}`),
      cell(badge(job)),
      cell(progressCell(job)),
      cell(`${job.actors_alive} / ${job.actors}`, "num"),
      cell(fmtValue(p.eval_return), "num"),
      cell(fmtCount(p.env_steps_per_s), "num"),
    );
    tr.addEventListener("click", () => selectJob(job.id));
    return tr;
  });
  if (rows.length === 0) rows.push(emptyRow("no jobs yet", 8));
  tbody.replaceChildren(...rows);
  $("jobs-updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
}

async function refreshJobs() {
  try {
    const data = await api("jobs");
    state.jobs = (data.jobs || []).slice().sort((a, b) => (b.created_at ?? 0) - (a.created_at ?? 0));
    state.jobsShown = true;
    setOffline(false);
    if (state.selected == null && state.jobs.length && state.openFirstJob) {
      const running = state.jobs.find((j) => j.state === "running");
      selectJob((running || state.jobs[0]).id);
    } else {
      const sel = state.jobs.find((j) => j.id === state.selected);
      if (sel) updatePanel(sel);
    }
    renderJobs();
    revealSweep();
  } catch (err) {
    setOffline(true, err);
  }
}

// ---------------------------------------------------------------- selected job panel

function updatePanel(job) {
  if (!job || job.id !== state.selected) return;
  const wasTerminal = state.job && TERMINAL.has(state.job.state);
  const hadRefs = Object.keys(references(state.job)).length;
  state.job = job;
  if (Object.keys(references(job)).length !== hadRefs) redrawCharts(); // a finished job's references arrived
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
  $("resume-btn").disabled = !TERMINAL.has(job.state);
  $("delete-btn").disabled = false;
  $("eval-btn").disabled = !job.last_checkpoint;
  if (job.error) errEl.textContent = `${job.error}\n→ read the process log below; Resume continues from the last checkpoint.`;
  const final = job.final;
  $("job-final").hidden = !final;
  if (final) {
    const refs = Object.entries(final.references || {}).map(([k, v]) => `${k} ${fmtValue(v && v[0])}`).join(", ");
    $("job-final").textContent = `final greedy return ${fmtValue(final.eval_return)} ± ${fmtValue(final.eval_ci95)}` +
      (final.best_eval_return != null ? ` (best ${fmtValue(final.best_eval_return)} at ${fmtCount(final.best_eval_step)})` : "") +
      (refs ? `; ${refs}` : "");
  }
  if (job.last_checkpoint !== state.checkpointShown) {
    state.checkpointShown = job.last_checkpoint;
    refreshDownloads(job);
  }
}

// What the download row says for a job with no checkpoint file of its own: a population job's checkpoints are its
// seeds' (each in its seed-N folder, downloaded from that seed's job); a job that ended without one never had one.
function noCheckpointText(job) {
  if ((job.members || []).length) return `each seed's checkpoints are on its own job (${job.members.length}): `;
  if (TERMINAL.has(job.state)) return `no checkpoint: the job was ${job.state} before its first`;
  return "no checkpoint yet";
}

async function refreshDownloads(job) {
  const id = job.id;
  try {
    const data = await api(`${jobPath(id)}/checkpoints`);
    if (id !== state.selected) return;
    const links = (data.checkpoints || []).map((c) => {
      const a = document.createElement("a");
      a.href = `${jobPath(id)}/checkpoints/${encodeURIComponent(c.name)}`;
      a.download = `${id}-${c.name}`;
      a.textContent = `${c.name} (${fmtBytes(c.bytes)})`;
      return a;
    });
    if (!links.length) {
      links.push(document.createTextNode(noCheckpointText(job)));
      for (const member of job.members || []) {  // a population's seeds: select one to download its checkpoints
        const a = document.createElement("a");
        a.href = `#job=${encodeURIComponent(member)}`;
        a.textContent = member;
        a.addEventListener("click", (ev) => { ev.preventDefault(); selectJob(member); });
        links.push(a);
      }
    }
    $("job-downloads").replaceChildren(...links);
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
  }
}

async function refreshLogs() {
  const id = state.selected;
  if (id == null || !$("logs-box").open) return;
  try {
    const data = await api(`${jobPath(id)}/logs?lines=200`);
    if (id !== state.selected) return;
    const pre = $("job-logs");
    const atBottom = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
    pre.textContent = (data.lines || []).join("\n") || "(nothing logged yet)";
    if (atBottom) pre.scrollTop = pre.scrollHeight;
    window.convoy.logs = (data.lines || []).length;
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
  }
}

function resetPanel() {
  state.checkpointShown = undefined;
  $("job-downloads").textContent = "–";
  $("job-logs").textContent = "–";
  $("eval-status").textContent = "";
  state.series = Object.fromEntries([...METRICS, BAND].map((m) => [m, []]));
  state.lastStep = null;
  state.metricsDrained = false;
  state.requestedShown = null;
  state.job = null;
}

// A link to what is shown: #job=ID (and &sweep=ID) in the address, read back when the page opens.
function writeHash() {
  const parts = [];
  if (state.selected) parts.push(`job=${encodeURIComponent(state.selected)}`);
  if (state.sweep) parts.push(`sweep=${encodeURIComponent(state.sweep)}`);
  history.replaceState(null, "", parts.length ? `#${parts.join("&")}` : location.pathname + location.search);
}

// What a link shows: #job=ID opens that job; #sweep=ID alone shows that sweep's chart (scrolled into view) and
// opens no job; both: the job, with the sweep selected below it.
function linkTarget(hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  const job = params.get("job") || null, sweep = params.get("sweep") || null;
  return { job, sweep, showSweep: sweep != null && job == null };
}

function readHash() {
  const link = linkTarget(location.hash);
  if (link.showSweep) {
    state.openFirstJob = false;
    state.revealSweep = link.sweep;
  }
  if (link.sweep) selectSweep(link.sweep);
  if (link.job) selectJob(link.job);
}

// Scrolls a linked sweep's chart into view once it is drawn and the jobs table above it has its rows (the page is
// laid out): once per link.
function revealSweep() {
  if (state.revealSweep == null || state.revealSweep !== state.sweep || !state.summary || !state.jobsShown) return;
  state.revealSweep = null;
  $("sweeps-card").scrollIntoView({ block: "start" });   // its heading and table, then its chart if below them
  $("sweep-figure").scrollIntoView({ block: "nearest" });
  $("sweeps-card").focus({ preventScroll: true });
  window.convoy.revealed = state.sweep;
}

function selectJob(id) {
  if (id === state.selected) return;
  state.selected = id;
  writeHash();
  state.gen += 1;
  resetPanel();
  const job = state.jobs.find((j) => j.id === id);
  if (job) updatePanel(job);
  else $("job-title").textContent = id;
  renderJobs();
  redrawCharts();
  api(jobPath(id)).then(updatePanel).catch((err) => showMessage(`Could not load job ${id}: ${err.message}`));
  pollMetrics();
  refreshLogs();
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
      for (const m of [...METRICS, BAND]) {
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

async function resumeJob() {
  const id = state.selected;
  if (id == null) return;
  try {
    const job = await api(`${jobPath(id)}/resume`, { method: "POST", body: {}, auth: true });
    replaceJob(job);
    showMessage(`Job ${id}: resumed from its last checkpoint (${job.state}).`, "info");
  } catch (err) {
    showMessage(`Resume failed — ${err.message}`);
  }
}

async function deleteJob() {
  const id = state.selected;
  if (id == null || !window.confirm(`Delete job ${id} with its history, metrics and files?`)) return;
  try {
    await api(jobPath(id), { method: "DELETE", auth: true });
    state.jobs = state.jobs.filter((j) => j.id !== id);
    state.compare.delete(id);
    state.selected = null;
    state.gen += 1;
    resetPanel();
    $("job-title").textContent = "no job selected";
    $("job-state").textContent = "";
    renderJobs();
    redrawCharts();
    showMessage(`Deleted job ${id}.`, "info");
  } catch (err) {
    showMessage(`Delete failed — ${err.message}`);
  }
}

async function evaluateJob() {
  const id = state.selected;
  if (id == null) return;
  const body = {
    episodes: Number($("eval-episodes").value),
    messages: $("eval-messages").value,
    checkpoint: $("eval-checkpoint").value,
  };
  try {
    const ev = await api(`${jobPath(id)}/evaluate`, { method: "POST", body, auth: true });
    state.evaluation = [id, ev.id];
    $("eval-status").textContent = `evaluation ${ev.id}: running ${body.episodes} episodes…`;
  } catch (err) {
    showMessage(`Evaluate failed — ${err.message}`);
  }
}

async function pollEvaluation() {
  if (!state.evaluation) return;
  const [id, evalId] = state.evaluation;
  try {
    const ev = await api(`${jobPath(id)}/evaluations/${evalId}`);
    if (ev.state === "running") return;
    state.evaluation = null;
    window.convoy.evaluation = ev;
    const text = ev.state === "completed"
      ? `evaluation ${ev.id}: ${fmtValue(ev.result.mean_return)} ± ${fmtValue(ev.result.ci95)} over ${ev.result.episodes} episodes ` +
        `(${ev.result.messages}; random ${fmtValue(ev.result.random_return)})`
      : `evaluation ${ev.id} failed: ${ev.error}`;
    if (id === state.selected) $("eval-status").textContent = text;
    showMessage(`Job ${id}: ${text}`, ev.state === "completed" ? "info" : "error");
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
  }
}

// ---------------------------------------------------------------- sweeps and comparisons

const PALETTE = ["#1d3f8f", "#d9822b", "#2e9d5b", "#c93c3c", "#8b5cf6", "#0f8b8d", "#b5651d", "#6b7785"];

function renderSweeps() {
  const rows = state.sweeps.map((sw) => {
    const tr = document.createElement("tr");
    tr.dataset.sweepId = sw.id;
    if (sw.id === state.sweep) tr.className = "selected";
    const counts = Object.entries(sw.states).map(([k, n]) => `${n} ${k}`).join(", ");
    const done = sw.jobs.reduce((a, m) => a + Math.min(m.env_steps, m.steps), 0);
    const total = sw.jobs.reduce((a, m) => a + m.steps, 0);
    const progress = progressCell({ state: sw.state, progress: { fraction: sw.fraction, env_steps: done }, steps: total });
    tr.append(cell(sw.id, "id"), cell(badge(sw)), cell(progress), cell(counts));
    tr.addEventListener("click", () => selectSweep(sw.id));
    return tr;
  });
  if (rows.length === 0) rows.push(emptyRow("no sweeps yet (convoy sweep submit FILE)", 4));
  $("sweeps").replaceChildren(...rows);
}

async function refreshSweeps() {
  try {
    state.sweeps = ((await api("sweeps")).sweeps || []).slice().sort((a, b) => b.created_at - a.created_at);
    renderSweeps();
    if (state.sweep) await refreshSummary();
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
  }
}

async function refreshSummary() {
  const id = state.sweep;
  try {
    const summary = await api(`sweeps/${encodeURIComponent(id)}/summary`);
    if (id !== state.sweep) return;
    state.summary = summary;
    drawSweep();
  } catch (err) {
    if (!(err instanceof ApiError)) setOffline(true, err);
    else if (id === state.revealSweep) {  // a link to a sweep that is not there
      state.revealSweep = null;
      showMessage(`Could not load sweep ${id}: ${err.message}`);
    }
  }
}

function selectSweep(id) {
  state.sweep = id;
  writeHash();
  state.summary = null;
  renderSweeps();
  refreshSummary();
}

async function toggleCompare(id, on) {
  if (on) {
    state.compare.add(id);
    try {
      const data = await api(`${jobPath(id)}/metrics?names=eval_return`);
      state.compareSeries[id] = (data.rows || []).filter((r) => Number.isFinite(r.eval_return)).map((r) => [r.env_steps, r.eval_return]);
    } catch (err) {
      showMessage(`Could not load job ${id}'s curve: ${err.message}`);
    }
  } else {
    state.compare.delete(id);
    delete state.compareSeries[id];
  }
  drawSweep();
}

// A summary group's curve as [x, mean, low, high]: its CI band within the returns its env allows (g.bounds: a
// success rate's [0, 1]; a t-interval over few seeds runs past them, where no return lies).
function groupBand(g) {
  const [lo, hi] = g.bounds || [-Infinity, Infinity];
  return g.curve.env_steps.map((x, j) => [x, g.curve.mean[j], g.curve.ci95[j] ?? 0]).filter((p) => p[1] != null)
    .map(([x, m, c]) => [x, m, Math.max(lo, m - c), Math.min(hi, m + c)]);
}

// The sweep chart: each group's mean curve with its CI band, and every ticked job's greedy curve dashed.
function drawSweep() {
  const canvas = $("chart-sweep");
  const groups = [];
  for (const [i, g] of ((state.summary && state.summary.groups) || []).entries()) {
    const pts = groupBand(g);
    if (pts.length) groups.push({ label: `${g.group} (n=${Math.max(...g.curve.n)})`, pts, color: PALETTE[i % PALETTE.length] });
  }
  const overlays = [...state.compare].filter((id) => (state.compareSeries[id] || []).length)
    .map((id, i) => ({ label: id, pts: state.compareSeries[id], color: PALETTE[(groups.length + i) % PALETTE.length] }));
  $("sweep-figure").hidden = !(state.sweep || overlays.length);
  const dpr = window.devicePixelRatio || 1;
  const w = canvas.clientWidth || 600, h = canvas.clientHeight || 260;
  canvas.width = Math.round(w * dpr);
  canvas.height = Math.round(h * dpr);
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, w, h);
  ctx.font = "11px system-ui, -apple-system, 'Segoe UI', Roboto, sans-serif";
  let bands = 0;
  const all = [...groups.flatMap((g) => g.pts.flatMap(([x, , lo, hi]) => [[x, lo], [x, hi]])), ...overlays.flatMap((o) => o.pts)];
  if (all.length === 0) {
    ctx.fillStyle = "#9aa5b1";
    ctx.textAlign = "center";
    ctx.fillText("no curve yet: select a sweep, or tick jobs in the compare column", w / 2, h / 2);
  } else {
    const xs = all.map((p) => p[0]), ys = all.map((p) => p[1]);
    const yt = niceTicks(Math.min(...ys), Math.max(...ys), 5), xt = niceTicks(Math.min(...xs), Math.max(...xs), Math.max(2, Math.floor(w / 110)));
    const left = 46, right = 12, top = 8, bottom = 22, pw = w - left - right, ph = h - top - bottom;
    const sx = (x) => left + ((x - xt.lo) / (xt.hi - xt.lo)) * pw;
    const sy = (y) => top + ph - ((y - yt.lo) / (yt.hi - yt.lo)) * ph;
    ctx.strokeStyle = "#edf0f4"; ctx.fillStyle = "#6b7785"; ctx.textAlign = "right"; ctx.textBaseline = "middle";
    for (const v of yt.ticks) { const y = sy(v); ctx.beginPath(); ctx.moveTo(left, y); ctx.lineTo(left + pw, y); ctx.stroke(); ctx.fillText(tickLabel(v, yt.step), left - 6, y); }
    ctx.textAlign = "center"; ctx.textBaseline = "top";
    for (const v of xt.ticks) ctx.fillText(tickLabel(v, xt.step), sx(v), top + ph + 6);
    for (const g of groups) {
      ctx.beginPath();
      g.pts.forEach(([x, , , hi], i) => (i ? ctx.lineTo(sx(x), sy(hi)) : ctx.moveTo(sx(x), sy(hi))));
      [...g.pts].reverse().forEach(([x, , lo]) => ctx.lineTo(sx(x), sy(lo)));
      ctx.closePath();
      ctx.globalAlpha = 0.18; ctx.fillStyle = g.color; ctx.fill(); ctx.globalAlpha = 1;
      bands += 1;
      ctx.beginPath();
      g.pts.forEach(([x, m], i) => (i ? ctx.lineTo(sx(x), sy(m)) : ctx.moveTo(sx(x), sy(m))));
      ctx.lineWidth = 2; ctx.strokeStyle = g.color; ctx.setLineDash([]); ctx.stroke();
    }
    for (const o of overlays) {
      ctx.beginPath();
      o.pts.forEach(([x, y], i) => (i ? ctx.lineTo(sx(x), sy(y)) : ctx.moveTo(sx(x), sy(y))));
      ctx.lineWidth = 1.5; ctx.strokeStyle = o.color; ctx.setLineDash([5, 4]); ctx.stroke(); ctx.setLineDash([]);
    }
  }
  const legend = [...groups, ...overlays].map((s, i) => {
    const span = document.createElement("span");
    const sw = document.createElement("span");
    sw.className = "swatch";
    sw.style.background = s.color;
    if (i >= groups.length) sw.style.background = `repeating-linear-gradient(90deg, ${s.color} 0 5px, transparent 5px 8px)`;
    span.append(sw, document.createTextNode(s.label));
    return span;
  });
  $("sweep-legend").replaceChildren(...legend);
  $("sweep-caption").textContent = state.sweep
    ? `sweep ${state.sweep}: mean greedy return over seeds, shaded 95 % CI` + (overlays.length ? `; ${overlays.length} job(s) dashed` : "")
    : "greedy return by group (select a sweep, or tick jobs to compare)";
  window.convoy.sweep = { id: state.sweep, groups: groups.length, bands, overlays: overlays.length };
  revealSweep();
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
  $("resume-btn").addEventListener("click", resumeJob);
  $("delete-btn").addEventListener("click", deleteJob);
  $("eval-btn").addEventListener("click", evaluateJob);
  $("logs-box").addEventListener("toggle", refreshLogs);
  for (const id of ["resume-btn", "delete-btn", "eval-btn"]) $(id).disabled = true;
  $("actors-input").addEventListener("keydown", (e) => { if (e.key === "Enter") scaleJob(); });
  $("scale-btn").disabled = true;
  $("stop-btn").disabled = true;
  resetPanel();
  redrawCharts();
  let resizeTimer = null;
  window.addEventListener("resize", () => { clearTimeout(resizeTimer); resizeTimer = setTimeout(() => { redrawCharts(); drawSweep(); }, 100); });
  refreshJobs();
  refreshSweeps();
  drawSweep();
  readHash();
  window.addEventListener("hashchange", readHash);  // a link followed on this page, or an address edited
  setInterval(refreshJobs, JOBS_EVERY_MS);
  setInterval(pollMetrics, METRICS_EVERY_MS);
  setInterval(refreshSweeps, SWEEPS_EVERY_MS);
  setInterval(refreshLogs, LOGS_EVERY_MS);
  setInterval(pollEvaluation, METRICS_EVERY_MS);
}

if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", boot);
else boot();
