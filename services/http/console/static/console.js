// swpc operator console: plain JavaScript, no framework, no build step.
// Live data comes pushed by the service (server-sent events at /events); the page only
// fetches when the operator opens a view or acts.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG_NS = "http://www.w3.org/2000/svg";
// COLORS: the modules' colours, from /console/palette.js (the run plot's, one per module)
const TERMINAL = new Set(["DONE", "FAILED", "ABORTED"]);
const TOKEN_KEY = "swpc-token";

const app = {
  hello: null,          // robot geometry and protocol defaults (the "hello" event)
  current: null,        // status of the run shown live
  live: null,           // last "live" event
  trail: { run: null, chunks: [] },   // [{module, points: [[x, y], ...]}]
  spins: [],
  seenRuns: new Set(),
  startAt: null,        // performance.now() of the last Start, until its run is under way
  startSeen: new Set(), // the runs known at that Start
  // Start -> the new run's first update pushed by the service / its first change of state
  // (the browser test's figures, not the operator's: never shown on the page)
  metrics: { firstLiveUpdateMs: null, firstChangeMs: null, statesSeen: [] },
  resultRun: null,
  checkRun: null,
  commissionRun: null,  // the commissioning shown in its view (the last one started)
  answered: null,       // "<run>:<state>" once the operator's answer to it was accepted
};
window.swpc = app;      // for the browser test (and a curious operator's console)

// ------------------------------------------------------------------ helpers
function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return e;
}
function svg(tag, attrs = {}) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}
const fmt = (x, d = 3) => (x === null || x === undefined || !isFinite(x) ? "–" : x.toFixed(d));
const signed = (x, d) => (x > 0 ? "+" : "") + fmt(x, d);
const wrapDeg = (a) => ((((a + 180) % 360) + 360) % 360) - 180;
const duration = (s) => (s < 60 ? `${s.toFixed(0)} s` :
  `${Math.floor(s / 60)} min ${String(Math.round(s % 60)).padStart(2, "0")} s`);
const colorOf = (module) => COLORS[(module - 1 + COLORS.length) % COLORS.length];
// a run's resource: a calibration's /calibrations/<id>, a check's /checks/<id>, a
// commissioning's /commissions/<id>
const RUN_PATHS = { check: "/checks/", commission: "/commissions/" };
const KIND_NAMES = { check: "Check", commission: "Commissioning" };
const runPath = (st) => (RUN_PATHS[st.kind] || "/calibrations/") + st.id;
const kindName = (st) => KIND_NAMES[st.kind] || "Calibration";

// stop: a request that stops the robot (an abort) is sent at once, with the token if the
// tab has one, never after asking for it (the service takes an abort without it)
async function api(method, path, body, stop = false) {
  const headers = {};
  if (body !== undefined) headers["Content-Type"] = "application/json";
  if (method !== "GET") {
    const token = stop ? sessionStorage.getItem(TOKEN_KEY) : await ensureToken();
    if (!token && !stop) throw new Error("no token given");
    if (token) headers.Authorization = "Bearer " + token;
  }
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (r.status === 401) {
    sessionStorage.removeItem(TOKEN_KEY);
    updateTokenButton();
    throw new Error("the token was refused: enter it again");
  }
  const data = r.headers.get("content-type")?.includes("json") ? await r.json() : null;
  if (!r.ok) {
    const d = data?.detail;
    throw new Error(Array.isArray(d) ? d.map(validationText).join("; ") : d || r.statusText);
  }
  return data;
}

// one of FastAPI's validation errors, naming what it is about: "overrides.protocol.sweep_deg:
// Input should be a valid number" (its loc without the leading "body")
function validationText(e) {
  const loc = (e.loc || []).filter((x, i) => !(i === 0 && x === "body")).join(".");
  return loc ? `${loc}: ${e.msg}` : e.msg;
}

// ------------------------------------------------------------------ dialogs
function tokenDialog(why) {
  const dlg = $("token-dialog");
  $("token-why").textContent = why || "Starting and installing need the service's bearer " +
    "token (aborting never does). It is kept for this browser tab only.";
  $("token-input").value = "";
  return new Promise((resolve) => {
    const done = (value) => { dlg.close(); resolve(value); };
    $("token-form").onsubmit = (ev) => {
      ev.preventDefault();
      const t = $("token-input").value.trim();
      if (t) { sessionStorage.setItem(TOKEN_KEY, t); updateTokenButton(); done(t); }
    };
    $("token-cancel").onclick = () => done(null);
    dlg.oncancel = () => resolve(null);
    dlg.showModal();
    $("token-input").focus();
  });
}
async function ensureToken() {
  return sessionStorage.getItem(TOKEN_KEY) || tokenDialog();
}
function updateTokenButton() {
  $("token-button").textContent = sessionStorage.getItem(TOKEN_KEY) ? "Token set ✓" : "Enter token";
  if (app.stream) connect();  // the stream with the token now (or without it)
}
function confirmDialog(title, text, okLabel) {
  const dlg = $("confirm-dialog");
  $("confirm-title").textContent = title;
  $("confirm-text").textContent = text;
  $("confirm-ok").textContent = okLabel;
  return new Promise((resolve) => {
    dlg.onclose = () => resolve(dlg.returnValue === "ok");
    dlg.returnValue = "cancel";
    dlg.showModal();
    $("confirm-cancel").focus();
  });
}

// ------------------------------------------------------------------ routing
function route() {
  const [view, arg] = (location.hash.slice(1) || "run").split("/");
  const known = ["run", "result", "history", "drift", "check", "files", "foxglove", "drives", "commission"];
  const v = known.includes(view) ? view : "run";
  for (const k of known) $("view-" + k).hidden = k !== v;
  const tab = v === "check" ? "drift" : v;  // a check's verdict belongs with the drift
  for (const a of document.querySelectorAll("nav a")) {
    if (a.dataset.view === tab) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  }
  if (v === "result") showResult(arg || app.resultRun);
  if (v === "check") showCheck(arg || app.checkRun);
  if (v === "drift") showDrift();
  if (v === "history") showHistory();
  if (v === "files") showFiles();
  if (v === "foxglove") showFoxglove(arg || app.resultRun);
  if (v === "drives") showDrives();
  if (v === "commission") showCommission(arg || app.commissionRun);
}

// ------------------------------------------------------------------ start / abort
function fillDefaults(p) {
  $("f-angles").value = p.angles_deg.join(", ");
  $("f-sweep").value = p.sweep_deg;
  $("f-settle").value = p.settle_time;
  $("f-stop").value = p.stop_time;
  $("f-align").value = p.align_time;
  $("f-resteer").value = p.resteer_time;
  $("f-modules").value = p.modules ? p.modules.join(", ") : "";
  $("f-drive").value = p.drive_length;
  $("f-rest").value = p.rest_time;
}
// the numbers typed in a form field, or an error naming the field and what is not a number
function numbersOf(id) {
  const words = $(id).value.split(/[,\s]+/).filter(Boolean);
  const bad = words.find((w) => !Number.isFinite(Number(w)));
  if (bad !== undefined) {
    const label = $(id).closest("label")?.firstChild?.textContent.trim() || id;
    throw new Error(`${label}: "${bad}" is not a number`);
  }
  return words.map(Number);
}
function overrides() {
  const p = app.hello.protocol;
  const protocol = {};
  const angles = numbersOf("f-angles");
  if (angles.join() !== p.angles_deg.join()) protocol.angles_deg = angles;
  const nums = { sweep_deg: "f-sweep", settle_time: "f-settle", stop_time: "f-stop",
    align_time: "f-align", resteer_time: "f-resteer" };
  if ($("f-metrology").value === "imu") Object.assign(nums, { drive_length: "f-drive", rest_time: "f-rest" });
  for (const [k, id] of Object.entries(nums)) {
    const v = Number($(id).value);
    if ($(id).value !== "" && v !== p[k]) protocol[k] = v;
  }
  const mods = numbersOf("f-modules");
  if (mods.length) protocol.modules = mods;
  return Object.keys(protocol).length ? { protocol } : {};
}
// ------------------------------------------------------------------ without motion capture
// The tape's distances between steering axes, entered before the start, over a drawing of
// the nominal layout; each pair read twice (docs/imu-operation.md).
function tapePairs() {
  const ids = app.hello.modules.map((m) => m.id);
  const out = [];
  for (let i = 0; i < ids.length; i++) for (let j = i + 1; j < ids.length; j++) out.push([ids[i], ids[j]]);
  return out;
}
function buildTape() {
  const mods = app.hello.modules;
  const xs = mods.map((m) => m.x_s), ys = mods.map((m) => m.y_s);
  const pad = 40, W = 400, H = 300;
  // the robot seen from above, its front (x of R) up: screen x = -y, screen y = -x
  const k = Math.min((W - 2 * pad) / Math.max(1e-9, Math.max(...ys) - Math.min(...ys)),
    (H - 2 * pad) / Math.max(1e-9, Math.max(...xs) - Math.min(...xs)));
  const cx = (Math.max(...xs) + Math.min(...xs)) / 2, cy = (Math.max(...ys) + Math.min(...ys)) / 2;
  const at = (m) => [W / 2 - k * (m.y_s - cy), H / 2 - k * (m.x_s - cx)];
  const d = $("tape-drawing");
  d.setAttribute("viewBox", `0 0 ${W} ${H}`);
  const parts = [], labels = [];
  for (const [a, b] of tapePairs()) {
    const [x1, y1] = at(mods.find((m) => m.id === a)), [x2, y2] = at(mods.find((m) => m.id === b));
    parts.push(svg("line", { x1, y1, x2, y2, "data-pair": `${a}-${b}` }));
    // the label halfway, else a third of the way either side (the diagonals cross there)
    const spots = [0.5, 0.3, 0.7].map((f) => [x1 + f * (x2 - x1), y1 + f * (y2 - y1)]);
    const [lx, ly] = spots.find(([x, y]) => labels.every(([u, v]) => Math.hypot(x - u, y - v) > 30)) || spots[0];
    labels.push([lx, ly]);
    const t = svg("text", { x: lx + 4, y: ly - 4, class: "pair" });
    t.textContent = `${a}–${b}`;
    parts.push(t);
  }
  for (const m of mods) {
    const [x, y] = at(m);
    parts.push(svg("circle", { cx: x, cy: y, r: 6 }));
    const t = svg("text", { x: x + 9, y: y + 18 });
    t.textContent = `module ${m.id}`;
    parts.push(t);
  }
  const front = svg("text", { x: W / 2 - 18, y: 16 });
  front.textContent = "front";
  parts.push(front);
  d.replaceChildren(...parts);
  $("tape-rows").replaceChildren(...tapePairs().map(([a, b]) => el("div", { class: "tape-row" },
    el("span", {}, `${a}–${b}`),
    ...[1, 2].map((n) => el("label", {}, `reading ${n}`,
      el("input", { id: `tape-${a}-${b}-${n}`, type: "number", min: "1", step: "any", inputmode: "decimal",
        "aria-label": `distance between the axes of modules ${a} and ${b}, reading ${n} (mm)` }))))));
}
function tapeReferences() {
  const sd = Number($("f-tape-sd").value) / 1000;
  const refs = [];
  for (const [a, b] of tapePairs()) {
    for (const n of [1, 2]) {
      const v = $(`tape-${a}-${b}-${n}`).value;
      if (v !== "") refs.push({ kind: "axis_distance", modules: [a, b], value: Number(v) / 1000, stddev: sd });
    }
  }
  return refs;
}
// the in-process simulator plays the operator's tape: every reading into its field
async function readSimulatorAxes() {
  $("start-error").textContent = "";
  try {
    const sd = Number($("f-tape-sd").value) / 1000;
    const got = await api("GET", `/simulator/axis-distances?stddev=${encodeURIComponent(sd)}`);
    const seen = {};
    for (const r of got.references) {
      const key = r.modules.join("-"), n = (seen[key] = (seen[key] || 0) + 1);
      const field = $(`tape-${key}-${n}`);
      if (field) field.value = (r.value * 1000).toFixed(1);
    }
  } catch (e) {
    $("start-error").textContent = "No tape readings: " + e.message;
  }
}
// what each choice of the two selects means, under it (their options stay short enough
// for a tablet's narrow column)
const METROLOGY_HINT = {
  mocap: "Motion capture measures every spin.",
  imu: "No motion capture: the gyro and the wheels' encoders, the tape's distances below and a straight drive at the end.",
};
const CHECK_HINT = {
  "": "The service's own way of measuring.",
  mocap: "Motion capture: every parameter is checked.",
  imu: "The gyro and the wheels: the robot's shape is checked (no motion capture needed).",
};
function showCheckHint() { $("f-check-hint").textContent = CHECK_HINT[$("f-check-metrology").value]; }
function showMetrology() {
  $("f-metrology-hint").textContent = METROLOGY_HINT[$("f-metrology").value];
  $("tape-fields").hidden = $("f-metrology").value !== "imu";
  $("tape-sim").hidden = !(app.hello && app.hello.in_process_simulator);
}
// MARK and MEASURE: what the run waits for, answered here (POST .../continue, .../references)
function renderOperator(st) {
  const waiting = st.kind === "calibration" && st.metrology === "imu" &&
    (st.state === "MARK" || st.state === "MEASURE");
  $("operator").hidden = !waiting;
  if (!waiting) return;
  const answered = app.answered === `${st.id}:${st.state}`;
  $("op-text").textContent = st.step;
  $("op-mark").hidden = st.state !== "MARK";
  $("op-measure").hidden = st.state !== "MEASURE";
  $("op-continue").disabled = answered;
  $("op-send").disabled = answered;
  $("op-sim-tape").hidden = !(app.hello && app.hello.in_process_simulator);
  $("op-title").textContent = answered ? "Sent: the run goes on" : "The run waits for you";
}
async function answerRun(what, body) {
  const st = app.current;
  $("op-error").textContent = "";
  try {
    onRun(await api("POST", `/calibrations/${st.id}/${what}`, body), false);
    app.answered = `${st.id}:${st.state}`;
    renderOperator(app.current);
  } catch (e) {
    $("op-error").textContent = "Not sent: " + e.message;
  }
}
async function readSimulatorTape() {
  $("op-error").textContent = "";
  try {
    const t = await api("GET", `/simulator/tape-measure?run=${encodeURIComponent(app.current.id)}`);
    $("op-distance").value = (t.value * 1000).toFixed(1);
  } catch (e) {
    $("op-error").textContent = "No tape reading: " + e.message;
  }
}
function sendMeasurement(ev) {
  ev.preventDefault();
  const value = Number($("op-distance").value) / 1000, stddev = Number($("op-distance-sd").value) / 1000;
  answerRun("references", { references: [{ kind: "straight_drive", value, stddev }] });
}

// the plan (docs/plan.md): GET /plan is 202 while the service makes it
function planText(p) {
  const r = p.requirement;
  const g = (x) => Number(x.toPrecision(3));
  const angles = p.protocol.angles_deg.join(", ");
  let t = `Planned: steering angles ${angles} deg, ${p.protocol.sweep_deg} deg sweeps, ` +
    `${p.robot_time_s.toFixed(1)} s of robot time (predicted). Targets: position ` +
    `${g(r.position_mm)} mm, beta ${g(r.beta_deg)} deg, radius ${g(r.radius_mm)} mm`;
  if (r.square_position_mm !== null) {
    t += `; the square path within ${g(r.square_position_mm)} mm, ` +
      `${g(r.square_heading_deg)} deg in ${r.square_share_percent.toFixed(0)} % of runs ` +
      `(predicted: ${r.square_share_percent.toFixed(0)} % within ` +
      `${p.square_position_mm.toFixed(2)} mm, ${p.square_heading_deg.toFixed(4)} deg)`;
  }
  return t + ". The protocol settings of the form are not used (greyed out).";
}
// the form's protocol settings, which a planned run does not use
const PROTOCOL_FIELDS = ["f-angles", "f-sweep", "f-modules", "f-settle", "f-stop", "f-align",
  "f-resteer", "f-drive", "f-rest"];
async function showPlan() {
  const planned = $("f-plan").checked;
  for (const id of PROTOCOL_FIELDS) $(id).disabled = planned;
  if (!planned) { $("plan-text").textContent = ""; return; }
  $("plan-text").textContent = "Planning (seconds to a minute)...";
  for (;;) {
    let r;
    try {
      r = await fetch("/plan");
    } catch (e) {
      $("plan-text").textContent = "No plan: " + e.message;
      return;
    }
    const data = await r.json();
    if (!$("f-plan").checked) return;
    if (r.status === 202) { await new Promise((ok) => setTimeout(ok, 1000)); continue; }
    $("plan-text").textContent = r.ok ? planText(data) : "No plan: " + data.detail;
    return;
  }
}
async function start(ev) {
  ev.preventDefault();
  $("start-error").textContent = "";
  const planned = $("f-plan").checked;
  let body;
  try {
    body = planned ? { plan: "auto", install: $("f-install").value }
      : { overrides: overrides(), install: $("f-install").value };
  } catch (e) {
    $("start-error").textContent = "Not started: " + e.message;
    return;
  }
  body.metrology = $("f-metrology").value;
  if (body.metrology === "imu") body.references = tapeReferences();
  if (!(await ensureToken())) { $("start-error").textContent = "a token is needed to start"; return; }
  $("start").disabled = true;
  app.startAt = performance.now();
  app.metrics.firstLiveUpdateMs = app.metrics.firstChangeMs = null;
  app.startSeen = new Set(app.seenRuns);
  try {
    const st = await api("POST", "/calibrations", body);
    onRun(st, false);
  } catch (e) {
    app.startAt = null;
    $("start-error").textContent = "Not started: " + e.message;
  } finally {
    $("start").disabled = !!app.current && !TERMINAL.has(app.current.state);
  }
}
async function startCheck() {
  $("start-error").textContent = "";
  if (!(await ensureToken())) { $("start-error").textContent = "a token is needed to check"; return; }
  $("check").disabled = $("start").disabled = true;
  app.startAt = performance.now();
  app.metrics.firstLiveUpdateMs = app.metrics.firstChangeMs = null;
  app.startSeen = new Set(app.seenRuns);
  try {
    const metrology = $("f-check-metrology").value;
    onRun(await api("POST", "/checks", metrology ? { metrology } : {}), false);
  } catch (e) {
    app.startAt = null;
    $("start-error").textContent = "Check not started: " + e.message;
  } finally {
    $("check").disabled = $("start").disabled = !!app.current && !TERMINAL.has(app.current.state);
  }
}
async function abortRun() {
  const run = app.current;
  if (!run || TERMINAL.has(run.state)) return;
  $("abort").disabled = true;
  try {
    onRun(await api("POST", `${runPath(run)}/abort`, undefined, true), false);
  } catch (e) {
    $("abort-text").textContent = "Abort failed: " + e.message;
  } finally {
    $("abort").disabled = false;
  }
}

// ------------------------------------------------------------------ live
function onRun(st, pushed) {
  if (pushed && app.startAt !== null && !app.startSeen.has(st.id)) {
    const m = app.metrics, dt = performance.now() - app.startAt;
    if (m.firstLiveUpdateMs === null) m.firstLiveUpdateMs = dt;
    if (st.state !== "PENDING") { m.firstChangeMs = dt; app.startAt = null; }
  }
  app.seenRuns.add(st.id);
  if (pushed) app.metrics.statesSeen.push([st.id, st.state, st.module_index]);
  if (app.current && app.current.id !== st.id && !TERMINAL.has(app.current.state) && TERMINAL.has(st.state)) {
    return;  // an old run's late news does not replace the running one
  }
  if (!app.current || app.current.id !== st.id) {
    app.trail = { run: st.id, chunks: [] };
    app.spins = [];
    if (app.current) $("start-error").textContent = "";  // a new run: the last error is old
  }
  app.current = st;
  renderRun();
  if (st.kind === "commission") {
    app.commissionRun = st.id;
    if (!$("view-commission").hidden) renderCommissionState(st);
    if (TERMINAL.has(st.state) && !$("view-commission").hidden) showCommission(st.id);
  } else if (st.state === "DONE" && st.kind === "check") app.checkRun = st.id;
  else if (st.state === "DONE" && !location.hash.startsWith("#result")) {
    app.resultRun = st.id;
  }
  if (TERMINAL.has(st.state)) {
    if (!$("view-history").hidden) showHistory();
    if (!$("view-drift").hidden) showDrift();
  }
}
function renderRun() {
  const st = app.current;
  const active = st && !TERMINAL.has(st.state);
  $("abort-bar").hidden = !active;
  // one run at a time: the service refuses a second
  $("start").disabled = $("check").disabled = $("com-start").disabled = !!active;
  if (!st) return;
  // a run that waits for its operator says so, in words, with a way to the answer
  $("abort-text").textContent = st.waits_for
    ? `${kindName(st)} ${st.id} waits for you (${st.state}): ${st.step}`
    : `${kindName(st)} ${st.id}: ${st.state}`;
  $("bar-answer").hidden = !(active && st.waits_for);
  $("run-id").textContent = st.id;
  const s = $("run-state");
  s.textContent = st.state;
  s.className = "state " + st.state;
  $("run-step").textContent = st.step;
  $("run-module").textContent = st.module_index ? `${st.module_index} of ${st.modules_total} (module ${st.module})` : `– of ${st.modules_total}`;
  $("run-angle").textContent = st.angle_index ? `${st.angle_index} of ${st.angles_total}: ${fmt(st.angle_deg, 1)}°` : "–";
  const target = !app.hello ? null : st.kind === "check" ? app.hello.check.sweep_deg :
    Number($("f-sweep").value) || app.hello.protocol.sweep_deg;
  // a planned run's spin ends by its forecast (below), not at a set sweep
  $("run-sweep").textContent = `${fmt(st.sweep_deg, 1)}°` +
    (st.state === "SPIN" && target && !st.forecast ? ` of ${target}°` : "");
  $("run-segments").textContent = String(st.segments);
  $("run-elapsed").textContent = st.elapsed_s === null ? "–" : `${duration(st.elapsed_s)} (robot time)`;
  $("run-remaining").textContent = st.remaining_s !== null ? `about ${duration(st.remaining_s)}` :
    !active ? "–" : "not estimated in this step";
  $("run-progress").value = st.progress;
  renderForecast(st);
  $("run-reason").textContent = st.reason ? `${st.state}: ${st.reason}` : "";
  $("run-notes").replaceChildren(...(st.notes || []).map((n) => el("li", {}, "Note: " + n)));
  renderOperator(st);
  const link = $("run-result-link");
  link.hidden = st.state !== "DONE";
  link.href = ({ check: "#check/", commission: "#commission/" }[st.kind] || "#result/") + st.id;
  link.textContent = st.kind === "check" ? `Open the verdict (${st.verdict})` :
    st.kind === "commission" ? `Open the report (${st.verdict})` : "Open the result";
}
// a planned run's std devs, forecast from its data so far (docs/plan.md, sequential stopping)
const FORECAST_ROWS = [
  ["position", "x_s, y_s, b", "position_mm", "mm"],
  ["beta", "homing error beta", "beta_deg", "°"],
  ["radius", "wheel radius r", "radius_mm", "mm"],
  ["square-position", "square path, end position (90 % of runs within)", "square_position_mm", "mm"],
  ["square-heading", "square path, end heading (90 % of runs within)", "square_heading_deg", "°"],
];
function renderForecast(st) {
  const f = st.forecast;
  $("forecast").hidden = !f;
  if (!f) return;
  const sig = (x) => (x === null || x === undefined || !isFinite(x) ? "–" : x.toPrecision(3));
  const rows = FORECAST_ROWS.filter(([, , key]) => f.targets[key] !== null && f.targets[key] !== undefined)
    .map(([id, name, key, unit]) => {
      const share = f[key] === null ? null : f[key] / f.targets[key];
      return el("tr", { id: `forecast-${id}` },
        el("th", { scope: "row" }, name),
        el("td", { class: "num" }, `${sig(f[key])} ${unit}`),
        el("td", { class: "num" }, `${sig(f.targets[key])} ${unit}`),
        el("td", {}, el("meter", { min: "0", max: "2", low: "0.999", high: "1", optimum: "0",
          value: String(share === null ? 2 : Math.min(share, 2)),
          "aria-label": `${name}: ${share === null ? "unknown" : Math.round(100 * share) + " %"} of its target` }),
          ` ${share === null ? "–" : Math.round(100 * share) + " %"}`));
    });
  $("forecast-rows").replaceChildren(...rows);
  const ratio = f.ratio === null ? "–" : `${Math.round(100 * f.ratio)} %`;
  $("forecast-note").textContent = st.state === "SPIN" ?
    `This spin ends once what it measures is within its targets (now ${ratio}), ` +
    "or at twice its planned sweep." :
    st.segments === 0 ? `The plan's prediction: ${ratio} of the targets at most.` :
    `After ${st.segments} spins: the spins to come as planned.`;
}
function onLive(ev) {
  app.live = ev;
  const rows = ev.nodes.map((n) => el("tr", {},
    el("td", {}, n.module), el("td", {}, n.node),
    n.alive === null ? el("td", { class: "muted" }, "unknown") :
      el("td", { class: n.alive ? "yes" : "no" }, n.alive ? "yes" : "no"),
    el("td", { class: n.homed ? "yes" : "no" }, n.homed ? "yes" : "no"),
    el("td", { class: n.errors.some((e) => e) ? "no" : "" }, n.errors.some((e) => e) ? n.errors.map((e) => "0x" + e.toString(16)).join(" / ") : "none"),
    el("td", { class: "num" }, n.steer_deg === null ? "–" : `${fmt(wrapDeg(n.steer_deg), 1)}°`)));
  $("node-rows").replaceChildren(...rows);
  $("node-note").hidden = !ev.nodes.some((n) => n.alive === null);
  $("can-state").textContent = ev.can || "–";
  const m = ev.mocap;
  const age = m.age_s === null ? "no pose yet" : `last pose ${(m.age_s * 1000).toFixed(0)} ms ago`;
  $("mocap-age").textContent = (m.stale ? "STALE, " : "live, ") + age;
  $("mocap-age").className = m.stale ? "no" : "yes";
  // a lab's bridge (swpc mocap): its source and body, the rate it receives, its losses
  const s = m.source;
  $("mocap-source").hidden = !s;
  if (s) {
    const delay = m.delay_ms ? `, delay ${fmt(m.delay_ms[0], 1)} ms (p99 ${fmt(m.delay_ms[1], 1)})` : "";
    $("mocap-source").textContent = `from ${s.source}, body '${s.body}'` +
      (s.seen ? `: ${fmt(s.rate_hz, 0)} Hz, ${s.dropped} frames dropped, ${s.not_seen} without the body${delay}`
        : ` NOT SEEN (the system has: ${s.bodies.join(", ") || "no bodies"})`);
    $("mocap-source").className = s.seen ? "" : "no";
  }
  if (ev.run && !app.current) onRun(ev.run, false);
  else if (ev.run && ev.run.id === app.current.id) {
    // sweep and progress move between state changes: the live event carries them
    if (ev.run.state === app.current.state) { app.current = ev.run; renderRun(); }
  }
  if (ev.trail && app.current && ev.trail.run === app.current.id) {
    if (ev.trail.reset || app.trail.run !== ev.trail.run) app.trail = { run: ev.trail.run, chunks: [] };
    const module = app.current.module || 0;
    let chunk = app.trail.chunks[app.trail.chunks.length - 1];
    if (!chunk || chunk.module !== module) {
      // the next module's path starts where the last one ended, if that one drew any
      chunk = { module, points: chunk ? chunk.points.slice(-1) : [] };
      app.trail.chunks.push(chunk);
    }
    chunk.points.push(...ev.trail.points);
    app.spins = ev.spins || [];
  }
  if (ev.drives && !$("view-drives").hidden) renderDrives(ev.drives);
  // without motion capture there is no pose to draw
  $("live-figure").hidden = !!app.current && app.current.metrology === "imu" && !(m.pose);
  drawLive();
}

// ------------------------------------------------------------------ drawing
// World coordinates (m, y up) into an SVG whose viewBox is fitted to what is drawn.
function fitView(el, pts, pad, minW = 0.2) {
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of pts) { x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y); }
  if (!isFinite(x0)) [x0, y0, x1, y1] = [-1, -1, 1, 1];
  const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
  let w = Math.max(x1 - x0 + 2 * pad, minW), h = Math.max(y1 - y0 + 2 * pad, minW * 0.75);
  if (w / h > 4 / 3) h = w * 3 / 4; else w = h * 4 / 3;
  el.setAttribute("viewBox", `${cx - w / 2} ${-cy - h / 2} ${w} ${h}`);
  el.replaceChildren();
  const g = svg("g", { transform: "scale(1,-1)" });
  el.append(g);
  return { g, w };
}
// a drawing's scale text at least 12 px on the screen however small the drawing is shown
// (a module's panel at 800 px is ~150 px wide: a thirty-second of it was 5 px); once the
// drawings are in the page, where their size is known
function fitScaleText(root) {
  for (const e of root.querySelectorAll("svg")) {
    const px = e.getBoundingClientRect().width, w = e.viewBox.baseVal.width;
    if (!(px > 0 && w > 0)) continue;
    for (const t of e.querySelectorAll("text.scale")) t.setAttribute("font-size", Math.max(w / 32, (12 * w) / px));
  }
}
function scaleBar(el, w) {
  const vb = el.viewBox.baseVal;
  const len = Math.pow(10, Math.floor(Math.log10(w / 4)));
  const x = vb.x + w * 0.04, y = vb.y + vb.height * 0.95;
  el.append(svg("line", { x1: x, y1: y, x2: x + len, y2: y, stroke: "#111", "stroke-width": w / 250 }));
  const t = svg("text", { x, y: y - w / 100, "font-size": w / 32, fill: "#111", class: "scale" });
  t.textContent = len >= 1 ? `${len} m` : `${Math.round(len * 1000)} mm`;
  el.append(t);
}
const rotate = (x, y, yaw) => [x * Math.cos(yaw) - y * Math.sin(yaw), x * Math.sin(yaw) + y * Math.cos(yaw)];
function robotShapes(g, pose, w, locked) {
  const mods = app.hello.modules;
  const [px, py, yaw] = pose;
  const world = (x, y) => { const [a, b] = rotate(x, y, yaw); return [px + a, py + b]; };
  const xs = mods.map((m) => m.x_s), ys = mods.map((m) => m.y_s);
  const m = Math.max(...mods.map((q) => q.b + q.r)) + 0.02;
  const corners = [[Math.min(...xs) - m, Math.min(...ys) - m], [Math.max(...xs) + m, Math.min(...ys) - m],
    [Math.max(...xs) + m, Math.max(...ys) + m], [Math.min(...xs) - m, Math.max(...ys) + m]];
  g.append(svg("polygon", { points: corners.map((c) => world(...c).join(",")).join(" "),
    fill: "rgba(16,24,32,0.06)", stroke: "#111", "stroke-width": w / 300 }));
  const [hx, hy] = world(Math.max(...xs) + m, 0);  // heading mark at the front
  const [ox, oy] = world(0, 0);
  g.append(svg("line", { x1: ox, y1: oy, x2: hx, y2: hy, stroke: "#111", "stroke-width": w / 400, "stroke-dasharray": `${w / 100}` }));
  const nodes = app.live ? app.live.nodes : [];
  for (const q of mods) {
    const n = nodes.find((n) => n.module === q.id);
    const th = (n && n.steer_deg !== null ? n.steer_deg * Math.PI / 180 : 0) + q.beta;
    const [sx, sy] = world(q.x_s, q.y_s);
    const [cx, cy] = world(q.x_s + q.b * Math.cos(th), q.y_s + q.b * Math.sin(th));
    const [dx, dy] = rotate(Math.cos(th), Math.sin(th), yaw);
    const c = colorOf(q.id);
    g.append(svg("line", { x1: cx - dx * q.r, y1: cy - dy * q.r, x2: cx + dx * q.r, y2: cy + dy * q.r,
      stroke: c, "stroke-width": w / 90, "stroke-linecap": "round" }));
    g.append(svg("circle", { cx: sx, cy: sy, r: w / 120, fill: q.id === locked ? "#b3001b" : "#fff",
      stroke: c, "stroke-width": w / 300 }));
  }
}
function drawLive() {
  const el = $("live-view");
  if (!app.hello) return;
  const pose = app.live && app.live.mocap.pose;
  const pts = [];
  for (const c of app.trail.chunks) pts.push(...c.points);
  for (const s of app.spins) pts.push([s.c_w[0] - s.radius, s.c_w[1] - s.radius], [s.c_w[0] + s.radius, s.c_w[1] + s.radius]);
  if (pose) pts.push([pose[0] - 0.35, pose[1] - 0.35], [pose[0] + 0.35, pose[1] + 0.35]);
  const { g, w } = fitView(el, pts, 0.1);
  for (const c of app.trail.chunks) {
    if (c.points.length < 2) continue;
    g.append(svg("polyline", { points: c.points.map((p) => p.join(",")).join(" "), fill: "none",
      stroke: colorOf(c.module || 1), "stroke-width": w / 250, "stroke-linejoin": "round" }));
  }
  drawSpins(g, app.spins, w);
  if (pose) robotShapes(g, pose, w, app.current && !TERMINAL.has(app.current.state) ? app.current.module : null);
  scaleBar(el, w);
}
function drawSpins(g, spins, w) {
  for (const s of spins) {
    const c = colorOf(s.module);
    g.append(svg("circle", { cx: s.c_w[0], cy: s.c_w[1], r: s.radius, fill: "none", stroke: c,
      "stroke-width": w / 400, "stroke-dasharray": `${w / 80} ${w / 120}` }));
    const k = w / 60;
    g.append(svg("path", { d: `M${s.c_w[0] - k},${s.c_w[1]}h${2 * k}M${s.c_w[0]},${s.c_w[1] - k}v${2 * k}`,
      stroke: c, "stroke-width": w / 200 }));
  }
}

// ------------------------------------------------------------------ result
async function showResult(id) {
  $("res-empty").hidden = !!id;
  $("res-body").hidden = !id;
  if (!id) return;
  app.resultRun = id;
  $("res-id").textContent = id;
  try {
    const [cmp, files] = await Promise.all([api("GET", `/calibrations/${id}/comparison`), api("GET", `/calibrations/${id}/files`)]);
    renderComparison(cmp);
    $("res-files").replaceChildren(...files.map((f) => el("li", {},
      el("a", { href: f.url, download: `${id}-${f.name}` }, f.name), ` (${(f.size / 1024).toFixed(0)} KiB)`)));
    for (const to of ["urdf", "ros2-params", "kinematics"]) {
      const a = $("res-export-" + to);
      a.href = `/calibrations/${id}/export?to=${to}`;
      a.setAttribute("download", "");  // the name the service gives (Content-Disposition)
    }
    $("res-plot").src = `/calibrations/${id}/plot.png`;
    $("res-foxglove").href = "#foxglove/" + id;
    renderGeometry(await api("GET", `/calibrations/${id}/geometry`));
    await showReached(id);
  } catch (e) {
    $("res-summary").textContent = `No result for ${id}: ${e.message}`;
    $("res-rows").replaceChildren();
  }
}
// on the simulator only: the result against its hidden truth (GET /simulator/reached)
async function showReached(id) {
  const p = $("res-truth");
  p.hidden = !(app.hello && app.hello.in_process_simulator);
  if (p.hidden) return;
  try {
    const r = await api("GET", `/simulator/reached?run=${encodeURIComponent(id)}`);
    const kinds = r.kinds.map((k) => `${k.kind} ${k.largest.toPrecision(2)} ${k.unit} (RMS z ${k.rms_z.toFixed(2)})`);
    const budget = r.budget_position_mm === null ? "" : `, budget ${r.budget_position_mm} mm`;
    const bound = r.within_budget === null ? "" :
      ` ${r.within_budget ? "Within" : "Beyond"} the budget (${r.budget_position_mm} mm, ` +
      `${r.budget_heading_deg.toFixed(3)} deg); by its covariance ${r.share_percent.toFixed(0)} % ` +
      `of runs end within ${r.bound_position_mm.toFixed(3)} mm, ${r.bound_heading_deg.toFixed(4)} deg.`;
    p.textContent = `Against the simulator's truth: largest errors ${kinds.join(", ")}; ` +
      `NEES ${r.nees.toFixed(2)} over ${r.dof} (about 1 when the std devs are honest); ` +
      `square path ${r.square_position_mm.toFixed(3)} mm, ${r.square_heading_deg.toFixed(4)} deg ` +
      `reached, ${r.forecast_position_mm.toFixed(3)} mm forecast (std dev)${budget}.${bound}`;
  } catch (e) {
    p.textContent = `Against the simulator's truth: not known (${e.message}).`;
  }
}
function chip(value, yes, no, goodWhenTrue) {
  if (value === null) return el("span", { class: "chip none" }, "unknown");
  const good = value === goodWhenTrue;
  return el("span", { class: "chip " + (value && !goodWhenTrue ? "sig" : good ? "ok" : "bad") }, value ? yes : no);
}
function renderComparison(cmp) {
  const inForce = cmp.in_force, rep = cmp.replaced;
  const from = (run) => (run ? ` (from run ${run})` : " (not from a run)");
  const ref = cmp.reference === "replaced file" ? `the file its install replaced, kept as ${rep.replaced}` + from(rep.replaced_run) :
    cmp.reference === "file in force" ? `the file in force, ${inForce.name}` + from(inForce.run) :
    `the nominal design: ${cmp.reference_why}`;
  $("res-summary").replaceChildren(
    el("b", { class: cmp.within_tolerance ? "yes" : "no" }, cmp.within_tolerance ? "Within tolerance" : "Over tolerance"),
    " · ", cmp.is_in_force ? el("b", { class: "yes" }, "this result is in force") :
      (cmp.installed ? "installed at the run's end, since replaced"
        : "not installed" + (cmp.install_held ? ` (${cmp.install_held})` : "")),
    " · compared with " + ref + `; significant = change over ${cmp.significance_k} std devs.`);
  $("res-frame").textContent = cmp.frame === "design-fit"
    ? "Compared in frame design-fit: the steering axes best aligned with the nominal ones" +
      (cmp.frame_note ? `; ${cmp.frame_note}.` : ".")
    : "Compared in frame R: the motion capture's rigid body.";
  $("res-ref-head").textContent = { "replaced file": "Replaced", "file in force": "In force", nominal: "Reference (none)" }[cmp.reference];
  $("res-install").disabled = cmp.is_in_force;
  $("res-install-note").textContent = cmp.is_in_force ? "already the file in force" : "";
  const d = (r) => (r.unit === "deg" ? 4 : 3);
  $("res-rows").replaceChildren(...cmp.rows.map((r) => el("tr", { "data-param": `${r.module}.${r.param}` },
    el("th", { scope: "row" }, `${r.module} ${r.param} `, el("span", { class: "muted" }, `(${r.unit})`)),
    el("td", { class: "num" }, fmt(r.nominal, d(r))), el("td", { class: "num" }, fmt(r.calibrated, d(r))),
    el("td", { class: "num" }, fmt(r.stddev, d(r) + 1)), el("td", { class: "num" }, fmt(r.tolerance, d(r) + 1)),
    el("td", {}, chip(r.within_tolerance, "yes", "NO", true)),
    el("td", { class: "num" }, fmt(r.reference_value, d(r))), el("td", { class: "num" }, signed(r.change, d(r))),
    el("td", { title: `|change| > ${cmp.significance_k} std devs` }, chip(r.significant, "yes", "no", false)))));
}
async function installResult() {
  const id = app.resultRun;
  if (!id) return;
  const ok = await confirmDialog("Install this result?",
    `The calibration ${id} becomes the kinematic file in force; the file it replaces is kept as a backup and can be rolled back.`,
    "Install");
  if (!ok) return;
  try {
    const r = await api("POST", `/calibrations/${id}/install`);
    $("res-install-note").textContent = `installed${r.backup ? `; previous file kept as ${r.backup}` : ""}`;
    await showResult(id);
  } catch (e) {
    $("res-install-note").textContent = "Not installed: " + e.message;
  }
}
function renderGeometry(geo) {
  const world = $("res-world");
  const pts = [];
  for (const s of geo.spins) pts.push([s.c_w[0] - s.radius, s.c_w[1] - s.radius], [s.c_w[0] + s.radius, s.c_w[1] + s.radius]);
  const { g, w } = fitView(world, pts, 0.08);
  for (const s of geo.spins) {
    g.append(svg("polyline", { points: s.path.map((p) => p.join(",")).join(" "), fill: "none",
      stroke: colorOf(s.module), "stroke-width": w / 300 }));
  }
  drawSpins(g, geo.spins, w);
  scaleBar(world, w);
  $("res-world-figure").hidden = !geo.spins.length;  // without motion capture: no path
  $("res-modules-fixed").hidden = !geo.spins.length;  // ... and no fixed points (×) to draw
  const panels = geo.calibrated.map((cal) => {
    const nom = geo.nominal.find((n) => n.id === cal.id);
    const el2 = svg("svg", { role: "img", "aria-label": `module ${cal.id} in the robot frame` });
    const span = nom.b + 0.006;
    const { g: gg, w: ww } = fitView(el2, [[nom.x_s - span, nom.y_s - span], [nom.x_s + span, nom.y_s + span]], 0, 0.01);
    const c = colorOf(cal.id);
    gg.append(svg("circle", { cx: nom.x_s, cy: nom.y_s, r: nom.b, fill: "none", stroke: "#777",
      "stroke-width": ww / 250, "stroke-dasharray": `${ww / 60}` }));
    const q = ww / 70;
    gg.append(svg("rect", { x: nom.x_s - q / 2, y: nom.y_s - q / 2, width: q, height: q, fill: "none",
      stroke: "#555", "stroke-width": ww / 250 }));
    gg.append(svg("circle", { cx: cal.x_s, cy: cal.y_s, r: cal.b, fill: "none", stroke: c, "stroke-width": ww / 160 }));
    gg.append(svg("circle", { cx: cal.x_s, cy: cal.y_s, r: ww / 120, fill: c }));
    for (const s of geo.spins.filter((s) => s.module === cal.id)) {
      const k = ww / 45;
      gg.append(svg("path", { d: `M${s.c_r[0] - k},${s.c_r[1] - k}l${2 * k},${2 * k}M${s.c_r[0] - k},${s.c_r[1] + k}l${2 * k},${-2 * k}`,
        stroke: "#111", "stroke-width": ww / 150 }));
    }
    const t = svg("text", { x: el2.viewBox.baseVal.x + ww * 0.04, y: el2.viewBox.baseVal.y + ww * 0.1, "font-size": ww / 12, fill: c });
    t.textContent = `module ${cal.id}`;
    el2.append(t);
    scaleBar(el2, ww);
    return el2;
  });
  $("res-modules").replaceChildren(...panels);
  fitScaleText($("res-modules"));
}

// ------------------------------------------------------------------ check and drift
async function showCheck(id) {
  $("chk-empty").hidden = !!id;
  $("chk-body").hidden = !id;
  if (!id) return;
  app.checkRun = id;
  $("chk-id").textContent = id;
  let st;
  try {
    st = await api("GET", `/checks/${id}`);
  } catch (e) {
    $("chk-verdict").textContent = `No check ${id}: ${e.message}`;
    return;
  }
  const res = st.result;
  if (!res) {
    $("chk-verdict").replaceChildren(el("span", { class: "state " + st.state }, st.state), " ",
      st.reason || "no verdict yet");
    $("chk-file").textContent = "";
    $("chk-module-rows").replaceChildren();
    $("chk-rows").replaceChildren();
    return;
  }
  const ok = res.verdict === "consistent";
  $("chk-verdict").replaceChildren(
    el("span", { id: "chk-verdict-chip", class: "chip " + (ok ? "ok" : "bad") }, ok ? "consistent" : "drifted"),
    " ", el("b", {}, ok ? "the robot matches its file" : res.action),
    ` · ${res.drifted_modules.length} of ${res.modules.length} modules drifted · robot time ` +
    duration(st.elapsed_s || 0) + (res.metrology === "imu"
      ? " · measured with the gyro and the wheels" : " · measured with motion capture"));
  const f = res.file || {};
  $("chk-file").textContent = `Judged against ${f.name || "the file in force"}` +
    (f.run ? ` (from run ${f.run})` : " (not from a run)") + `, sha256 ${f.sha256 || "?"}; ` +
    `false-alarm rate ${(100 * res.false_alarm).toFixed(0)} % over the robot (Šidák: ` +
    `${(100 * res.alpha_module).toFixed(2)} % per module).` + (res.notes.length ? " " + res.notes.join(" ") : "");
  $("chk-module-rows").replaceChildren(...res.modules.map((m) => el("tr", { "data-module": m.id },
    el("th", { scope: "row" }, `module ${m.id}`), el("td", { class: "num" }, fmt(m.chi2, 2)),
    el("td", { class: "num" }, fmt(res.chi2_threshold, 2)),
    el("td", {}, el("span", { class: "chip " + (m.drifted ? "bad" : "ok") }, m.drifted ? "drifted" : "consistent")),
    el("td", {}, m.parameters.join(", ") || "–"))));
  const d = (r) => (r.unit === "deg" ? 4 : 3);
  $("chk-rows").replaceChildren(...res.table.map((r) => el("tr", { "data-param": `${r.module}.${r.param}` },
    el("th", { scope: "row" }, `${r.module} ${r.param} `, el("span", { class: "muted" }, `(${r.unit})`)),
    el("td", { class: "num" }, fmt(r.file, d(r))), el("td", { class: "num" }, fmt(r.check, d(r))),
    el("td", { class: "num" }, signed(r.change, d(r))), el("td", { class: "num" }, fmt(r.stddev, d(r) + 1)),
    el("td", { class: "num" }, signed(r.z, 1)),
    el("td", {}, chip(r.drifted, "yes", "no", false)))));
}
const dateOf = (t) => (t || "").slice(0, 10);
function driftChart(p, verdicts) {
  // x: time (s since the first point), y: the value; the band reference +- tolerance
  const pts = p.points.filter((q) => q.value !== null);
  const W = 250, H = 150, L = 52, R = 8, T = 8, B = 8;  // the values' labels left of L
  const e = svg("svg", { viewBox: `0 0 ${W} ${H}`, role: "img",
    "aria-label": `module ${p.module} ${p.param} over time` });
  if (!pts.length) return e;
  const ts = pts.map((q) => Date.parse(q.time));
  const line = p.trend ? p.trend.line.map((q) => [Date.parse(q.time), q.value]) : [];
  const t0 = Math.min(...ts, ...line.map((q) => q[0])), t1 = Math.max(...ts, ...line.map((q) => q[0]), t0 + 1);
  const ys = pts.flatMap((q) => [q.value - (q.stddev || 0), q.value + (q.stddev || 0)]);
  if (p.reference !== null) ys.push(p.reference - p.tolerance, p.reference + p.tolerance);
  for (const q of line) ys.push(q[1]);
  let y0 = Math.min(...ys), y1 = Math.max(...ys);
  const pad = (y1 - y0) * 0.08 || Math.abs(y0) * 1e-3 || 1;
  y0 -= pad; y1 += pad;
  const X = (t) => L + (W - L - R) * (t - t0) / (t1 - t0);
  const Y = (y) => T + (H - T - B) * (y1 - y) / (y1 - y0);
  if (p.reference !== null) {
    e.append(svg("rect", { x: L, width: W - L - R, y: Y(p.reference + p.tolerance),
      height: Y(p.reference - p.tolerance) - Y(p.reference + p.tolerance), fill: "#e4efe6" }));
    e.append(svg("line", { x1: L, x2: W - R, y1: Y(p.reference), y2: Y(p.reference), stroke: "#0a6b2d", "stroke-width": 1.2 }));
  }
  if (line.length === 2) {
    e.append(svg("line", { x1: X(line[0][0]), y1: Y(line[0][1]), x2: X(line[1][0]), y2: Y(line[1][1]),
      stroke: "#8a4b00", "stroke-width": 1.5, "stroke-dasharray": "5 3" }));
  }
  const label = (y, v) => {
    const t = svg("text", { x: L - 4, y, "font-size": 11, fill: "#111", "text-anchor": "end" });
    t.textContent = fmt(v, p.unit === "deg" ? 4 : 3);
    e.append(t);
  };
  label(T + 10, y1);
  label(H - B - 2, y0);
  pts.forEach((q, i) => {
    const x = X(ts[i]), y = Y(q.value), s = q.stddev || 0;
    const c = q.kind === "check" ? (verdicts[q.run] === "drifted" ? "#b3001b" : "#0a6b2d") : "#0b4fa8";
    if (s > 0) e.append(svg("line", { x1: x, x2: x, y1: Y(q.value + s), y2: Y(q.value - s), stroke: c, "stroke-width": 1.2 }));
    e.append(q.kind === "check"
      ? svg("rect", { x: x - 3.5, y: y - 3.5, width: 7, height: 7, fill: "#fff", stroke: c, "stroke-width": 1.8 })
      : svg("circle", { cx: x, cy: y, r: 3.5, fill: c }));
  });
  return e;
}
async function showDrift() {
  const [h, checks] = await Promise.all([api("GET", "/history"), api("GET", "/checks")]);
  const verdicts = Object.fromEntries(h.runs.map((r) => [r.run, r.verdict]));
  const last = h.last_check;
  const f = h.file_in_force;
  const count = (kind, word) => {
    const n = h.runs.filter((r) => r.kind === kind).length;
    return `${n} ${word}${n === 1 ? "" : "s"}`;
  };
  $("drift-summary").replaceChildren(
    `${count("calibration", "calibration")} and ${count("check", "check")} · file in force: ` +
    (f ? `${f.name}${f.run ? " (from run " + f.run + ")" : ""}` : "none") + " · last check: ",
    last ? el("a", { href: "#check/" + last.id }, `${last.id} (${last.verdict || last.state})`) : "none yet");
  const d = (p) => (p.unit === "deg" ? 4 : 3);
  $("drift-charts").replaceChildren(...h.parameters.map((p) => {
    const tr = p.trend;
    const drawn = p.points.filter((q) => q.value !== null).length;
    const what = !tr ? (drawn < 2 ? "no trend: fewer than two points"
      : "no trend: its points span less than a day, too short for a slope per week") :
      `${signed(tr.per_week, d(p) + 1)} ${p.unit}/week ± ${fmt(tr.per_week_std, d(p) + 1)}` +
      (tr.outside ? " · outside its tolerance now" : "") +
      (tr.leaves_tolerance ? ` · leaves ±${fmt(p.tolerance, d(p))} ${p.unit} on ${dateOf(tr.leaves_tolerance)}` :
        " · no significant trend");
    const other = p.points.filter((q) => q.other_frame).length;
    const moved = p.points.filter((q) => q.re_expressed).length;
    const frames = (moved ? ` · ${moved} from motion capture re-expressed in design-fit` : "") +
      (other ? ` · ${other} of another frame not drawn` : "");
    return el("figure", { "data-param": `${p.module}.${p.param}` },
      el("h3", {}, `module ${p.module} ${p.param} (${p.unit})`), driftChart(p, verdicts),
      el("figcaption", { class: "muted" }, what + frames));
  }));
  if (!h.parameters.length) $("drift-charts").replaceChildren(el("p", {}, "No calibration or check finished yet."));
  checks.reverse();
  $("check-rows").replaceChildren(...checks.map((c) => el("tr", { "data-run": c.id },
    el("td", {}, (c.created || "").replace("T", " ").replace("Z", "")),
    el("td", { class: "mono" }, c.id),
    el("td", {}, el("span", { class: "state " + c.state }, c.state)),
    el("td", {}, c.verdict ? el("span", { class: "chip " + (c.verdict === "consistent" ? "ok" : "bad") }, c.verdict) : (c.reason || "–")),
    el("td", {}, el("a", { href: "#check/" + c.id }, "verdict")))));
  if (!checks.length) $("check-rows").replaceChildren(el("tr", {}, el("td", { colspan: 5 }, "none yet")));
}

// ------------------------------------------------------------------ history and files
const CHANGES = { run: "installed by its run", install: "installed", rollback: "rolled back" };
async function showHistory() {
  const [runs, files, changes] = await Promise.all([api("GET", "/calibrations"),
    api("GET", "/kinematics/files"), api("GET", "/kinematics/changes")]);
  const when = (t) => (t || "").replace("T", " ").replace("Z", "");
  $("change-rows").replaceChildren(...changes.map((c) => el("tr", { "data-action": c.action },
    el("td", {}, when(c.time)),
    el("td", {}, CHANGES[c.action] || c.action, ...(c.run ? [" · run ", el("a", { href: "#result/" + c.run }, c.run)] : [])),
    el("td", {}, el("span", { class: "mono name" }, c.file)),
    el("td", {}, c.replaced ? el("span", { class: "mono name" }, c.replaced) : "none in force",
      c.replaced_run ? ` (from run ${c.replaced_run})` : ""))));
  if (!changes.length) $("change-rows").replaceChildren(el("tr", {}, el("td", { colspan: 4 }, "none yet")));
  const inForce = files.in_force && files.in_force.run;
  runs.reverse();
  $("history-rows").replaceChildren(...runs.map((r) => el("tr", { "data-run": r.id },
    el("td", {}, (r.created || "").replace("T", " ").replace("Z", "")),
    el("td", { class: "mono" }, r.id),
    el("td", {}, el("span", { class: "state " + r.state }, r.state)),
    el("td", {}, r.reason || ""),
    el("td", {}, r.installed === null ? "–" : r.installed ? "yes" : "no",
      r.id === inForce ? el("span", { class: "chip ok in-force" }, "in force") : ""),
    el("td", {}, r.state === "DONE" ? el("a", { href: "#result/" + r.id }, "result, plots, files") :
      el("a", { href: `/calibrations/${r.id}/files/can.log`, download: `${r.id}-can.log` }, "CAN log")))));
}
async function showFiles() {
  $("kin-error").textContent = "";
  const k = await api("GET", "/kinematics/files");
  $("kin-path").textContent = k.path;
  const f = k.in_force;
  $("kin-in-force").replaceChildren(f ? el("p", {}, el("b", {}, "In force: "), el("span", { class: "mono", id: "kin-in-force-name" }, f.name),
    ` · created ${f.created || "?"} · ` + (f.run ? `from run ${f.run}` : "not from a calibration run") + (f.valid ? "" : ` · INVALID: ${f.error}`))
    : el("p", {}, "No kinematic file installed yet."));
  $("backup-rows").replaceChildren(...k.backups.map((b) => el("tr", { "data-backup": b.name },
    el("td", {}, (b.backup_time || "").replace("T", " ").replace("Z", "")),
    el("td", {}, el("span", { class: "mono name" }, b.name), el("br"),
      el("span", { class: "muted" }, "created " + (b.created || "?") + (b.valid ? "" : " · INVALID"))),
    el("td", {}, b.run ? el("a", { href: "#result/" + b.run }, b.run) : "–"),
    el("td", {}, el("button", { type: "button", class: "secondary", onclick: () => rollback(b) }, "Roll back to this")))));
  if (!k.backups.length) $("backup-rows").replaceChildren(el("tr", {}, el("td", { colspan: 4 }, "none yet")));
}
async function rollback(b) {
  const ok = await confirmDialog("Roll back the kinematic file?",
    `${b.name} (${b.run ? "from run " + b.run : "not from a run"}) becomes the file in force again; the current file is kept as a backup.`,
    "Roll back");
  if (!ok) return;
  try {
    await api("POST", "/kinematics/rollback", { backup: b.name });
    await showFiles();
  } catch (e) {
    $("kin-error").textContent = "Not rolled back: " + e.message;
  }
}

// ------------------------------------------------------------------ foxglove
const isoNs = (ns) => new Date(ns / 1e6).toISOString().replace("T", " ").replace(/\.\d+Z$/, " UTC");
async function showFoxglove(id) {
  if (!id) {
    const done = (await api("GET", "/calibrations")).filter((r) => r.state === "DONE");
    if (!done.length) return;
    id = done[done.length - 1].id;
  }
  $("fox-run").textContent = `${id}'s`;
  let s;
  try {
    s = await api("GET", `/calibrations/${id}/mcap`);
  } catch (e) {
    $("fox-summary").textContent = `No MCAP for ${id}: ${e.message}`;
    $("fox-table").hidden = true;
    return;
  }
  const native = s.channels.filter((c) => c.native).length;
  $("fox-summary").replaceChildren(
    el("a", { href: `/calibrations/${id}/files/run.mcap`, download: `${id}-run.mcap` }, "run.mcap"),
    ` (${(s.size / 1024).toFixed(0)} KiB): ` + (s.indexed
      ? `${s.channels.length} channels, ${native} of them in a schema Foxglove shows natively.`
      : "no summary: the recording was cut short (mcap recover rewrites its index)."));
  $("fox-table").hidden = !s.indexed;
  $("fox-rows").replaceChildren(...s.channels.map((c) => el("tr", { "data-topic": c.topic },
    el("td", { class: "mono" }, c.topic), el("td", { class: "mono" }, c.schema_name || "–"),
    el("td", { class: "num" }, c.messages),
    el("td", {}, c.native ? el("span", { class: "chip ok" }, "yes") : el("span", { class: "chip none" }, "no")))));
  const times = s.start_ns === null ? "no messages" : s.epoch_times
    ? `log times in epoch time, ${isoNs(s.start_ns)} to ${isoNs(s.end_ns)}`
    : `log times on the run's clock (${(s.start_ns / 1e9).toFixed(1)} s to ${(s.end_ns / 1e9).toFixed(1)} s), not epoch time`;
  $("fox-extra").textContent = s.indexed ? `${times[0].toUpperCase()}${times.slice(1)}; metadata: ` +
    (s.metadata.join(", ") || "none") + "; attachments: " + (s.attachments.join(", ") || "none") + "." : "";
}

// ------------------------------------------------------------------ drives
// Each module axis' drive (GET /drives; then every live event carries the same document)
// ------------------------------------------------------------------ commissioning
async function startCommission() {
  $("com-error").textContent = "";
  if (!(await ensureToken())) { $("com-error").textContent = "a token is needed to commission"; return; }
  $("com-start").disabled = true;
  try {
    const st = await api("POST", "/commissions");
    location.hash = "#commission/" + st.id;
    onRun(st, false);
  } catch (e) {
    $("com-error").textContent = "Commissioning not started: " + e.message;
  } finally {
    $("com-start").disabled = !!app.current && !TERMINAL.has(app.current.state);
  }
}
function renderCommissionState(st) {
  $("com-empty").hidden = true;
  $("com-body").hidden = false;
  $("com-id").textContent = st.id;
  $("com-state").textContent = `${st.state}: ${st.step}` +
    (st.module_index ? ` · module ${st.module_index} of ${st.modules_total}` : "") +
    (st.elapsed_s !== null ? ` · ${duration(st.elapsed_s)} of robot time` : "");
  if (!TERMINAL.has(st.state)) {
    $("com-verdict").textContent = "Commissioning…";
    for (const id of ["com-findings", "com-unknown", "com-module-rows", "com-rest"]) $(id).replaceChildren();
    $("com-motion").textContent = "";
    $("com-fix").hidden = true;
  }
}
async function showCommission(id) {
  if (!id) {
    const all = await api("GET", "/commissions").catch(() => []);
    id = all.length ? all[all.length - 1].id : null;
  }
  if (!id) { $("com-empty").hidden = false; $("com-body").hidden = true; return; }
  let st;
  try {
    st = await api("GET", "/commissions/" + id);
  } catch (e) {
    $("com-empty").hidden = false;
    $("com-empty").textContent = `No commissioning ${id}: ${e.message}`;
    $("com-body").hidden = true;
    return;
  }
  app.commissionRun = st.id;
  renderCommissionState(st);
  if (TERMINAL.has(st.state)) renderCommission(st);
}
function renderCommission(st) {
  const res = st.result;
  $("com-accepted").textContent = "";
  if (!res) {
    $("com-verdict").replaceChildren(el("span", { class: "chip bad" }, st.state), ": " + (st.reason || "no report"));
    $("com-fix").hidden = true;
    return;
  }
  $("com-verdict").replaceChildren(res.right
    ? el("span", { class: "chip ok" }, "Right: the robot agrees with its config on every axis")
    : el("span", { class: "chip bad" }, `Not right: ${res.findings.length} finding(s), ` +
      `${res.unknown.length} not known`));
  $("com-findings").replaceChildren(...res.findings.map((f) => el("li", {}, f.text)));
  $("com-unknown").replaceChildren(...res.unknown.map((u) => el("li", { class: "muted" }, "Not known: " + u)));
  const sign = (v) => (v === null ? "–" : v > 0 ? "as configured" : "reversed");
  const num = (v, d) => (v === null ? "–" : fmt(v, d));
  $("com-module-rows").replaceChildren(...res.modules.map((m) => el("tr", { "data-module": m.module },
    el("th", { scope: "row" }, String(m.module)),
    el("td", { class: m.physical !== null && m.physical !== m.module ? "no" : "" },
      m.swapped ? "steering and wheel swapped" : m.physical === null ? "–" : String(m.physical)),
    el("td", {}, sign(m.steer_sign)), el("td", { class: "num" }, num(m.steer_ratio, 2)),
    el("td", { class: "num" }, m.zero_deg === null ? "–" : `${fmt(m.zero_deg, 1)}°`),
    el("td", {}, sign(m.wheel_sign)), el("td", { class: "num" }, num(m.wheel_ratio, 2)))));
  $("com-motion").textContent = `${fmt(res.robot_time_s, 1)} s of robot time; the largest motion ` +
    `${fmt(res.largest_turn_deg, 1)}° of turn and ${fmt(res.largest_move_mm, 0)} mm; ` +
    `${res.stops.length} roll(s) stopped early.`;
  $("com-fix").hidden = !res.diff && !res.not_in_config.length;
  $("com-diff").replaceChildren(...res.diff.split("\n").map((line) => el("span",
    { class: line.startsWith("+") && !line.startsWith("+++") ? "add" : line.startsWith("-") && !line.startsWith("---") ? "del" : "" },
    line + "\n")));
  $("com-diff").hidden = !res.diff;
  $("com-rest").replaceChildren(...res.not_in_config.map((t) => el("li", {}, "Not in the config: " + t)));
  $("com-accept").hidden = !res.diff || !!res.config_error;
  if (res.config_error) $("com-accepted").textContent = "The corrected config does not load: " + res.config_error;
}
async function acceptCommission() {
  const id = app.commissionRun;
  if (!id) return;
  const ok = await confirmDialog("Write the corrected robot config?",
    "The service's robot config file is replaced by the one shown (the one in force is kept " +
    "beside it as a backup). A change of the drives takes effect when the service restarts.",
    "Write it");
  if (!ok) return;
  $("com-accept").disabled = true;
  try {
    const r = await api("POST", `/commissions/${id}/accept`);
    $("com-accepted").textContent = `Written to ${r.written} (the one it replaced: ${r.backup}). ` +
      (r.restart ? "Restart the service for the drives' change, then commission again."
        : "In force now: commission again to see it right.");
  } catch (e) {
    $("com-accepted").textContent = "Not written: " + e.message;
  } finally {
    $("com-accept").disabled = false;
  }
}

async function showDrives() {
  if (app.live && app.live.drives) renderDrives(app.live.drives);
  try {
    renderDrives(await api("GET", "/drives"));
  } catch (e) {
    $("drv-summary").textContent = "No drives: " + e.message;
  }
}
function renderDrives(doc) {
  const down = doc.axes.filter((a) => a.alive === false).length;
  const faults = doc.axes.filter((a) => a.fault).length;
  const alive = doc.axes.filter((a) => a.alive === true).length;
  $("drv-summary").replaceChildren(
    `${doc.kind} drives on ${doc.bus} · driver ${doc.driver} · ${doc.axes.length} axes: ` +
    (doc.watched ? `${alive} alive` : "liveness unknown") + " · ",
    down || faults ? el("span", { class: "chip bad", id: "drv-verdict" },
      [down ? `${down} without heartbeat` : "", faults ? `${faults} in fault` : ""].filter(Boolean).join(", "))
      : el("span", { class: "chip ok", id: "drv-verdict" }, "no fault"),
    doc.fault_cause ? ` · last stopped on: ${doc.fault_cause}` : "");
  const yesNo = (v) => (v === null ? el("td", { class: "muted" }, "unknown") :
    el("td", { class: v ? "yes" : "no" }, v ? "yes" : "no"));
  // a name in capitals (CYCLIC_SYNC_POSITION, OVER_TEMPERATURE|WATCHDOG_TIMEOUT) may wrap
  // after its underscores and bars in a narrow window, never inside a word
  const words = (t) => t.split(/(?<=[_|])/).flatMap((w, i) => (i ? [el("wbr"), w] : [w]));
  $("drive-rows").replaceChildren(...doc.axes.map((a) => {
    const bad = a.fault || a.alive === false;
    const age = a.heartbeat_age_s === null ? "none yet" : `${(a.heartbeat_age_s * 1000).toFixed(0)} ms ago`;
    const state = [a.nmt, a.state].filter((x) => x !== null).join(" · ") || "–";
    const code = a.error && !a.error_name.startsWith("0x") ? ` (0x${a.error.toString(16).padStart(4, "0")})` : "";
    const error = !a.error ? el("td", {}, a.error === null ? "–" : "none") :
      el("td", { class: a.fault ? "no" : "" }, a.fault ? "FAULT: " : "", ...words(a.error_name),
        el("span", { class: "mono" }, code));
    return el("tr", { "data-axis": `${a.module}.${a.axis}`, class: bad ? "bad" : "" },
      el("th", { scope: "row" }, `${a.module} ${a.axis}`), el("td", { class: "num" }, a.node),
      yesNo(a.alive), el("td", { class: "num" }, age), el("td", {}, ...words(state)),
      el("td", {}, ...words(a.mode ?? "–")), error,
      a.homed === null ? el("td", { class: "muted" }, a.axis === "wheel" ? "n/a" : "–") : yesNo(a.homed));
  }));
  $("drv-unwatched").hidden = doc.watched || !doc.axes.length;
  $("drv-modules").hidden = doc.axis_detail || doc.driver === "not open";
}

// ------------------------------------------------------------------ event stream
// With the token the stream is read with fetch (EventSource cannot send a header): the
// service keeps room for the operator's streams, and a client without the token holds
// only a few. Without it, EventSource. Either way: named events, ids, Last-Event-ID when
// it reconnects, the service's retry.
function openStream(url, token, handlers, onState) {
  if (!token) {
    const es = new EventSource(url);
    es.onopen = () => onState(true);
    es.onerror = () => onState(false);
    for (const [name, fn] of Object.entries(handlers)) es.addEventListener(name, (ev) => fn(ev.data));
    return { token, close: () => es.close() };
  }
  let closed = false, lastId = null, retry = 1000, ctrl = null;
  const dispatch = (ev) => { if (ev.data.length && handlers[ev.name]) handlers[ev.name](ev.data.join("\n")); };
  function field(ev, line) {
    if (line.startsWith(":")) return;
    const c = line.indexOf(":");
    const name = c < 0 ? line : line.slice(0, c);
    let v = c < 0 ? "" : line.slice(c + 1);
    if (v.startsWith(" ")) v = v.slice(1);
    if (name === "data") ev.data.push(v);
    else if (name === "event") ev.name = v;
    else if (name === "id") lastId = v;
    else if (name === "retry" && /^\d+$/.test(v)) retry = Number(v);
  }
  async function read(r) {
    const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "", ev = { name: "message", data: [] };
    for (;;) {
      const { value, done } = await reader.read();
      if (done) return;
      buf += value;
      let nl;
      while ((nl = buf.search(/[\r\n]/)) >= 0) {
        if (buf[nl] === "\r" && nl === buf.length - 1) break;  // its \n may follow
        const line = buf.slice(0, nl);
        buf = buf.slice(nl + (buf[nl] === "\r" && buf[nl + 1] === "\n" ? 2 : 1));
        if (line === "") { dispatch(ev); ev = { name: "message", data: [] }; } else field(ev, line);
      }
    }
  }
  (async () => {
    while (!closed) {
      ctrl = new AbortController();
      try {
        const headers = { Authorization: "Bearer " + token, Accept: "text/event-stream" };
        if (lastId !== null) headers["Last-Event-ID"] = lastId;
        const r = await fetch(url, { headers, signal: ctrl.signal, cache: "no-store" });
        if (!r.ok || !r.body) throw new Error("HTTP " + r.status);
        onState(true);
        await read(r);
      } catch (e) {
        if (closed) return;
      }
      onState(false);
      await new Promise((resolve) => setTimeout(resolve, retry));
    }
  })();
  return { token, close: () => { closed = true; if (ctrl) ctrl.abort(); } };
}

function connect() {
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (app.stream) {
    if (app.stream.token === token) return;
    app.stream.close();
  }
  const state = $("link-state");
  const onState = (live) => {
    state.textContent = live ? "live" : "reconnecting…";
    state.className = live ? "pill ok" : "pill bad";
  };
  app.stream = openStream("/events", token, {
    hello: (data) => {
      const first = !app.hello;
      app.hello = JSON.parse(data);
      $("robot-name").textContent = "· robot " + app.hello.robot + (app.hello.in_process_simulator ? " (simulator)" : "");
      if (first) {
        fillDefaults(app.hello.protocol);
        $("f-metrology").value = app.hello.metrology;
        buildTape();
        showMetrology();
      }
    },
    run: (data) => onRun(JSON.parse(data), true),
    live: (data) => onLive(JSON.parse(data)),
  }, onState);
}

document.addEventListener("DOMContentLoaded", () => {
  $("start-form").addEventListener("submit", start);
  $("tape-sim").addEventListener("click", readSimulatorAxes);
  $("f-check-metrology").addEventListener("change", showCheckHint);
  showCheckHint();
  $("bar-answer").addEventListener("click", () => {
    if (!location.hash.startsWith("#run") && location.hash !== "") { location.hash = "#run"; route(); }
    $("operator").scrollIntoView({ block: "center" });
    const first = app.current && app.current.waits_for === "continue" ? "op-continue" : "op-distance";
    $(first).focus();
  });
  // an error is about what was sent: gone once the operator changes the form
  $("start-form").addEventListener("input", () => { $("start-error").textContent = ""; });
  $("f-plan").addEventListener("change", showPlan);
  $("check").addEventListener("click", startCheck);
  $("f-metrology").addEventListener("change", showMetrology);
  $("op-continue").addEventListener("click", () => answerRun("continue"));
  $("op-measure").addEventListener("submit", sendMeasurement);
  $("op-sim-tape").addEventListener("click", readSimulatorTape);
  $("abort").addEventListener("click", abortRun);
  $("res-install").addEventListener("click", installResult);
  $("com-start").addEventListener("click", startCommission);
  $("com-accept").addEventListener("click", acceptCommission);
  $("token-button").addEventListener("click", () => tokenDialog("Enter the service's bearer token (kept for this tab)."));
  window.addEventListener("hashchange", route);
  updateTokenButton();
  route();
  connect();
});
