"use strict";
// The operator's page: draws the site from /api/site, keeps it live from /api/events (server-sent events),
// and steers through the JSON API with the session's CSRF token. Map y points up; SVG y points down: every
// world point (x, y) is drawn at (x, -y).

const SVG = "http://www.w3.org/2000/svg";
const state = { zones: {}, nodes: {}, robots: {}, blocks: {}, trails: {}, alerts: [], offset: 0, connected: true, streamOk: true };
let geo = null;
let csrf = null;
let mode = null; // {kind: "goal", robot} | {kind: "confirm", robot, pose} | {kind: "rect", start} | {kind: "poly", points: []}
let home = null; // the whole map's viewBox [x, y, w, h] (SVG coordinates: y down)
let view = null; // the part shown: zoom and pan change it
const MAX_ZOOM = 20;
let zoom = 1;

// A marker (a point, a node, a robot, a label) keeps its size on the screen whatever the zoom: drawn around
// (0, 0) as at zoom 1, and placed at the world point (x, y).
function marker(parent, x, y, attrs) {
  const g = el("g", { ...attrs, class: `marker ${(attrs && attrs.class) || ""}` }, parent);
  placeMarker(g, x, y);
  return g;
}
function placeMarker(g, x, y) {
  if (x !== undefined) {
    g.dataset.x = x;
    g.dataset.y = y;
  }
  g.setAttribute("transform", `translate(${g.dataset.x} ${-g.dataset.y}) scale(${1 / zoom})`);
}
// The numerous fixed markers (nodes, named points, zone labels) are placed by their own attributes, with no
// transform each: 1500 transforms were 1500 paint chunks, which Chromium layerized again on every frame a robot
// moved. Their sizes follow the zoom: [element, attribute, value at zoom 1].
const sized = [];
function size(node, attr, value) {
  sized.push([node, attr, value]);
  node.setAttribute(attr, value / zoom);
  return node;
}
const $ = (id) => document.getElementById(id);

function el(tag, attrs, parent) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs || {})) node.setAttribute(k, v);
  if (parent) parent.appendChild(node);
  return node;
}
const pts = (poly) => poly.map(([x, y]) => `${x},${-y}`).join(" ");
const serverNow = () => Date.now() / 1000 + state.offset;
const fmtAge = (s) => (s == null ? "never" : s < 60 ? `${s.toFixed(0)} s` : s < 3600 ? `${(s / 60).toFixed(0)} min` : `${(s / 3600).toFixed(1)} h`);

function worldFromEvent(ev) {
  const svg = $("map");
  const p = svg.createSVGPoint();
  p.x = ev.clientX;
  p.y = ev.clientY;
  const w = p.matrixTransform(svg.getScreenCTM().inverse());
  return [Math.round(w.x * 100) / 100, Math.round(-w.y * 100) / 100];
}
// For tests and scripts: where on the screen a world point is drawn.
window.worldToClient = function (x, y) {
  const svg = $("map");
  const p = svg.createSVGPoint();
  p.x = x;
  p.y = -y;
  const s = p.matrixTransform(svg.getScreenCTM());
  return [s.x, s.y];
};

// An action's error is shown next to the control that acted (`near`), in view: the one error line moves there.
function showError(text, near) {
  let box = $("action-error");
  if (!box) {
    // it left with the row it was shown in (a block lifted): a new one
    box = document.createElement("p");
    Object.assign(box, { id: "action-error", className: "error" });
    box.setAttribute("role", "alert");
    (near || $("map-pane")).appendChild(box);
  }
  if (near && near.tagName === "TD") near.appendChild(box);
  else if (near && box.previousElementSibling !== near) near.insertAdjacentElement("afterend", box);
  box.textContent = text;
  if (text) box.scrollIntoView({ block: "nearest" });
}

async function api(method, path, body, near) {
  const res = await fetch(path, {
    method,
    headers: { "Content-Type": "application/json", "X-CSRF-Token": csrf || "" },
    body: body === undefined ? undefined : JSON.stringify(body),
  }).catch(() => null);
  const data = res ? await res.json().catch(() => ({})) : {};
  showError(res && res.ok ? "" : data.error || (res ? `${method} ${path}: ${res.status}` : "the console is not reachable"), near);
  if (res && res.status === 401) window.location.assign("/login");
  return res && res.ok ? data : null;
}

// -- drawing --------------------------------------------------------------------------------------------

function drawSite() {
  const [x0, y0, x1, y1] = geo.bounds;
  const w = x1 - x0, h = y1 - y0;
  const svg = $("map");
  home = [x0, -y1, w, h];
  setView(home);
  const img = $("map-image");
  Object.entries({ x: x0, y: -y1, width: w, height: h, preserveAspectRatio: "none" }).forEach(([k, v]) => img.setAttribute(k, v));
  const fs = Math.max(w, h) / 70;
  geo.fs = fs;
  geo.robotR = Math.max(fs * 0.9, 0.12); // robots: a disc far larger than a named point (fs / 3)
  svg.style.setProperty("--fs", fs);
  $("site-name").textContent = geo.site;
  const zl = $("layer-zones");
  const select = $("block-zone");
  for (const z of geo.zones) {
    el("polygon", { points: pts(z.polygon), class: "zone unknown", id: `zone-${z.id}`, "data-state": "unknown" }, zl);
    const cx = z.polygon.reduce((a, p) => a + p[0], 0) / z.polygon.length;
    const cy = z.polygon.reduce((a, p) => a + p[1], 0) / z.polygon.length;
    size(el("text", { class: "zone-label", x: cx, y: -cy, "text-anchor": "middle" }, zl), "font-size", fs).textContent = z.id;
    const opt = document.createElement("option");
    opt.value = opt.textContent = z.id;
    select.appendChild(opt);
  }
  const pl = $("layer-points");
  for (const [name, [x, y]] of Object.entries(geo.points)) {
    size(el("circle", { cx: x, cy: -y, class: "point" }, pl), "r", fs / 3);
    const label = size(size(el("text", { x, y: -y, class: "point-label" }, pl), "dx", fs / 2), "font-size", fs);
    label.textContent = name;
  }
  const nl = $("layer-nodes");
  for (const n of geo.nodes) {
    size(el("circle", { cx: n.position[0], cy: -n.position[1], class: "node silent", id: `node-${n.id}` }, nl), "r", fs / 4);
  }
}

function renderZone(z) {
  state.zones[z.id] = z;
  dirty.zones.add(z.id);
  drawDue.zones.add(z.id);
}
function drawZone(id) {
  const z = state.zones[id];
  const poly = $(`zone-${id}`);
  if (z && poly) {
    setAttr(poly, "class", `zone ${z.state}` + (z.stale_nodes.length ? " has-stale" : ""));
    setAttr(poly, "data-state", z.state);
    setAttr(poly, "data-stale", z.stale_nodes.join(" "));
  }
}
// An attribute written only when it changes: an unchanged write still costs Chromium a style pass.
function setAttr(node, name, value) {
  if (node.getAttribute(name) !== value) node.setAttribute(name, value);
}

function nodeClass(n) {
  if (n.online === false) return "offline";
  if (n.heard_at == null) return "silent";
  return n.fresh ? "online" : "stale";
}

function renderNode(n) {
  state.nodes[n.id] = n;
  dirty.nodes.add(n.id);
  drawDue.nodes.add(n.id);
}
function drawNode(id) {
  const n = state.nodes[id];
  const dot = $(`node-${id}`);
  if (n && dot) {
    setAttr(dot, "class", `node ${nodeClass(n)}`);
    setAttr(dot, "data-online", String(n.online));
  }
}

function renderRobot(r) {
  state.robots[r.id] = r;
  dirty.robots.add(r.id);
  if (!r.pose) return;
  const trail = (state.trails[r.id] = state.trails[r.id] || []);
  if (r.trail) trail.splice(0, trail.length, ...r.trail.map(([x, y]) => [x, y, r.t || 0]));
  else trail.push([r.pose[0], r.pose[1], r.t || serverNow()]);
  const horizon = (r.t || serverNow()) - 300;
  while (trail.length && trail[0][2] && trail[0][2] < horizon) trail.shift();
  drawDue.robots.add(r.id);
}
function drawRobot(id) {
  const r = state.robots[id];
  if (!r || !r.pose) return;
  const trail = state.trails[id] || [];
  const layer = $("layer-robots");
  let g = $(`robot-${r.id}`);
  const R = geo.robotR;
  if (!g) {
    g = el("g", { id: `robot-${r.id}`, class: "robot-group" }, layer);
    el("polyline", { class: "trail" }, g);
    el("polyline", { class: "path" }, g);
    el("circle", { class: "goal", r: R }, marker(g, 0, 0, { class: "goal-mark" }));
    const m = marker(g, 0, 0, { class: "robot-mark" });
    el("circle", { class: "robot", r: R }, m);
    el("polygon", { class: "robot-heading" }, m);
    el("text", { class: "robot-label", x: R * 1.2, y: -R * 1.2, "font-size": geo.fs * 1.2 }, m);
  }
  const [x, y, yaw] = r.pose;
  // a disc with a white arrowhead pointing where the robot faces
  const at = (k, a) => [R * k * Math.cos(yaw + a), R * k * Math.sin(yaw + a)];
  placeMarker(g.querySelector(".robot-mark"), x, y);
  g.querySelector(".robot-heading").setAttribute("points", pts([at(0.85, 0), at(0.6, 2.4), at(0.6, -2.4)]));
  g.querySelector(".trail").setAttribute("points", pts(trail));
  g.querySelector(".path").setAttribute("points", r.path ? pts([r.pose, ...r.path]) : "");
  const goal = g.querySelector(".goal-mark");
  const gp = typeof r.goal === "string" ? geo.points[r.goal] : r.goal;
  if (gp && r.state !== "arrived" && r.state !== "cancelled") {
    placeMarker(goal, gp[0], gp[1]);
    goal.removeAttribute("display");
  } else goal.setAttribute("display", "none");
  g.querySelector(".robot-label").textContent = r.id;
}

function renderBlock(b) {
  state.blocks[b.id] = b;
  dirty.blocks.add(b.id);
  const layer = $("layer-blocks");
  let shape = $(`block-${b.id}`);
  if (!shape) shape = el("polygon", { id: `block-${b.id}`, class: "opblock" }, layer);
  const poly = b.polygon || (geo.zones.find((z) => z.id === b.zone) || {}).polygon;
  shape.setAttribute("points", poly ? pts(poly) : "");
}

function renderAlerts() {
  const list = $("alert-list");
  const ids = new Set(state.alerts.map((a) => a.id));
  for (const li of [...list.querySelectorAll("li")]) if (!ids.has(li.dataset.id)) li.remove();
  for (const a of state.alerts) {
    let li = list.querySelector(`li[data-id="${a.id}"]`);
    if (!li) {
      li = document.createElement("li");
      li.dataset.id = a.id;
      li.id = `alert-${a.id}`;
      const text = document.createElement("span");
      text.className = "alert-text";
      li.appendChild(text);
      const when = document.createElement("span");
      when.className = "alert-when";
      li.appendChild(when);
      const ack = button(li, "Acknowledge", "ack", () => api("POST", `/api/alerts/${a.id}/ack`, {}, list));
      ack.setAttribute("aria-label", `acknowledge: ${a.text}`);
      list.appendChild(li);
    }
    li.className = `alert ${a.kind}` + (a.acknowledged ? " acked" : "");
    li.dataset.acknowledged = String(a.acknowledged);
    setText(li.querySelector(".alert-text"), a.text);
    const ack = li.querySelector(".ack");
    ack.hidden = a.acknowledged;
  }
  $("alerts").hidden = state.alerts.length === 0;
  const open = state.alerts.filter((a) => !a.acknowledged).length;
  $("alerts-title").textContent = open ? `Alerts (${open} to acknowledge)` : "Alerts (all acknowledged)";
  $("alerts-ack-all").hidden = open < 2;
  renderAlertTimes();
}

function renderAlertTimes() {
  const now = serverNow();
  for (const a of state.alerts) {
    const li = document.getElementById(`alert-${a.id}`);
    if (!li) continue;
    const when = a.until != null ? `in ${fmtAge(Math.max(0, a.until - now))}` : `${fmtAge(Math.max(0, now - a.since))} ago`;
    setText(li.querySelector(".alert-when"), (a.acknowledged ? "acknowledged, " : "") + when);
  }
}

const MAX_EVENTS_SHOWN = 50;
function renderEvent(e) {
  drawDue.events.push(e);
  if (drawDue.events.length > MAX_EVENTS_SHOWN) drawDue.events.splice(0, drawDue.events.length - MAX_EVENTS_SHOWN);
}
// The frame's new events in one append and one scroll: reading scrollHeight after each event forced a layout of
// the whole page per event.
function drawEvents() {
  if (!drawDue.events.length) return;
  const list = $("events");
  const items = drawDue.events.map((e) => {
    const li = document.createElement("li");
    li.className = `event ${e.kind}`;
    li.textContent = `${new Date(e.t * 1000).toLocaleTimeString()}  ${e.text}`;
    return li;
  });
  drawDue.events = [];
  list.append(...items);
  while (list.children.length > MAX_EVENTS_SHOWN) list.firstElementChild.remove();
  list.scrollTop = 1e9; // the end: the browser clamps it, no height read
}

function dropBlock(id) {
  delete state.blocks[id];
  dirty.blocks.add(id);
  const shape = $(`block-${id}`);
  if (shape) shape.remove();
}

// -- tables: rows are made once per entry and updated in place (a thousand nodes cost no rebuild) ----------

const dirty = { robots: new Set(), blocks: new Set(), zones: new Set(), nodes: new Set() };
// What the map and the events list still have to draw: drawn together in the next animation frame.
const drawDue = { zones: new Set(), nodes: new Set(), robots: new Set(), events: [] };

function setText(td, text, cls) {
  const value = String(text);
  if (td.textContent !== value) td.textContent = value;
  if (cls !== undefined && td.className !== cls) td.className = cls;
}
function button(parent, label, cls, onClick) {
  const b = document.createElement("button");
  b.type = "button";
  b.textContent = label;
  b.className = cls;
  b.addEventListener("click", onClick);
  parent.appendChild(b);
  return b;
}
function row(table, id, cells) {
  let tr = document.getElementById(id);
  if (!tr) {
    tr = table.tBodies[0].insertRow();
    tr.id = id;
    for (let i = 0; i < cells; i++) tr.insertCell();
  }
  return tr;
}

function robotRow(r) {
  const isNew = !document.getElementById(`robot-row-${r.id}`);
  const tr = row($("robots"), `robot-row-${r.id}`, 7);
  if (isNew) {
    const actions = tr.cells[6];
    const pick = document.createElement("select");
    pick.setAttribute("aria-label", `goal for ${r.id}`);
    pick.add(new Option("go to...", ""));
    for (const name of Object.keys(geo.points)) pick.add(new Option(name, name));
    actions.appendChild(pick);
    // Choosing a point (arrow keys included) sends nothing: the operator confirms with "Go".
    const go = button(actions, "Go", "go", async () => {
      if (!pick.value) return;
      const sent = await api("POST", `/api/robots/${r.id}/goal`, { point: pick.value }, actions);
      if (sent) pick.value = "";
      go.disabled = !pick.value;
    });
    go.disabled = true;
    go.setAttribute("aria-label", `send ${r.id} to the chosen point`);
    pick.addEventListener("change", () => (go.disabled = !pick.value));
    button(actions, "Click goal", "click-goal", () => setMode({ kind: "goal", robot: r.id }));
    button(actions, "Cancel", "cancel", () => api("POST", `/api/robots/${r.id}/cancel`, undefined, actions));
  }
  const c = tr.cells;
  setText(c[0], r.id);
  setText(c[1], r.state ? r.state + (r.reason ? `: ${r.reason}` : "") : "no status", "robot-state");
  setText(c[2], r.goal == null ? "" : typeof r.goal === "string" ? r.goal : r.goal.slice(0, 2).map((v) => v.toFixed(1)).join(", "));
  setText(c[3], r.replans ?? "", "robot-replans");
  setText(c[4], (r.blocked_zones || []).join(" "));
}

function blockRow(b) {
  const isNew = !document.getElementById(`block-row-${b.id}`);
  const tr = row($("blocks"), `block-row-${b.id}`, 5);
  if (isNew) {
    button(tr.cells[4], "Lift", "lift", () => api("DELETE", `/api/blocks/${b.id}`, undefined, tr.cells[4]));
    // the same block, expiring later: robots never see the area clear in between
    const ext = button(tr.cells[4], "Extend", "extend", () => {
      const s = durationS(tr.cells[4]);
      if (s != null) api("POST", `/api/blocks/${b.id}/extend`, { for_s: s }, tr.cells[4]);
    });
    ext.title = "extend by the duration in the form above (e.g. 10m)";
    ext.setAttribute("aria-label", `extend block ${b.id} by the duration in the form`);
  }
  tr.cells[4].querySelector(".extend").disabled = b.expires_at == null;
  setText(tr.cells[0], b.id);
  setText(tr.cells[1], b.zone || `polygon of ${b.polygon.length}`);
  setText(tr.cells[3], b.reason || "");
}

function zoneRow(z) {
  const tr = row($("zones"), `zone-row-${z.id}`, 3);
  setText(tr.cells[0], z.id);
  const note = [z.operator_blocks.length ? "operator" : "", z.stale_nodes.length ? `stale: ${z.stale_nodes.join(" ")}` : ""].filter(Boolean);
  setText(tr.cells[1], z.state + (note.length ? ` (${note.join("; ")})` : ""), `state-${z.state}`);
  setText(tr.cells[2], z.nodes.join(" "));
}

// The zones and nodes lists are written only while they are in view: a changed row of a list below the fold
// cost Chromium a layout of its whole table (up to 50 ms with 500 zones); a list scrolled into view is brought up
// to date in the next frame. Node rows in view: the clock redraws only their ages (a thousand rows rewritten
// every second cost Chromium a layout of the whole list); rows scrolled into view get theirs at once. One
// observer watches the lists (one per row cost a thousand intersections each frame); the rows shown are found by
// their offsets.
const listInView = { "zones-list": false, "nodes-list": false };
let nodesListInView = false;
const listObserver = new IntersectionObserver((entries) => {
  for (const e of entries) listInView[e.target.id] = e.isIntersecting;
  nodesListInView = listInView["nodes-list"];
  if (nodesListInView) scheduleAges();
  if (entries.some((e) => e.isIntersecting)) {
    tablesReady = true;
    scheduleFrame();
  }
});
listObserver.observe($("zones-list"));
listObserver.observe($("nodes-list"));
$("nodes-list").addEventListener("scroll", () => scheduleAges(), { passive: true });
let agesDue = false;
function scheduleAges() {
  if (agesDue) return;
  agesDue = true;
  requestAnimationFrame(() => {
    agesDue = false;
    const now = serverNow();
    for (const tr of nodeRowsShown()) if (state.nodes[tr.id.slice(9)]) nodeAge(tr, state.nodes[tr.id.slice(9)], now);
  });
}
// Read at the start of a frame (layout is clean then), before any write.
function nodeRowsShown() {
  const rows = $("nodes").tBodies[0].rows;
  if (!nodesListInView || !rows.length) return [];
  if ($("filter").value.trim()) return [...rows].filter((tr) => !tr.hidden);
  const list = $("nodes-list");
  const top = list.scrollTop, bottom = top + list.clientHeight;
  let lo = 0, hi = rows.length - 1; // the first row not wholly above the list's top (rows go down in order)
  while (lo < hi) {
    const mid = (lo + hi) >> 1;
    if (rows[mid].offsetTop + rows[mid].offsetHeight < top) lo = mid + 1;
    else hi = mid;
  }
  const shown = [];
  for (let i = lo; i < rows.length && rows[i].offsetTop <= bottom; i++) shown.push(rows[i]);
  return shown;
}
function nodeAge(tr, n, now) {
  setText(tr.cells[4], n.heard_at == null ? "never" : `${fmtAge(Math.max(0, now - n.heard_at))} ago`);
}

function nodeRow(n) {
  const tr = row($("nodes"), `node-row-${n.id}`, 6);
  nodeAge(tr, n, serverNow());
  const link = n.online === false ? "offline" : n.online ? (n.fresh ? "online" : "silent") : "unknown";
  setText(tr.cells[0], n.id);
  setText(tr.cells[1], n.zone);
  setText(tr.cells[2], n.state || "");
  setText(tr.cells[3], link, n.online === false ? "offline link" : "link");
  setText(tr.cells[5], n.info ? Object.entries(n.info).map(([k, v]) => `${k}=${v}`).join(" ") : "", "info");
}

function renderTables() {
  for (const id of dirty.robots) if (state.robots[id]) robotRow(state.robots[id]);
  for (const id of dirty.blocks) {
    if (state.blocks[id]) blockRow(state.blocks[id]);
    else document.getElementById(`block-row-${id}`)?.remove();
  }
  dirty.robots.clear();
  dirty.blocks.clear();
  if (listInView["zones-list"]) {
    for (const id of dirty.zones) if (state.zones[id]) zoneRow(state.zones[id]);
    dirty.zones.clear();
  }
  if (listInView["nodes-list"]) {
    for (const id of dirty.nodes) if (state.nodes[id]) nodeRow(state.nodes[id]);
    dirty.nodes.clear();
  }
}

function renderClock() {
  // Once a second, in an animation frame: the ages and times left, which change without any message.
  const shownNodeRows = nodeRowsShown();
  const now = serverNow();
  for (const r of Object.values(state.robots)) {
    const tr = document.getElementById(`robot-row-${r.id}`);
    if (tr) setText(tr.cells[5], r.t ? fmtAge(Math.max(0, now - r.t)) : "");
  }
  for (const b of Object.values(state.blocks)) {
    const tr = document.getElementById(`block-row-${b.id}`);
    if (tr) setText(tr.cells[2], b.expires_at == null ? "until lifted" : fmtAge(Math.max(0, b.expires_at - now)), "left");
  }
  for (const tr of shownNodeRows) if (state.nodes[tr.id.slice(9)]) nodeAge(tr, state.nodes[tr.id.slice(9)], now);
  const counts = Object.values(state.zones).reduce((a, z) => ((a[z.state] = (a[z.state] || 0) + 1), a), {});
  setText($("counts"), Object.entries(counts).map(([k, v]) => `${v} ${k}`).join(", "));
  setText($("clock"), new Date(now * 1000).toLocaleTimeString());
  renderAlertTimes();
}

function applyFilter() {
  const filter = $("filter").value.trim().toLowerCase();
  for (const tr of $("zones").tBodies[0].rows) tr.hidden = !!filter && !tr.id.slice(9).toLowerCase().includes(filter);
  for (const tr of $("nodes").tBodies[0].rows) {
    const n = state.nodes[tr.id.slice(9)];
    tr.hidden = !!filter && !(n && (n.id.toLowerCase().includes(filter) || n.zone.toLowerCase().includes(filter)));
  }
}

// Tables at most every 300 ms, drawn in an animation frame with the map.
let tablesDue = false;
let tablesReady = false;
function scheduleTables() {
  if (tablesDue) return;
  tablesDue = true;
  setTimeout(() => {
    tablesDue = false;
    tablesReady = true;
    scheduleFrame();
  }, 300);
}

// Every update of the feed lands in state at once and is drawn in one animation frame: a burst of messages costs
// one style and layout pass, and nothing reads layout between writes (the events list scrolls last).
let frameDue = false;
function scheduleFrame() {
  if (frameDue) return;
  frameDue = true;
  requestAnimationFrame(drawFrame);
}
function drawFrame() {
  frameDue = false;
  for (const id of drawDue.zones) drawZone(id);
  for (const id of drawDue.nodes) drawNode(id);
  for (const id of drawDue.robots) drawRobot(id);
  drawDue.zones.clear();
  drawDue.nodes.clear();
  drawDue.robots.clear();
  if (tablesReady) {
    tablesReady = false;
    renderTables();
    if ($("filter").value) applyFilter();
  }
  renderBanner();
  drawEvents();
}

function renderBanner() {
  const banner = $("banner");
  const why = !state.streamOk ? "Lost the console server: reconnecting..." : state.linkError ? `The console is blind: ${state.linkError}` : !state.connected ? "The MQTT broker is not reachable: the console reconnects by itself; what you see may be out of date." : "";
  if (banner.hidden !== !why) banner.hidden = !why;
  setText(banner, why);
}

// -- the feed -------------------------------------------------------------------------------------------

function apply(ev) {
  if (ev.now) state.offset = ev.now - Date.now() / 1000;
  if (ev.broker_connected !== undefined) state.connected = ev.broker_connected;
  if (ev.type === "snapshot" || ev.type === "link") state.linkError = ev.link_error || null;
  if (ev.type === "snapshot") {
    for (const id of Object.keys(state.blocks)) dropBlock(id);
    state.trails = {};
  }
  (ev.zones || []).forEach(renderZone);
  (ev.nodes || []).forEach(renderNode);
  for (const [id, [seq, heardAt]] of Object.entries(ev.heard || {})) {
    const n = state.nodes[id]; // a heartbeat that changed nothing else: its age is redrawn once a second
    if (n) Object.assign(n, { seq, heard_at: heardAt });
  }
  (ev.robots || []).forEach(renderRobot);
  (ev.blocks || []).forEach(renderBlock);
  (ev.gone || []).forEach(dropBlock);
  if (ev.type === "snapshot") {
    $("events").replaceChildren();
    drawDue.events = [];
  }
  if (ev.alerts) {
    state.alerts = ev.alerts;
    renderAlerts();
  }
  (ev.events || []).forEach(renderEvent);
  scheduleFrame();
  scheduleTables();
}

function connect() {
  const source = new EventSource("/api/events");
  source.onmessage = (msg) => {
    state.streamOk = true;
    apply(JSON.parse(msg.data));
  };
  source.onerror = async () => {
    state.streamOk = false;
    renderBanner();
    // EventSource retries by itself, but not after an answer other than 200 (a console still starting): then
    // open a new one within a second or two. Only a session the console no longer knows goes to the login.
    const res = await fetch("/api/session").catch(() => null);
    if (res && res.status === 401) window.location.assign("/login");
    else if (source.readyState === EventSource.CLOSED) setTimeout(connect, 1500);
  };
}

// -- zoom and pan: the SVG's viewBox is the part of the map shown ------------------------------------------

function setView(v) {
  const [, , hw, hh] = home;
  let [x, y, w, h] = v;
  const scale = Math.min(1, Math.max(1 / MAX_ZOOM, w / hw));
  const cx = x + w / 2, cy = y + h / 2;
  w = hw * scale;
  h = hh * scale;
  // keep the view's centre on the map
  const mx = Math.min(Math.max(cx, home[0]), home[0] + hw), my = Math.min(Math.max(cy, home[1]), home[1] + hh);
  view = [mx - w / 2, my - h / 2, w, h];
  $("map").setAttribute("viewBox", view.join(" "));
  const was = zoom;
  zoom = hw / w;
  $("map").dataset.zoom = zoom.toFixed(3);
  if (zoom !== was) {
    for (const g of document.querySelectorAll("#world .marker")) placeMarker(g);
    for (const [node, attr, value] of sized) node.setAttribute(attr, value / zoom);
  }
  $("zoom-level").textContent = `${zoom < 10 ? zoom.toFixed(1) : zoom.toFixed(0)}x`;
}

// Zoom by `factor` (> 1: in) keeping the SVG point (sx, sy) where it is on the screen; the view's centre if none.
function zoomAt(factor, sx, sy) {
  const [x, y, w, h] = view;
  if (sx === undefined) [sx, sy] = [x + w / 2, y + h / 2];
  const nw = w / factor, nh = h / factor;
  setView([sx - ((sx - x) / w) * nw, sy - ((sy - y) / h) * nh, nw, nh]);
}

// Pan by a fraction of the view (dx, dy; +x right, +y down on the screen).
function panBy(dx, dy) {
  const [x, y, w, h] = view;
  setView([x + dx * w, y + dy * h, w, h]);
}

function svgPoint(clientX, clientY) {
  const svg = $("map");
  const p = svg.createSVGPoint();
  p.x = clientX;
  p.y = clientY;
  return p.matrixTransform(svg.getScreenCTM().inverse());
}

let panned = false; // the last press dragged the map: its click picks nothing
function setupZoom() {
  const svg = $("map");
  $("zoom-in").addEventListener("click", () => zoomAt(1.5));
  $("zoom-out").addEventListener("click", () => zoomAt(1 / 1.5));
  $("zoom-reset").addEventListener("click", () => setView(home));
  svg.addEventListener(
    "wheel",
    (ev) => {
      ev.preventDefault();
      const p = svgPoint(ev.clientX, ev.clientY);
      zoomAt(Math.exp(-ev.deltaY * (ev.deltaMode === 1 ? 0.05 : 0.002)), p.x, p.y);
    },
    { passive: false },
  );
  svg.addEventListener("keydown", (ev) => {
    const step = 0.1;
    const keys = {
      "+": () => zoomAt(1.5), "=": () => zoomAt(1.5), "-": () => zoomAt(1 / 1.5), "_": () => zoomAt(1 / 1.5),
      "0": () => setView(home),
      ArrowLeft: () => panBy(-step, 0), ArrowRight: () => panBy(step, 0),
      ArrowUp: () => panBy(0, -step), ArrowDown: () => panBy(0, step),
    };
    const act = keys[ev.key];
    if (!act || ev.ctrlKey || ev.metaKey || ev.altKey) return;
    ev.preventDefault();
    act();
  });
  // Drag with one pointer pans (unless drawing a rectangle); two touching fingers pinch-zoom and pan.
  const down = new Map(); // pointerId -> [clientX, clientY]
  let start = null; // {view, points: [[x, y], ...] at the start of the gesture}
  const gesture = () => ({ view: view.slice(), points: [...down.values()].map((p) => p.slice()) });
  svg.addEventListener("pointerdown", (ev) => {
    if (ev.button !== 0 || (mode && mode.kind === "rect")) return;
    down.set(ev.pointerId, [ev.clientX, ev.clientY]);
    start = gesture();
    panned = false;
  });
  svg.addEventListener("pointermove", (ev) => {
    if (!down.has(ev.pointerId) || !start) return;
    down.set(ev.pointerId, [ev.clientX, ev.clientY]);
    const now = [...down.values()];
    if (now.length !== start.points.length) {
      start = gesture();
      return;
    }
    const rect = svg.getBoundingClientRect();
    const perPx = Math.max(start.view[2] / rect.width, start.view[3] / rect.height); // "meet": the larger
    const mid = (ps) => [ps.reduce((a, p) => a + p[0], 0) / ps.length, ps.reduce((a, p) => a + p[1], 0) / ps.length];
    const [m0, m1] = [mid(start.points), mid(now)];
    if (!panned && Math.hypot(m1[0] - m0[0], m1[1] - m0[1]) < 5 && now.length === 1) return;
    panned = true;
    let factor = 1;
    if (now.length === 2) {
      const d = (ps) => Math.hypot(ps[0][0] - ps[1][0], ps[0][1] - ps[1][1]) || 1;
      factor = d(now) / d(start.points);
    }
    const [x, y, w, h] = start.view;
    // the start's midpoint (in SVG units) follows the fingers' midpoint, scaled about it
    const sx = x + w / 2 + (m0[0] - rect.left - rect.width / 2) * perPx;
    const sy = y + h / 2 + (m0[1] - rect.top - rect.height / 2) * perPx;
    const nw = w / factor, nh = h / factor, np = perPx / factor;
    const cx = sx - (m1[0] - rect.left - rect.width / 2) * np;
    const cy = sy - (m1[1] - rect.top - rect.height / 2) * np;
    setView([cx - nw / 2, cy - nh / 2, nw, nh]);
  });
  const up = (ev) => {
    down.delete(ev.pointerId);
    start = down.size ? gesture() : null;
  };
  svg.addEventListener("pointerup", up);
  svg.addEventListener("pointercancel", up);
}

// -- steering -------------------------------------------------------------------------------------------

function setMode(m) {
  mode = m;
  $("layer-draft").replaceChildren();
  const line = $("mode-line");
  if (m && m.kind === "confirm") {
    // Nothing moves a robot until the operator confirms the target the click chose.
    const [x, y] = m.pose;
    el("circle", { class: "goal draft-goal", r: geo.robotR }, marker($("layer-draft"), x, y));
    line.replaceChildren(`Send ${m.robot} to (${x.toFixed(2)}, ${y.toFixed(2)})? `);
    const ok = button(line, "Confirm", "confirm", () => {
      setMode(null);
      api("POST", `/api/robots/${m.robot}/goal`, { pose: [x, y, 0] }, $("mode-line"));
    });
    ok.id = "goal-confirm";
    button(line, "Cancel", "cancel-goal", () => setMode(null)).id = "goal-cancel";
    ok.focus();
    return;
  }
  line.textContent = !m ? "" : m.kind === "goal" ? `Click the map: goal for ${m.robot} (Esc cancels)` : m.kind === "rect" ? "Drag a rectangle on the map (Esc cancels)" : "Click the corners; double-click closes the polygon (Esc cancels)";
}

// "90s", "10m", "2h" from the form's duration field, in seconds; an error next to `near` if it is none.
function durationS(near) {
  const text = $("block-for").value.trim();
  const m = /^(\d+(?:\.\d+)?)\s*([smhd]?)$/.exec(text);
  if (!m) {
    showError(`not a duration: ${text} (e.g. 90s, 10m, 2h)`, near);
    return null;
  }
  return parseFloat(m[1]) * { "": 1, s: 1, m: 60, h: 3600, d: 86400 }[m[2]];
}

function blockBody(extra) {
  const forS = durationS($("block-form"));
  return forS == null ? null : { ...extra, reason: $("block-reason").value || undefined, for_s: forS };
}

function setupSteering() {
  const svg = $("map");
  $("block-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const body = blockBody({ zone: $("block-zone").value });
    if (body) api("POST", "/api/blocks", body, $("block-form"));
  });
  $("draw-rect").addEventListener("click", () => setMode({ kind: "rect" }));
  $("draw-poly").addEventListener("click", () => setMode({ kind: "poly", points: [] }));
  document.addEventListener("keydown", (ev) => ev.key === "Escape" && setMode(null));
  svg.addEventListener("mousedown", (ev) => {
    if (mode && mode.kind === "rect") mode.start = worldFromEvent(ev);
  });
  svg.addEventListener("mousemove", (ev) => {
    if (!mode) return;
    const p = worldFromEvent(ev);
    const draft = $("layer-draft");
    if (mode.kind === "rect" && mode.start) {
      const [a, b] = [mode.start, p];
      draft.replaceChildren();
      el("polygon", { class: "draft", points: pts([a, [b[0], a[1]], b, [a[0], b[1]]]) }, draft);
    } else if (mode.kind === "poly" && mode.points.length) {
      draft.replaceChildren();
      el("polygon", { class: "draft", points: pts([...mode.points, p]) }, draft);
    }
  });
  svg.addEventListener("mouseup", (ev) => {
    if (!mode || mode.kind !== "rect" || !mode.start) return;
    const [a, b] = [mode.start, worldFromEvent(ev)];
    setMode(null);
    if (Math.abs(a[0] - b[0]) < 0.05 || Math.abs(a[1] - b[1]) < 0.05) return;
    const body = blockBody({ polygon: [a, [b[0], a[1]], b, [a[0], b[1]]] });
    if (body) api("POST", "/api/blocks", body, $("mode-line"));
  });
  svg.addEventListener("click", (ev) => {
    if (!mode || panned) return;
    const p = worldFromEvent(ev);
    if (mode.kind === "goal" || mode.kind === "confirm") {
      setMode({ kind: "confirm", robot: mode.robot, pose: p }); // another click picks another target
    } else if (mode.kind === "poly") {
      mode.points.push(p);
    }
  });
  svg.addEventListener("dblclick", () => {
    if (!mode || mode.kind !== "poly") return;
    // The double-click's two clicks added the last corner twice.
    const points = mode.points.filter((p, i, a) => i === 0 || p[0] !== a[i - 1][0] || p[1] !== a[i - 1][1]);
    setMode(null);
    if (points.length < 3) {
      showError("a polygon needs at least 3 corners", $("mode-line"));
      return;
    }
    const body = blockBody({ polygon: points });
    if (body) api("POST", "/api/blocks", body, $("mode-line"));
  });
  $("filter").addEventListener("input", applyFilter);
  $("alerts-ack-all").addEventListener("click", () => api("POST", "/api/alerts/ack-all", {}, $("alert-list")));
  $("logout").addEventListener("click", async () => {
    await api("POST", "/api/logout");
    window.location.assign("/login");
  });
}

async function main() {
  const session = await fetch("/api/session");
  if (session.status === 401) return window.location.assign("/login");
  csrf = (await session.json()).csrf;
  geo = await (await fetch("/api/site")).json();
  drawSite();
  setupZoom();
  setupSteering();
  connect();
  setInterval(() => requestAnimationFrame(renderClock), 1000);
}
main();
