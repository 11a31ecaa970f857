// swpc fleet page: GET /robots every REFRESH_MS, GET /robots/{name} for the selected one.
"use strict";
const REFRESH_MS = 2000;
const SCALE = { x_s: [1000, "mm"], y_s: [1000, "mm"], b: [1000, "mm"], r: [1000, "mm"],
  beta: [180 / Math.PI, "deg"] };
let selected = decodeURIComponent(location.hash.slice(1)) || null;

function el(tag, attrs, ...kids) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) e.setAttribute(k, v);
  for (const k of kids) e.append(k instanceof Node ? k : document.createTextNode(String(k)));
  return e;
}
function fmt(v, param, digits) {
  if (v === null || v === undefined) return "–";
  return (v * SCALE[param][0]).toFixed(digits === undefined ? 3 : digits);
}
function ago(s) {
  if (s < 60) return `${s.toFixed(0)} s ago`;
  if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
  if (s < 86400 * 2) return `${(s / 3600).toFixed(1)} h ago`;
  return `${(s / 86400).toFixed(0)} days ago`;
}
function largest(drift) {
  // the parameter that moved most, relative to its first value's unit (mm or deg)
  let best = null;
  for (const d of drift) {
    const c = Math.abs(d.change * SCALE[d.param][0]);
    if (best === null || c > best.c) best = { c, d };
  }
  if (best === null || best.c === 0) return "none";
  const d = best.d;
  return `module ${d.module} ${d.param} ${d.change >= 0 ? "+" : ""}${fmt(d.change, d.param)} ${SCALE[d.param][1]}`;
}
function spark(points, param) {
  const w = 160, h = 32, pad = 3;
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.setAttribute("viewBox", `0 0 ${w} ${h}`);
  svg.setAttribute("width", w); svg.setAttribute("height", h);
  svg.setAttribute("role", "img");
  svg.setAttribute("aria-label", `${param} over ${points.length} calibrations`);
  const v = points.map((p) => p.value);
  const lo = Math.min(...v), hi = Math.max(...v), span = hi - lo || 1;
  const x = (i) => pad + (points.length > 1 ? (i * (w - 2 * pad)) / (points.length - 1) : (w - 2 * pad) / 2);
  const y = (val) => h - pad - ((val - lo) * (h - 2 * pad)) / span;
  const line = document.createElementNS(svg.namespaceURI, "polyline");
  line.setAttribute("points", v.map((val, i) => `${x(i)},${y(val)}`).join(" "));
  line.setAttribute("fill", "none"); line.setAttribute("stroke", "#0b4fa8"); line.setAttribute("stroke-width", "2");
  svg.append(line);
  v.forEach((val, i) => {
    const c = document.createElementNS(svg.namespaceURI, "circle");
    c.setAttribute("cx", x(i)); c.setAttribute("cy", y(val)); c.setAttribute("r", "2.5");
    c.setAttribute("fill", "#111"); svg.append(c);
  });
  return svg;
}
function statusCell(r) {
  const chip = el("span", { class: `chip ${r.status === "live" ? "ok" : "bad"}`, "data-status": r.status },
    r.status);
  const td = el("td", {}, chip);
  if (r.stale_reason) td.append(el("div", { class: "muted" }, r.stale_reason));
  return td;
}
function robotRow(r) {
  const name = el("a", { href: `#${encodeURIComponent(r.robot)}`, class: "mono name" }, r.robot);
  // the robot's own console, where its operator starts and aborts runs (SWPC_FLEET_CONSOLE_URL)
  const consoleLink = r.console_url ? el("a", { href: r.console_url, class: "console-link",
    target: "_blank", rel: "noopener" }, "console") : null;
  const f = r.file_in_force;
  const file = f === null ? "none" : f.error ? `unreadable: ${f.error}` :
    `${f.created || "?"}${f.run ? ` (run ${f.run})` : " (by hand)"}`;
  const chk = r.last_check === null ? "none yet" : (r.last_check.verdict || JSON.stringify(r.last_check));
  // a stale robot's health is its last word, not its state now: said so
  const health = !r.health ? "–" : r.status === "live" ? r.health.status
    : `unknown now (last said ${r.health.status}, ${ago(r.age_s)})`;
  return el("tr", { "data-robot": r.robot },
    el("th", { scope: "row" }, name, ...(consoleLink ? [consoleLink] : [])), statusCell(r),
    el("td", {}, `${r.last_seen} (${ago(r.age_s)})`), el("td", {}, file), el("td", {}, chk),
    el("td", {}, health), el("td", { class: "num" }, r.calibrations), el("td", {}, largest(r.drift)));
}
async function refresh() {
  const state = document.getElementById("link-state");
  try {
    const res = await fetch("/robots", { cache: "no-store" });
    if (!res.ok) throw new Error(res.statusText);
    const robots = await res.json();
    const rows = document.getElementById("robot-rows");
    rows.replaceChildren(...(robots.length ? robots.map(robotRow) :
      [el("tr", {}, el("td", { colspan: "8" }, "no robot has published yet"))]));
    const live = robots.filter((r) => r.status === "live").length;
    document.getElementById("fleet-counts").textContent =
      `${robots.length} robots, ${live} live, ${robots.length - live} stale`;
    state.textContent = "connected"; state.className = "pill ok";
    if (!selected && robots.length) selected = robots[0].robot;
    if (selected) await showDrift(selected);
  } catch (err) {
    state.textContent = "fleet service unreachable"; state.className = "pill bad";
  }
}
async function showDrift(name) {
  const res = await fetch(`/robots/${encodeURIComponent(name)}`, { cache: "no-store" });
  const sec = document.getElementById("drift");
  if (!res.ok) { sec.hidden = true; return; }
  const r = await res.json();
  document.getElementById("drift-robot").textContent = r.robot;
  document.getElementById("drift-facts").textContent =
    `${r.calibrations} calibrations, ${r.documents} states kept, service ${r.version || "?"}; status ${r.status}`;
  const rows = r.drift.map((d) => el("tr", {},
    el("td", { class: "num" }, d.module), el("td", {}, `${d.param} (${SCALE[d.param][1]})`),
    el("td", { class: "num" }, fmt(d.first, d.param)), el("td", { class: "num" }, fmt(d.last, d.param)),
    el("td", { class: "num" }, fmt(d.change, d.param)),
    el("td", { class: "num" }, d.per_week === null ? "–" : `${fmt(d.per_week, d.param)} ${SCALE[d.param][1]}/week`),
    el("td", {}, spark(d.points, d.param))));
  document.getElementById("drift-rows").replaceChildren(...rows);
  sec.hidden = false;
}
window.addEventListener("hashchange", () => {
  selected = decodeURIComponent(location.hash.slice(1)) || selected;
  refresh();
});
refresh();
setInterval(refresh, REFRESH_MS);
