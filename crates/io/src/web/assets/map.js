// The live map: the site over its floor plan, every tracked device moving
// as the gateway locates it (Server-Sent Events from /api/live), its recent
// trail and a halo sized by its confidence, routes requested by clicking a
// device and a place, and the gateway's status.
//
// Device ids and place names come from the air and the broker: they are
// only ever set as text (textContent, <title>), never parsed as HTML.
//
// The devices (dots, halos, trails) are drawn on a canvas over the plan's
// SVG, whole, once per animation frame that has fixes: with a thousand
// devices, an SVG element per dot made every frame re-record and re-raster
// thousands of elements (frame work p50 31 ms at 1,000 fixes a second),
// where a canvas draws them in three paths (docs/web.md, "Measured"). The
// pointer finds devices in the device table (devicesAt), not the DOM. The
// plan changes only on a reload; its labels are laid out around each other
// (site.js).
//
// A building of several floors shows one floor at a time (the switcher over
// the plan, `?floor=` in the address): its plan, places and beacons, and the
// devices whose latest fix is on it. A device on another floor, or whose
// floor is unknown, is listed but not drawn, and the list says so.

import { api, h, s, fill, Frame, PlanView, drawSite, drawFloorplan, token, setToken } from "/assets/site.js";

const $ = (id) => document.getElementById(id);
/** Fixes kept per device for its trail. */
const TRAIL = 20;
/** Above this many devices only the selected device's trail is drawn. */
const TRAILS_FOR_ALL = 200;
/** Share of fixes inside the halo, for a circular normal error whose
 * chance of being within one cell is the published confidence. */
const HALO_SHARE = 0.68;
/** Devices in the list at most (the map shows them all). */
const LIST_MAX = 200;

let site = null;
let access = {};
let floors = []; // the building's floors, lowest first ({ name, level })
let floor = null; // the floor shown, on a building of several; null on one floor
let buildingName = "";
let survey = null; // survey mode's state on the floor shown (GET /api/survey)
// Dragging pans, except on a device or a place, which take clicks.
const view = new PlanView($("plan"), {
  panWithLeft: (e) => !(e.target.closest && e.target.closest(".device, .place")),
  overlays: [document.querySelector(".legend"), $("cursor"), $("floor-switch")],
});
const devices = new Map(); // id -> { id, cell, floor, t, confidence, place, unknown, trail: [[gx, gy]], shown, dirty }
const layer = $("devices-layer");
let redraw = true; // the canvas is out of date
view.onChange(() => {
  redraw = true;
  schedule();
});
let selected = null; // device id
let routes = new Map(); // device -> last path payload
let guidance = new Map(); // device -> last guidance payload
let pending = []; // fix batches waiting for the next frame
let frameQueued = false;
// This page's own figures, since it opened or since "reset".
const FIGURES_KEPT = 20000;
const latencies = []; // ms from the gateway's web sink taking a fix to its dot being drawn
const frameWork = []; // ms of main-thread work (script, style, layout, paint) per drawn frame
const frameIntervals = []; // ms between frames
let lastFrame = 0;
let received = 0; // fixes drawn since the page opened or "reset"
let moved = 0; // dots that moved, likewise
let countedSince = performance.now();
function keep(list, value) {
  list.push(value);
  if (list.length > FIGURES_KEPT) list.splice(0, list.length - FIGURES_KEPT);
}
// A message posted during a frame is delivered once that frame is rendered:
// the time until then is the frame's work.
const afterPaint = new MessageChannel();
afterPaint.port1.onmessage = (e) => keep(frameWork, performance.now() - e.data);
$("page-reset").addEventListener("click", () => {
  for (const list of [latencies, frameWork, frameIntervals]) list.length = 0;
  received = 0;
  moved = 0;
  countedSince = performance.now();
  pageStats();
});

function haloRadius(confidence) {
  // P(d <= 1 cell) = 1 - exp(-1 / (2 sigma^2)) = confidence.
  const c = Math.min(Math.max(confidence, 0.01), 0.995);
  const sigma2 = -1 / (2 * Math.log(1 - c));
  const r = Math.sqrt(-2 * sigma2 * Math.log(1 - HALO_SHARE));
  return Math.min(Math.max(r, 0.35), 12);
}

async function load() {
  access = await api("/api/access");
  $("token-box").hidden = !access.needs_token;
  $("token").value = token();
  $("edit-link").hidden = !access.editor;
  await loadSite(true, new URLSearchParams(location.search).get("floor"));
  connect();
  refreshSurvey();
}

/** Whether the device is drawn on the floor shown (on one floor, all are). */
function onFloor(d) {
  return floor === null || d.floor === floor;
}

/** `path` asking for the floor shown, if there are several. */
function floorUrl(path) {
  return floor === null ? path : `${path}?floor=${encodeURIComponent(floor)}`;
}

/** The floors of the building (again after a reload) and the one to show:
 * the one asked for (the switcher, the address), else the lowest. */
async function loadFloors(asked) {
  const building = await api("/api/floors");
  floors = building.floors;
  buildingName = building.building;
  const several = floors.length > 1;
  floor = several ? (floors.find((f) => f.name === asked) || floors[0]).name : null;
  $("floor-switch").hidden = !several;
  $("floor-name").hidden = !several;
  if (!several) return;
  fill(
    $("floor-switch"),
    h("span", { class: "title", "aria-hidden": "true" }, "floor"),
    [...floors].reverse().map((f) =>
      h(
        "button",
        { type: "button", "data-floor": f.name, "aria-pressed": String(f.name === floor), title: `show floor ${f.name} (level ${f.level})`, onclick: () => showFloor(f.name) },
        h("span", {}, f.name),
        h("span", { class: "count" }),
      ),
    ),
  );
  countFloors();
  const url = new URL(location.href);
  url.searchParams.set("floor", floor);
  history.replaceState(null, "", url);
}

/** Shows floor `name`: its plan, places and beacons, and its devices. */
async function showFloor(name) {
  if (name !== floor) await loadSite(false, name);
}

/** The devices on each floor, on the switcher's buttons. */
function countFloors() {
  if (floor === null) return;
  const counts = new Map();
  for (const d of devices.values()) counts.set(d.floor, (counts.get(d.floor) || 0) + 1);
  for (const button of $("floor-switch").querySelectorAll("button")) {
    const n = counts.get(button.dataset.floor) || 0;
    const text = n ? String(n) : "";
    const count = button.querySelector(".count");
    if (count.textContent !== text) count.textContent = text;
    button.setAttribute("aria-label", `floor ${button.dataset.floor}, ${n} device${n === 1 ? "" : "s"}`);
  }
}

/** Draws the site the gateway serves (again after a reload): floor `asked`'s
 * on a building of several. */
async function loadSite(first, asked) {
  const before = { site, floor };
  await loadFloors(asked);
  site = await api(floorUrl("/api/site"));
  fill($("site-name"), floor === null ? site.name : buildingName);
  fill($("floor-name"), floor === null ? "" : `floor ${floor}`);
  $("plan").dataset.site = site.name;
  $("edit-link").href = floorUrl("/edit");
  $("edit-link").textContent = floor === null ? "Edit site" : `Edit floor ${floor}`;
  document.title = floor === null ? `gangway · ${site.name}` : `gangway · ${site.name} · floor ${floor}`;
  // Survey mode records the floor shown, into that floor's file.
  $("survey").hidden = !access.survey;
  if (!first && before.floor !== floor) {
    survey = null;
    refreshSurvey();
  }
  const plan = site.floorplan;
  drawFloorplan(view.layers.floorplan, plan && plan.url, plan && plan.matrix, plan && plan.width, plan && plan.height);
  drawSite(view, site, { withPlan: !!plan });
  const resized = before.site && (before.site.width !== site.width || before.site.height !== site.height);
  if (first || (before.floor !== floor && resized)) view.fit(0, 0, site.width, site.height);
  redraw = true;
  listDirty = true;
  renderList(true); // where each device is, said for this floor at once
  schedule();
  showRoute();
  drawHeat();
  fill(
    $("places"),
    site.places.map((p) => h("li", {}, h("button", { type: "button", class: "link", onclick: () => pickPlace(p) }, `${p.name}  [${p.cell.join(", ")}]`))),
  );
  for (const node of view.layers.places.querySelectorAll(".place")) {
    node.addEventListener("click", (e) => {
      if ($("survey-on").checked) return; // a spot to survey, like any cell
      if (!selected && deviceAt(e)) return; // a device standing there: pick it first
      e.stopPropagation();
      pickPlace(site.places.find((p) => p.name === node.dataset.place));
    });
  }
  $("plan").dataset.siteHash = site.map_hash;
  $("plan").dataset.floor = floor ?? "";
}

$("token").addEventListener("change", () => setToken($("token").value.trim()));

$("plan").addEventListener("pointermove", (e) => {
  if (!site) return;
  const [gx, gy] = view.toGrid(e);
  fill($("cursor"), `cell [${Math.floor(gx)}, ${Math.floor(gy)}]`);
  showTip(e, devicesAt(e));
});
$("plan").addEventListener("pointerleave", () => showTip(null, []));

/** The located devices drawn under a pointer event, nearest first (the
 * selected one first among equals: it is drawn on top). */
function devicesAt(e) {
  if (!site) return [];
  const [gx, gy] = view.toGrid(e);
  const reach = Math.max(0.5, 8 * view.unitsPerPixel());
  const near = [];
  for (const d of devices.values()) {
    if (!d.cell || !onFloor(d)) continue;
    const dd = Math.hypot(d.cell[0] + 0.5 - gx, d.cell[1] + 0.5 - gy);
    if (dd <= reach) near.push([dd - (d.id === selected ? 1e-6 : 0), d]);
  }
  return near.sort((a, b) => a[0] - b[0]).map(([, d]) => d);
}

function deviceAt(e) {
  return devicesAt(e)[0] || null;
}

/** The tooltip of the devices under the pointer (text only). */
function showTip(e, here) {
  const tip = $("tip");
  const d = here[0];
  if (!d) {
    tip.hidden = true;
    return;
  }
  const others = here.slice(1, 4).map((o) => o.id);
  const more = here.length > 4 ? `, … ${here.length - 4} more` : "";
  tip.textContent =
    `${d.id}: ${d.unknown ? "unknown (last located here)" : d.place || "cell " + d.cell.join(", ")}, confidence ${(d.confidence * 100).toFixed(0)} %` +
    (others.length ? ` · also here: ${others.join(", ")}${more}` : "");
  const frame = $("plan").getBoundingClientRect();
  tip.style.left = `${e.clientX - frame.left + 12}px`;
  tip.style.top = `${e.clientY - frame.top + 12}px`;
  tip.hidden = false;
}

$("plan").addEventListener("click", (e) => {
  if (view.lastDragMoved || !site) return;
  const hit = deviceAt(e);
  if (hit && !$("survey-on").checked) return selectDevice(hit.id);
  if (!selected || (e.target.closest(".place") && !$("survey-on").checked)) return;
  const [gx, gy] = view.toGrid(e);
  if ($("survey-on").checked) return surveyAt([gx, gy]);
  const x = Math.floor(gx);
  const y = Math.floor(gy);
  if (x < 0 || y < 0 || x >= site.width || y >= site.height || site.tiles[y * site.width + x] === ".") return;
  requestRoute([x, y], `cell [${x}, ${y}]`);
});

// ---- live updates ----

function connect() {
  const source = new EventSource("/api/live");
  source.addEventListener("open", () => fill($("connection"), "live"));
  source.addEventListener("error", () => fill($("connection"), h("span", { class: "bad" }, "reconnecting…")));
  source.addEventListener("snapshot", (e) => {
    const snap = JSON.parse(e.data);
    for (const d of devices.values()) removeDevice(d.id);
    for (const fix of snap.devices) applyFix(fix, snap.sent_ms, false);
    routes = new Map(snap.routes.map((r) => [r.device, r]));
    guidance = new Map(snap.guidance.map((g) => [g.device, g]));
    schedule();
    showRoute();
  });
  source.addEventListener("fixes", (e) => {
    pending.push(JSON.parse(e.data));
    schedule();
  });
  source.addEventListener("forget", (e) => {
    for (const id of JSON.parse(e.data)) removeDevice(id);
    schedule();
  });
  source.addEventListener("path", (e) => {
    const path = JSON.parse(e.data);
    routes.set(path.device, path);
    if (path.device === selected) showRoute();
  });
  source.addEventListener("guidance", (e) => {
    const g = JSON.parse(e.data);
    guidance.set(g.device, g);
    if (g.device === selected) showRoute();
  });
  source.addEventListener("status", (e) => showStatus(JSON.parse(e.data)));
  // The gateway reloaded its site (SIGHUP, or a save in the editor).
  source.addEventListener("site", () => loadSite(false, floor).catch((e) => fill($("connection"), h("span", { class: "bad" }, e.message))));
}

function schedule() {
  if (!frameQueued) {
    frameQueued = true;
    requestAnimationFrame(frame);
  }
}

function frame() {
  const started = performance.now();
  afterPaint.port2.postMessage(started);
  frameQueued = false;
  const batches = pending;
  pending = [];
  for (const batch of batches) {
    for (const fix of batch.fixes) applyFix(fix, batch.sent_ms, true);
  }
  draw();
  // Drawn in this frame: the time from the web sink taking the batch's
  // oldest fix to now.
  const drawnAt = Date.now();
  for (const batch of batches) {
    received += batch.fixes.length;
    keep(latencies, drawnAt - (batch.taken_ms || batch.sent_ms));
  }
}

function applyFix(fix, sentMs, live) {
  let d = devices.get(fix.device);
  if (!d) {
    d = { id: fix.device, trail: [], drawnAt: null };
    devices.set(fix.device, d);
  }
  d.t = fix.t;
  d.confidence = fix.confidence;
  noteConfidence(fix);
  d.place = fix.place;
  d.unknown = !fix.cell;
  const on = fix.floor ?? null;
  if (d.floor !== undefined && on !== d.floor) d.trail = []; // its trail was on another floor
  d.floor = on;
  if (fix.cell) {
    d.cell = fix.cell;
    const at = [fix.cell[0] + 0.5, fix.cell[1] + 0.5];
    const last = d.trail[d.trail.length - 1];
    if (!last || last[0] !== at[0] || last[1] !== at[1]) d.trail.push(at);
    if (d.trail.length > TRAIL) d.trail.shift();
    if (fix.trail && !live) d.trail = fix.trail.map((c) => [c[0] + 0.5, c[1] + 0.5]);
  }
  d.dirty = true;
}

function removeDevice(id) {
  const d = devices.get(id);
  if (!d) return;
  devices.delete(id);
  redraw = true;
  if (selected === id) selected = null;
  listDirty = true;
}

let listDirty = true;

/** Paints every device on the canvas: trails, then halos, then dots (the
 * selected device last, over the others), in grid units through the
 * plan's view box. */
function paint() {
  const ratio = window.devicePixelRatio || 1;
  const width = layer.clientWidth;
  const height = layer.clientHeight;
  if (layer.width !== Math.round(width * ratio) || layer.height !== Math.round(height * ratio)) {
    layer.width = Math.round(width * ratio);
    layer.height = Math.round(height * ratio);
  }
  const g = layer.getContext("2d");
  g.setTransform(1, 0, 0, 1, 0, 0);
  g.clearRect(0, 0, layer.width, layer.height);
  if (!site) return;
  const [bx, by, bw] = view.box;
  const k = (width / bw) * ratio;
  g.setTransform(k, 0, 0, k, -bx * k, -by * k);
  const upp = view.unitsPerPixel();
  // Dots stay at least 3 screen pixels wide, whatever the zoom.
  const r = Math.max(0.3, 3 * upp);
  const allTrails = devices.size <= TRAILS_FOR_ALL;
  const located = [];
  const unknown = [];
  let chosen = null;
  for (const d of devices.values()) {
    if (!d.cell || !onFloor(d)) continue;
    if (d.id === selected) chosen = d;
    else (d.unknown ? unknown : located).push(d);
  }
  const trails = (list, color) => {
    g.beginPath();
    for (const d of list) {
      if (d.trail.length < 2) continue;
      g.moveTo(d.trail[0][0], d.trail[0][1]);
      for (const [x, y] of d.trail.slice(1)) g.lineTo(x, y);
    }
    g.strokeStyle = color;
    g.lineWidth = 0.1;
    g.lineJoin = "round";
    g.stroke();
  };
  const circles = (list, radius) => {
    g.beginPath();
    for (const d of list) {
      const rr = radius(d);
      if (rr <= 0) continue;
      g.moveTo(d.cell[0] + 0.5 + rr, d.cell[1] + 0.5);
      g.arc(d.cell[0] + 0.5, d.cell[1] + 0.5, rr, 0, 2 * Math.PI);
    }
  };
  const halo = (d) => Math.round(haloRadius(d.confidence) * 20) / 20;
  const dot = () => r;
  if (allTrails) trails(located, "rgba(11, 107, 203, 0.35)");
  circles(located, halo);
  g.fillStyle = "rgba(11, 107, 203, 0.12)";
  g.fill();
  g.strokeStyle = "rgba(11, 107, 203, 0.35)";
  g.lineWidth = 0.04;
  g.stroke();
  circles(unknown, dot);
  g.fillStyle = "#98a2b3";
  g.fill();
  g.setLineDash([0.1, 0.06]);
  g.strokeStyle = "#475467";
  g.lineWidth = 0.08;
  g.stroke();
  g.setLineDash([]);
  circles(located, dot);
  g.fillStyle = "#0b6bcb";
  g.fill();
  g.strokeStyle = "#fff";
  g.stroke();
  layer.dataset.drawn = String(located.length + unknown.length + (chosen ? 1 : 0));
  if (chosen) {
    trails([chosen], "rgba(11, 70, 140, 0.6)"); // not red: routes are
    if (!chosen.unknown) {
      circles([chosen], halo);
      g.fillStyle = "rgba(217, 45, 32, 0.12)";
      g.fill();
      g.strokeStyle = "rgba(217, 45, 32, 0.35)";
      g.lineWidth = 0.04;
      g.stroke();
    }
    circles([chosen], dot);
    g.fillStyle = chosen.unknown ? "#98a2b3" : "#d92d20";
    g.fill();
    g.strokeStyle = chosen.unknown ? "#d92d20" : "#fff";
    g.lineWidth = 0.08;
    g.stroke();
  }
}

/** Draws the devices if anything changed since the last frame. */
function draw() {
  for (const d of devices.values()) {
    if (!d.dirty) continue;
    d.dirty = false;
    listDirty = true;
    redraw = true;
    if (!d.cell) continue; // never located: in the list only
    if (d.drawnAt && (d.drawnAt[0] !== d.cell[0] || d.drawnAt[1] !== d.cell[1])) moved++;
    d.drawnAt = d.cell;
  }
  if (redraw) paint();
  redraw = false;
  if (listDirty) {
    listDirty = false;
    renderList();
  }
  if ($("device-count").textContent !== String(devices.size)) fill($("device-count"), String(devices.size));
}

$("device-filter").addEventListener("input", () => {
  listDirty = true;
  schedule();
});

let listTimer = 0;
let listed = { ids: [], rows: new Map(), more: 0 }; // what the list shows
function renderList(now = false) {
  // The list is text; at most once a second however fast fixes come (at
  // once when the floor shown changes), and rebuilt only when its devices
  // change (otherwise its texts are updated).
  if (listTimer && !now) return;
  clearTimeout(listTimer);
  const render = () => {
    listTimer = 0;
    const filter = $("device-filter").value.trim().toLowerCase();
    const all = [...devices.keys()].filter((id) => !filter || id.toLowerCase().includes(filter)).sort();
    const ids = all.slice(0, LIST_MAX);
    const more = all.length - ids.length;
    if (more !== listed.more || ids.length !== listed.ids.length || ids.some((id, i) => id !== listed.ids[i])) {
      const rows = new Map();
      const items = ids.map((id) => {
        const where = h("span", {});
        const li = h("li", { "data-device": id }, h("button", { type: "button", class: "link", onclick: () => selectDevice(id) }, id), where);
        rows.set(id, { li, where });
        return li;
      });
      if (more > 0) items.push(h("li", { class: "muted" }, `… and ${more} more (filter to find one)`));
      fill($("devices"), items);
      listed = { ids, rows, more };
    }
    for (const [id, row] of listed.rows) {
      const d = devices.get(id);
      let where = d.unknown ? "unknown" : d.place || (d.cell ? `[${d.cell.join(", ")}]` : "unknown");
      if (floor !== null && d.floor === null) where = "floor unknown: not drawn";
      else if (floor !== null && d.floor !== floor) where = `on floor ${d.floor}: ${where}`;
      const cell = d.cell ? d.cell.join(",") : "";
      if (row.where.textContent !== where) row.where.textContent = where;
      row.where.classList.toggle("muted", !!d.unknown || !onFloor(d));
      if (row.li.dataset.floor !== (d.floor ?? "")) row.li.dataset.floor = d.floor ?? "";
      row.li.classList.toggle("selected", id === selected);
      if (row.li.dataset.cell !== cell) row.li.dataset.cell = cell;
    }
    countFloors();
  };
  if (now) render();
  else listTimer = setTimeout(render, 1000);
}

// ---- routes ----

function selectDevice(id) {
  const before = selected && devices.get(selected);
  selected = id;
  if (before) before.dirty = true;
  const d = devices.get(id);
  if (d) d.dirty = true;
  // Picked in the list on another floor: show its floor.
  if (d && floor !== null && d.floor && d.floor !== floor) showFloor(d.floor).catch((e) => fill($("connection"), h("span", { class: "bad" }, e.message)));
  listDirty = true;
  fill($("route-pick"), "device ", h("b", {}, id), ": now click a place");
  showRoute();
  schedule();
}

function pickPlace(place) {
  if (!place) return;
  // In survey mode a place (from the list too, for the keyboard) is a spot.
  if ($("survey-on").checked) {
    if (selected) surveyAt([place.cell[0] + 0.5, place.cell[1] + 0.5]);
    return;
  }
  if (!selected) {
    fill($("route-pick"), h("span", { class: "bad" }, "click a device first"));
    return;
  }
  requestRoute(place.name, place.name);
}

async function requestRoute(to, shown) {
  const device = selected;
  const body = { device, to };
  if (floor !== null) body.floor = floor; // a place or cell of the floor shown
  if ($("profile").value) body.profile = $("profile").value;
  fill($("route-pick"), "asking a route for ", h("b", {}, device), " to ", h("b", {}, shown), "…");
  try {
    const reply = await api("/api/route", { method: "POST", json: body });
    fill($("route-pick"), "route requested for ", h("b", {}, device), " to ", h("b", {}, shown), ` (${reply.request_id})`);
  } catch (e) {
    fill($("route-pick"), h("span", { class: "bad" }, e.message));
  }
}

function showRoute() {
  const path = selected && routes.get(selected);
  const box = $("route");
  if (!path) {
    fill(view.layers.route);
    fill(box);
    return;
  }
  if (path.error) {
    fill(view.layers.route);
    fill(box, h("p", { class: "bad" }, `${path.error.code}: ${path.error.message}`));
    return;
  }
  // The line the walker was given (metres), in grid units: on a building,
  // the leg on the floor shown (if the route crosses it).
  const frame = new Frame(site.cell_m, site.origin_m, site.y_axis);
  const leg = path.legs ? path.legs.find((l) => l.floor === floor) : path;
  if (leg) {
    const points = leg.line.map((p) => frame.grid([p.x_m, p.y_m]).join(",")).join(" ");
    const end = leg.waypoints[leg.waypoints.length - 1].cell;
    fill(
      view.layers.route,
      s("polyline", { class: "route", points }),
      s("circle", { class: "route-end", cx: end[0] + 0.5, cy: end[1] + 0.5, r: 0.45 }),
    );
  } else fill(view.layers.route);
  const planner = path.legs ? path.legs.map((l) => l.planner).filter((p, i, all) => all.indexOf(p) === i).join(", ") : path.planner;
  const floorsCrossed = path.legs && path.legs.length > 1 ? `, floors ${path.legs.map((l) => l.floor).join(" → ")}` : "";
  const g = guidance.get(selected);
  const progress = [];
  if (g && g.request_id === path.request_id) {
    const total = g.progress_m + g.remaining_m;
    progress.push(
      h("p", {}, h("b", {}, g.state.replace("_", " ")), g.text ? ` · ${g.text}` : ""),
      h("progress", { max: total > 0 ? total.toFixed(1) : 1, value: g.progress_m.toFixed(1) }),
      h("p", { class: "muted" }, `${g.progress_m.toFixed(1)} m walked, ${g.remaining_m.toFixed(1)} m to go, about ${Math.round(g.eta_s)} s; reroutes ${g.reroutes}`),
    );
  }
  fill(
    box,
    h("p", {}, `${path.length_m.toFixed(1)} m by ${planner}${floorsCrossed}, planned in ${(path.latency_us / 1000).toFixed(2)} ms`),
    progress,
    h("ol", { class: "instructions" }, path.instructions.map((i) => h("li", {}, floorsCrossed && i.floor ? `${i.floor}: ${i.text}` : i.text))),
  );
}

// ---- survey ----

/** The selected device stands at grid point `g`: record its fingerprints there. */
async function surveyAt(g) {
  const [x, y] = new Frame(site.cell_m, site.origin_m, site.y_axis).world(g).map((v) => Math.round(v * 100) / 100);
  const samples = Math.round(Number($("survey-samples").value)) || 10;
  try {
    await api(floorUrl("/api/survey"), { method: "POST", json: { device: selected, x_m: x, y_m: y, samples } });
    refreshSurvey();
  } catch (e) {
    fill($("survey-status"), h("span", { class: "bad" }, e.message));
  }
}

$("survey-stop").addEventListener("click", async () => {
  try {
    await api(floorUrl("/api/survey/stop"), { method: "POST", json: {} });
  } catch (e) {
    fill($("survey-status"), h("span", { class: "bad" }, e.message));
  }
  refreshSurvey();
});

$("survey-on").addEventListener("change", () => {
  $("plan").dataset.tool = $("survey-on").checked ? "survey" : "pan";
  refreshSurvey();
});
$("heat").addEventListener("change", () => refreshSurvey());

async function refreshSurvey() {
  if (!access.survey) return;
  try {
    survey = await api(floorUrl("/api/survey"));
  } catch (e) {
    fill($("survey-status"), h("span", { class: "bad" }, e.message));
    return;
  }
  // One RSSI layer per anchor of the floor shown: each floor has its own.
  const heat = $("heat");
  const labels = survey.anchors.map((id) => `RSSI of ${id}`);
  const listed = [...heat.options].filter((o) => o.value.startsWith("rssi:"));
  if (listed.map((o) => o.textContent).join("\n") !== labels.join("\n")) {
    if (heat.value.startsWith("rssi:")) heat.value = "";
    listed.forEach((o) => o.remove());
    labels.forEach((label, i) => heat.append(h("option", { value: "rssi:" + i }, label)));
  }
  const spot = survey.spot;
  $("survey-stop").hidden = !spot || spot.taken >= spot.wanted;
  const covered = survey.cells.length;
  const lines = [`${survey.recorded} windows recorded here; ${covered} cell${covered === 1 ? "" : "s"} surveyed in ${survey.file}`];
  if (spot) lines.unshift(`${spot.device} at ${spot.x_m}, ${spot.y_m} m: ${spot.taken} of ${spot.wanted} windows${spot.taken >= spot.wanted ? " (done)" : "…"}`);
  if (survey.error) lines.push(survey.error);
  fill($("survey-status"), lines.map((l) => h("div", {}, l)));
  drawHeat();
}
setInterval(() => {
  if ($("survey-on").checked || $("heat").value) refreshSurvey();
}, 2000);

/** Colours from blue (low) to red (high). */
function ramp(v) {
  const k = Math.min(1, Math.max(0, v));
  return `hsl(${Math.round(240 - 240 * k)} 85% 50%)`;
}

const confidence = new Map(); // "x,y" -> [sum, count] of published confidences
function noteConfidence(fix) {
  if (!fix.cell) return;
  const key = `${fix.floor ?? ""}|${fix.cell.join(",")}`;
  const c = confidence.get(key) || [0, 0];
  c[0] += fix.confidence;
  c[1] += 1;
  confidence.set(key, c);
}

function drawHeat() {
  const mode = $("heat").value;
  const cells = [];
  let legend = "";
  if (mode === "samples" && survey) {
    const most = Math.max(1, ...survey.cells.map((c) => c.samples));
    for (const c of survey.cells) cells.push([c.cell, c.samples / most, `${c.samples} windows`]);
    legend = `blue: few windows, red: ${most}; cells without colour are not surveyed`;
  } else if (mode.startsWith("rssi:") && survey) {
    const i = Number(mode.slice(5));
    for (const c of survey.cells) {
      const r = c.rssi[i];
      if (r !== null && r !== undefined) cells.push([c.cell, (r + 100) / 60, `${r.toFixed(0)} dBm`]);
    }
    legend = `mean RSSI of ${survey.anchors[i]} where surveyed: blue -100 dBm, red -40 dBm; no colour: not heard`;
  } else if (mode === "confidence") {
    for (const [key, [sum, n]] of confidence) {
      const [on, cell] = key.split("|");
      if (floor === null || on === floor) cells.push([cell.split(",").map(Number), sum / n, `mean confidence ${(sum / n).toFixed(2)} over ${n} fixes`]);
    }
    legend = "mean published confidence of the fixes in each cell since this page opened: blue 0, red 1";
  }
  fill($("heat-legend"), legend);
  // Place markers go pale over a heat map: a surveyed spot is often a place.
  $("plan").classList.toggle("heat-on", cells.length > 0);
  fill(
    view.layers.heat,
    cells.map(([cell, v, title]) =>
      s("rect", { class: "heat", x: cell[0], y: cell[1], width: 1, height: 1, fill: ramp(v) }, s("title", {}, title)),
    ),
  );
}

// ---- status ----

const STATUS_KEYS = [
  ["mqtt", "broker"],
  ["ble_state", "radio"],
  ["tracked", "devices tracked"],
  ["fixes", "fixes"],
  ["sightings", "sightings"],
  ["routes", "routes"],
  ["request_errors", "request errors"],
  ["pending_requests", "requests waiting"],
  ["overloaded", "overloaded"],
  ["rate_limited", "rate limited"],
  ["rejected_messages", "messages refused"],
  ["evicted_devices", "devices forgotten"],
  ["queue_depth", "queued to the broker"],
  ["reloads", "reloads"],
  ["uptime_s", "up"],
];

function showStatus(stats) {
  const rows = [];
  for (const [key, label] of STATUS_KEYS) {
    let value = key === "ble_state" ? stats.ble && stats.ble.state : stats[key];
    if (value === undefined || value === null) continue;
    if (key === "uptime_s") value = `${Math.floor(value / 60)} min`;
    rows.push(h("dt", {}, label), h("dd", {}, String(value)));
  }
  fill($("status"), rows);
  fill($("fallbacks"), (stats.fallbacks || []).length ? stats.fallbacks.map((f) => h("li", {}, f)) : [h("li", { class: "ok" }, "none")]);
}

function percentile(values, p) {
  if (!values.length) return NaN;
  const sorted = Float64Array.from(values).sort(); // numeric, and fast
  return sorted[Math.min(sorted.length - 1, Math.floor(p * sorted.length))];
}

/** A figure for the panel, or a dash while nothing was measured (after a replay ends, say). */
function ms(value, digits) {
  return Number.isFinite(value) ? value.toFixed(digits) : "–";
}

/** This page's own figures: fixes a second, fix-to-screen latency, frame time. */
function pageStats() {
  const now = performance.now();
  const seconds = Math.max(0.001, (now - countedSince) / 1000);
  const stats = {
    fixes_per_s: received / seconds,
    moved_per_s: moved / seconds,
    latency_p50_ms: percentile(latencies, 0.5),
    latency_p99_ms: percentile(latencies, 0.99),
    frame_p50_ms: percentile(frameWork, 0.5),
    frame_p99_ms: percentile(frameWork, 0.99),
    interval_p50_ms: percentile(frameIntervals, 0.5),
    devices: devices.size,
  };
  fill(
    $("page-stats"),
    h("dt", {}, "devices drawn"), h("dd", {}, String(stats.devices)),
    h("dt", {}, "fixes a second"), h("dd", {}, stats.fixes_per_s.toFixed(0)),
    h("dt", {}, "dots moved a second"), h("dd", {}, stats.moved_per_s.toFixed(0)),
    h("dt", {}, "fix → screen p50 / p99"), h("dd", {}, `${ms(stats.latency_p50_ms, 0)} / ${ms(stats.latency_p99_ms, 0)} ms`),
    h("dt", {}, "frame work p50 / p99"), h("dd", {}, `${ms(stats.frame_p50_ms, 1)} / ${ms(stats.frame_p99_ms, 1)} ms`),
    h("dt", {}, "frame interval p50"), h("dd", {}, `${ms(stats.interval_p50_ms, 1)} ms`),
  );
  $("page-stats").dataset.latencyP99 = stats.latency_p99_ms;
  $("page-stats").dataset.latencyP50 = stats.latency_p50_ms;
  $("page-stats").dataset.frameP50 = stats.frame_p50_ms;
  $("page-stats").dataset.frameP99 = stats.frame_p99_ms;
  $("page-stats").dataset.intervalP50 = stats.interval_p50_ms;
  $("page-stats").dataset.fixesPerS = stats.fixes_per_s;
  $("page-stats").dataset.movedPerS = stats.moved_per_s;
  $("page-stats").dataset.frames = frameWork.length;
  $("page-stats").dataset.devices = stats.devices;
}
setInterval(pageStats, 2000);

// Frame times, from the browser's own frame clock.
function tick(now) {
  if (lastFrame) keep(frameIntervals, now - lastFrame);
  lastFrame = now;
  requestAnimationFrame(tick);
}
requestAnimationFrame(tick);

load().catch((e) => fill($("connection"), h("span", { class: "bad" }, e.message)));
