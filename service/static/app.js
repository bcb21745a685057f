// The compabs dashboard: the job list (polled), live per-stage progress (server-sent events), results, a submit
// form. Plain DOM; every string that comes from the server is set with textContent or as an attribute value,
// never parsed as HTML.
"use strict";

const STAGES = ["plan", "lipschitz", "subsystems", "interconnection", "audit", "synthesis", "closed_loop"];
const TERMINAL = new Set(["succeeded", "failed", "cancelled"]);
const POLL_MS = 3000;
// Chromium allows six HTTP/1.1 connections per host and every EventSource holds one: keep some for fetches.
// Active jobs beyond this many are updated by the poll only.
const MAX_STREAMS = 3;
const TOKEN_KEY = "compabs.token";

const jobsEl = document.getElementById("jobs");
const noticeEl = document.getElementById("notice");
const tokenEl = document.getElementById("token");
const specEl = document.getElementById("spec");
const submitMsgEl = document.getElementById("submit-message");
const jobTemplate = document.getElementById("job-template");
const stageTemplate = document.getElementById("stage-template");

const views = new Map();    // job id -> {el, job}
const streams = new Map();  // job id -> EventSource
let pollTimer = null;

// ------------------------------------------------------------------------------------------------ token, requests
function token() {
  return localStorage.getItem(TOKEN_KEY) || "";
}

// A URL for EventSource, <img> and links, which cannot send headers: the token goes in the query.
function withToken(path) {
  const t = token();
  if (!t) return path;
  return path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(t);
}

// The API's JSON with exact integers: JSON.parse makes every number a double, which rounds integers beyond 2^53
// (13422659310152401 abstract states would show as 13,422,659,310,152,400). The reviver reads such an integer
// again from its source text (the reviver's context.source, in Chromium since 114) as a BigInt.
function parseJson(text) {
  return JSON.parse(text, (key, value, context) => {
    if (typeof value === "number" && !Number.isSafeInteger(value) && context && typeof context.source === "string" &&
        /^-?[0-9]+$/.test(context.source)) {
      return BigInt(context.source);
    }
    return value;
  });
}

class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

// The message of an error answer: FastAPI's {"detail": "..."} or its validation list [{loc, msg}, ...].
function detailOf(body, fallback) {
  const detail = body && body.detail;
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => {
      const loc = Array.isArray(d.loc) ? d.loc.filter((p) => p !== "body").join(".") : "";
      return (loc ? loc + ": " : "") + (d.msg || JSON.stringify(d));
    }).join("; ");
  }
  return fallback;
}

async function api(path, options = {}) {
  const headers = new Headers(options.headers || {});
  const t = token();
  if (t) headers.set("Authorization", "Bearer " + t);
  const response = await fetch(path, {...options, headers});
  let body = null;
  const type = response.headers.get("Content-Type") || "";
  if (type.includes("json")) {
    try { body = parseJson(await response.text()); } catch (e) { body = null; }
  }
  if (response.status === 401 || response.status === 403) {
    showAuthNotice(response.status, detailOf(body, response.statusText));
    throw new ApiError(response.status, detailOf(body, "unauthorized"));
  }
  if (!response.ok) {
    throw new ApiError(response.status, detailOf(body, `${response.status} ${response.statusText}`));
  }
  clearAuthNotice();
  return body;
}

function showAuthNotice(status, detail) {
  const what = token() ? "the API token is not accepted" : "the API needs a token";
  noticeEl.textContent = `${status} Unauthorized: ${what}. Enter it in the token field above.` +
    (detail ? ` (server: ${detail})` : "");
  noticeEl.dataset.status = String(status);
  noticeEl.hidden = false;
}

function clearAuthNotice() {
  if (noticeEl.dataset.status === "401" || noticeEl.dataset.status === "403") {
    noticeEl.hidden = true;
    noticeEl.textContent = "";
    delete noticeEl.dataset.status;
  }
}

function showNotice(text) {
  noticeEl.textContent = text;
  noticeEl.dataset.status = "error";
  noticeEl.hidden = false;
}

// ------------------------------------------------------------------------------------------------ formatting
function formatNumber(v) {
  if (typeof v === "bigint") return v.toLocaleString("en-US");  // exact, grouped
  if (typeof v !== "number") return String(v);
  if (Number.isInteger(v)) return v.toLocaleString("en-US");
  return Math.abs(v) >= 1e6 || (v !== 0 && Math.abs(v) < 1e-3) ? v.toExponential(3) : String(+v.toFixed(3));
}

function formatTime(iso) {
  if (!iso) return "";
  const d = new Date(iso);
  return isNaN(d) ? String(iso) : d.toLocaleString();
}

function duration(job) {
  if (!job.started_at) return "";
  const end = job.finished_at ? new Date(job.finished_at) : new Date();
  const s = (end - new Date(job.started_at)) / 1000;
  return isNaN(s) ? "" : `${s.toFixed(1)} s`;
}

// Only http(s) links from the server become hrefs.
function safeHttpUrl(url) {
  try {
    const u = new URL(url, location.href);
    return u.protocol === "http:" || u.protocol === "https:" ? u.href : null;
  } catch (e) {
    return null;
  }
}

// Scalars of a nested object as [dotted key, value] pairs.
function flatten(obj, prefix = "", out = []) {
  for (const [k, v] of Object.entries(obj || {})) {
    const key = prefix ? `${prefix}.${k}` : k;
    if (v !== null && typeof v === "object" && !Array.isArray(v)) flatten(v, key, out);
    else if (["number", "bigint", "string", "boolean"].includes(typeof v)) out.push([key, v]);  // null: not known, not shown
  }
  return out;
}

// The key counts first, then anything else the summary carries.
const SUMMARY_ORDER = ["abstract_states", "region_states", "domain_states", "audit_transitions", "audit_violations",
  "closed_loop_runs", "closed_loop_violations"];

function summaryRows(summary) {
  const rows = flatten(summary);
  const rank = (k) => {
    const i = SUMMARY_ORDER.indexOf(k);
    return i < 0 ? SUMMARY_ORDER.length : i;
  };
  return rows.sort((a, b) => rank(a[0]) - rank(b[0]));
}

// ------------------------------------------------------------------------------------------------ rendering
function stageRow(view, name) {
  let row = view.el.querySelector(`.stage[data-stage="${CSS.escape(name)}"]`);
  if (!row) {
    row = stageTemplate.content.firstElementChild.cloneNode(true);
    row.dataset.stage = name;
    row.querySelector(".stage-name").textContent = name.replace("_", " ");
    row.querySelector("progress").setAttribute("aria-label", `${name} progress`);
    view.el.querySelector(".stages").appendChild(row);
  }
  return row;
}

function setStage(view, p) {
  const row = stageRow(view, p.stage);
  const done = Number(p.done) || 0;  // for the fraction; the counts shown are p.done and p.total as parsed
  const total = Number(p.total) || 0;
  let fraction = typeof p.fraction === "number" ? p.fraction : total > 0 ? done / total : 0;
  if (total === 0 && view.job && view.job.status === "succeeded") fraction = 1;  // a stage with nothing to do
  fraction = Math.min(1, Math.max(0, fraction));
  const pct = Math.floor(fraction * 100 + 1e-9);  // floor: "100%" only when the stage is complete
  row.querySelector("progress").value = pct;
  row.querySelector(".pct").textContent = `${pct}%`;
  row.querySelector(".stage-message").textContent =
    (total > 0 ? `${formatNumber(p.done)} / ${formatNumber(p.total)}` : "") + (p.message ? `  ${p.message}` : "");
  row.dataset.done = String(p.done ?? 0);
  row.dataset.total = String(p.total ?? 0);
  row.classList.toggle("complete", pct === 100);
}

function createView(job) {
  const el = jobTemplate.content.firstElementChild.cloneNode(true);
  el.dataset.jobId = job.id;
  const view = {el, job: null, figures: new Set()};
  el.querySelector(".cancel").addEventListener("click", () => cancelJob(view));
  for (const name of STAGES) stageRow(view, name);
  return view;
}

function render(view, job) {
  view.job = job;
  const el = view.el;
  el.dataset.status = job.status;
  el.querySelector(".job-name").textContent = job.name || "(unnamed)";
  el.querySelector(".job-id").textContent = job.id;
  const status = el.querySelector(".status");
  status.textContent = job.status;
  status.dataset.status = job.status;
  renderTimes(view);

  const dash = el.querySelector(".dask-dashboard");
  const dashUrl = job.dask_dashboard ? safeHttpUrl(job.dask_dashboard) : null;
  dash.hidden = !dashUrl;
  if (dashUrl) dash.href = dashUrl;

  el.querySelector(".cancel").hidden = TERMINAL.has(job.status);

  const err = el.querySelector(".error");
  err.hidden = !job.error;
  err.textContent = job.error || "";

  for (const s of job.stages || []) setStage(view, s);

  const results = el.querySelector(".results");
  const succeeded = job.status === "succeeded";
  results.hidden = !succeeded;
  if (succeeded) renderResults(view, job);
}

function renderTimes(view) {
  const job = view.job;
  const times = [`created ${formatTime(job.created_at)}`];
  const d = duration(job);
  if (d) times.push(job.finished_at ? `ran ${d}` : `running ${d}`);
  view.el.querySelector(".times").textContent = times.join(", ");
}

function renderResults(view, job) {
  const el = view.el;
  const base = `/jobs/${encodeURIComponent(job.id)}`;
  el.querySelector(".report-link").href = withToken(`${base}/report`);
  el.querySelector(".controller-link").href = withToken(`${base}/controller`);
  const dl = el.querySelector(".summary");
  dl.replaceChildren();
  for (const [key, value] of summaryRows(job.summary)) {
    const dt = document.createElement("dt");
    dt.textContent = key.replaceAll("_", " ");
    const dd = document.createElement("dd");
    dd.textContent = formatNumber(value);
    dd.dataset.key = key;
    dl.append(dt, dd);
  }
  const figures = el.querySelector(".figures");
  for (const name of job.figures || []) {
    if (view.figures.has(name)) continue;  // added once: a re-render must not reload the image
    view.figures.add(name);
    const fig = document.createElement("figure");
    const link = document.createElement("a");
    const img = document.createElement("img");
    const src = withToken(`${base}/figures/${encodeURIComponent(name)}`);
    link.href = src;
    link.target = "_blank";
    link.rel = "noopener";
    img.src = src;
    img.alt = `${name} of job ${job.id}`;
    img.loading = "lazy";
    img.dataset.figure = name;
    link.appendChild(img);
    const caption = document.createElement("figcaption");
    caption.textContent = name;
    fig.append(link, caption);
    figures.appendChild(fig);
  }
}

function updateJob(job) {
  let view = views.get(job.id);
  if (!view) {
    view = createView(job);
    views.set(job.id, view);
  }
  render(view, job);
  return view;
}

function placeJobs() {
  const ordered = [...views.values()].sort((a, b) =>
    String(b.job.created_at || "").localeCompare(String(a.job.created_at || "")));
  ordered.forEach((view, i) => {
    if (jobsEl.children[i] !== view.el) jobsEl.insertBefore(view.el, jobsEl.children[i] || null);
  });
  document.getElementById("jobs-empty").hidden = views.size > 0;
}

// ------------------------------------------------------------------------------------------------ live updates
function openStream(id) {
  if (streams.has(id) || streams.size >= MAX_STREAMS) return;
  const source = new EventSource(withToken(`/jobs/${encodeURIComponent(id)}/events`));
  streams.set(id, source);
  source.addEventListener("progress", (ev) => {
    const view = views.get(id);
    if (!view) return;
    try {
      setStage(view, parseJson(ev.data));
      renderTimes(view);
    } catch (e) {
      console.warn("bad progress event", e);
    }
  });
  source.addEventListener("status", (ev) => {
    let job;
    try {
      job = parseJson(ev.data);
    } catch (e) {
      console.warn("bad status event", e);
      return;
    }
    updateJob(job);
    placeJobs();
    if (TERMINAL.has(job.status)) closeStream(id);
  });
  source.onerror = () => {
    // The server closes the stream after a terminal status; an error before that (a restart, a 401) is left
    // to EventSource's own reconnection while the poll keeps the job current. A closed source is dropped so
    // that the next poll can open a new one.
    if (source.readyState === EventSource.CLOSED) closeStream(id);
  };
}

function closeStream(id) {
  const source = streams.get(id);
  if (source) source.close();
  streams.delete(id);
}

function closeAllStreams() {
  for (const id of [...streams.keys()]) closeStream(id);
}

async function refresh() {
  let body;
  try {
    body = await api("/jobs");
  } catch (e) {
    if (!(e instanceof ApiError && (e.status === 401 || e.status === 403))) {
      showNotice(`Cannot list the jobs: ${e.message}`);
    }
    return;
  }
  if (noticeEl.dataset.status === "error") {
    noticeEl.hidden = true;
    delete noticeEl.dataset.status;
  }
  const jobs = (body && body.jobs) || [];
  const seen = new Set();
  for (const job of jobs) {
    seen.add(job.id);
    // A streamed job's progress comes from its stream, which is ahead of the poll: only take its status when the
    // poll knows more (e.g. the stream missed the end).
    const view = views.get(job.id);
    if (view && streams.has(job.id) && !TERMINAL.has(job.status)) continue;
    updateJob(job);
  }
  for (const [id, view] of views) {
    if (!seen.has(id)) {
      closeStream(id);
      view.el.remove();
      views.delete(id);
    }
  }
  placeJobs();
  for (const job of jobs) {
    if (TERMINAL.has(job.status)) closeStream(job.id);
    else openStream(job.id);
  }
  document.getElementById("jobs-updated").textContent = `updated ${new Date().toLocaleTimeString()}`;
}

async function poll() {
  clearTimeout(pollTimer);
  try {
    await refresh();
  } finally {
    pollTimer = setTimeout(poll, POLL_MS);
  }
}

// ------------------------------------------------------------------------------------------------ actions
async function cancelJob(view) {
  const button = view.el.querySelector(".cancel");
  button.disabled = true;
  try {
    const job = await api(`/jobs/${encodeURIComponent(view.job.id)}`, {method: "DELETE"});
    if (job && job.id) updateJob(job);
  } catch (e) {
    showNotice(`Cannot cancel job ${view.job.id}: ${e.message}`);
  } finally {
    button.disabled = false;
  }
  poll();
}

async function submitSpec(event) {
  event.preventDefault();
  const button = document.getElementById("submit");
  const text = specEl.value;
  const isJson = /^\s*[{[]/.test(text);
  submitMsgEl.textContent = "Submitting…";
  submitMsgEl.className = "";
  delete submitMsgEl.dataset.submittedId;
  button.disabled = true;
  try {
    const job = await api("/jobs", {
      method: "POST",
      headers: {"Content-Type": isJson ? "application/json" : "application/yaml"},
      body: text,
    });
    submitMsgEl.textContent = `Submitted job ${job.id}.`;
    submitMsgEl.dataset.submittedId = job.id;
    updateJob(job);
    placeJobs();
    if (!TERMINAL.has(job.status)) openStream(job.id);
  } catch (e) {
    submitMsgEl.textContent = `Not submitted: ${e.message}`;
    submitMsgEl.className = "error";
  } finally {
    button.disabled = false;
  }
}

function loadExample() {
  specEl.value = document.getElementById("example-spec").textContent;
}

function applyToken() {
  const value = tokenEl.value.trim();
  if (value) localStorage.setItem(TOKEN_KEY, value);
  else localStorage.removeItem(TOKEN_KEY);
  // Streams and image URLs carry the old token: start over.
  closeAllStreams();
  for (const view of views.values()) view.el.remove();
  views.clear();
  poll();
}

// ------------------------------------------------------------------------------------------------ start
// A link may carry the token (/?token=...): keep it like a typed one and take it out of the address bar.
const params = new URLSearchParams(location.search);
if (params.has("token")) {
  localStorage.setItem(TOKEN_KEY, params.get("token"));
  params.delete("token");
  const query = params.toString();
  history.replaceState(null, "", location.pathname + (query ? "?" + query : "") + location.hash);
}
tokenEl.value = token();
document.getElementById("token-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  applyToken();
});
document.getElementById("submit-form").addEventListener("submit", submitSpec);
document.getElementById("load-example").addEventListener("click", loadExample);
document.getElementById("schema-link").addEventListener("click", (ev) => {
  ev.currentTarget.href = withToken("/schema");
});
if (!specEl.value.trim()) loadExample();
poll();
