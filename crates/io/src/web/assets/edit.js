// The site editor: a site document (the site file as data, SiteDoc in
// src/site/doc.rs) edited over its floor plan. Every change is sent to the
// gateway, which writes the TOML and loads it exactly as `gangway check`
// does; its problems are shown as they are. Nothing here writes TOML.

import {
  api, h, s, fill, Frame, similarity, applyMatrix, invertMatrix, tilePaths, gridLines, PlanView, drawFloorplan, token, setToken, anchorMarker, placeMarker, connectorMarker,
} from "/assets/site.js";

const $ = (id) => document.getElementById(id);
const round = (v, step) => Math.round(v / step) * step;
const fixed = (v, digits) => Number(v.toFixed(digits));
const CHECK_DELAY_MS = 200;
/** Largest grid the editor makes by itself (the site file allows more). */
const MAX_AUTO_CELLS = 1_000_000;

let doc = null;
let image = null; // { name, url, width, height }
let measure = []; // pixel points picked with Measure
let draft = []; // world points of the obstacle or wall being drawn
let selected = null; // { kind, key }
let lastView = null; // the last valid site view from the check
let access = { read_only: false, needs_token: false };
let served = false; // the file is the site of the gateway serving this page
let checkTimer = 0;
let checkSeq = 0;
let painting = null;
let dragging = null;
let heard = []; // beacons the gateway heard (GET /api/heard), when it serves this page
let placing = null; // a heard beacon's { uuid, major, minor } the next Beacon click places

const svg = $("plan");
const view = new PlanView(svg, {
  panWithLeft: (e) => tool() === "pan" && !(e.target.closest && e.target.closest("[data-kind]")),
});

function tool() {
  return document.querySelector("input[name=tool]:checked").value;
}

function frame() {
  return new Frame(Number(doc.cell_m) || 1, doc.origin_m, doc.y_axis);
}

/** The grid the document describes: its map rows, or an open floor. */
function grid() {
  if (doc.map !== undefined && doc.map !== null) {
    const rows = doc.map.split("\n").map((r) => r.trim()).filter((r) => r.length > 0);
    return { w: rows.length ? [...rows[0]].length : 0, h: rows.length, rows };
  }
  if (doc.width_m && doc.height_m) {
    const c = Number(doc.cell_m) || 1;
    const w = Math.max(1, Math.ceil(doc.width_m / c - 1e-9));
    const hh = Math.max(1, Math.ceil(doc.height_m / c - 1e-9));
    return { w, h: hh, rows: null };
  }
  return { w: 0, h: 0, rows: null };
}

function setRows(rows) {
  doc.map = rows.join("\n") + "\n";
  delete doc.width_m;
  delete doc.height_m;
}

/** Pixels of the plan image to grid units. */
function imageMatrix() {
  const plan = doc.floorplan;
  if (plan && plan.reference && plan.reference.length === 2) {
    const f = frame();
    return similarity(
      plan.reference.map((r) => r.px),
      plan.reference.map((r) => f.grid(r.m)),
    );
  }
  // Not scaled yet: the image 40 units wide at the corner, to measure on.
  const k = image ? 40 / image.width : 1;
  return [k, 0, 0, k, 0, 0];
}

// ---- loading ----

// On a building of several floors, the floor whose site file is edited
// (`/edit?floor=NAME`; the lowest when absent): every editor request names it.
let floor = new URLSearchParams(location.search).get("floor");
function onFloor(path) {
  return floor === null ? path : `${path}${path.includes("?") ? "&" : "?"}floor=${encodeURIComponent(floor)}`;
}

/** The floor selector of a building: choosing a floor opens its site file. */
function showFloors(opened) {
  floor = opened.floor;
  const floors = opened.floors || [];
  $("floor-box").hidden = floors.length < 2;
  if (floors.length < 2) return;
  fill(
    $("floor"),
    [...floors].reverse().map((f) => h("option", { value: f.name }, `${f.name} (level ${f.level})`)),
  );
  $("floor").value = floor;
  document.title = `gangway site editor · floor ${floor}`;
}
$("floor").addEventListener("change", () => {
  location.href = `/edit?floor=${encodeURIComponent($("floor").value)}`;
});

async function load() {
  access = await api("/api/access");
  $("token-box").hidden = !access.needs_token;
  $("token").value = token();
  $("save").disabled = access.read_only;
  const opened = await api(onFloor("/api/editor"));
  showFloors(opened);
  loadConnectors(opened).catch((e) => showConnectorsStatus(e.message, true));
  served = opened.served_by_gateway;
  fill($("file"), opened.exists ? `editing ${opened.path}` : `new file ${opened.path}`, served ? " (the site this gateway serves: saving applies it)" : "");
  $("download").download = opened.path.split("/").pop();
  doc = opened.doc || { name: "new-site", cell_m: 1 };
  image = opened.image;
  if (opened.open_error) showProblems([opened.open_error + " (the file cannot be opened as a site; saving replaces it)"]);
  syncForm();
  render();
  fitView();
  scheduleCheck();
}

function fitView() {
  const g = grid();
  let box = [0, 0, Math.max(g.w, 10), Math.max(g.h, 10)];
  if (image) {
    const m = imageMatrix();
    const corners = [[0, 0], [image.width, 0], [0, image.height], [image.width, image.height]].map((p) => applyMatrix(m, p));
    const xs = corners.map((p) => p[0]).concat(g.w ? [0, g.w] : []);
    const ys = corners.map((p) => p[1]).concat(g.h ? [0, g.h] : []);
    box = [Math.min(...xs), Math.min(...ys), Math.max(...xs), Math.max(...ys)];
  }
  view.fit(...box);
}

// ---- the form ----

function syncForm() {
  $("name").value = doc.name ?? "";
  $("cell-m").value = doc.cell_m ?? 1;
  $("origin-x").value = doc.origin_m ? doc.origin_m[0] : 0;
  $("origin-y").value = doc.origin_m ? doc.origin_m[1] : 0;
  $("y-axis").value = doc.y_axis || "down";
  const g = grid();
  $("cols").value = g.w || "";
  $("rows").value = g.h || "";
  $("labels-on").checked = !!doc.labels;
  if (doc.labels) $("first-row").value = doc.labels.first_row;
  fill($("image-name"), image ? `${image.name} (${image.width} × ${image.height} px)` : "no plan image");
  const plan = doc.floorplan;
  if (plan && plan.reference && plan.reference.length === 2) {
    const [a, b] = plan.reference;
    const px = Math.hypot(b.px[0] - a.px[0], b.px[1] - a.px[1]);
    const m = Math.hypot(b.m[0] - a.m[0], b.m[1] - a.m[1]);
    fill($("scale-info"), `${(px / m).toFixed(2)} px per metre`);
  } else {
    fill($("scale-info"), image ? "not scaled yet" : "");
  }
}

function changed() {
  render();
  scheduleCheck();
}

$("name").addEventListener("input", () => {
  doc.name = $("name").value;
  scheduleCheck();
});

$("cell-m").addEventListener("change", () => {
  const next = Number($("cell-m").value);
  if (!(next > 0)) return;
  const g = grid();
  const before = Number(doc.cell_m) || 1;
  // A painted map keeps its area in metres: resample it to the new cells.
  if (g.rows && next !== before) {
    const w = Math.max(1, Math.round((g.w * before) / next));
    const hh = Math.max(1, Math.round((g.h * before) / next));
    if (w * hh <= MAX_AUTO_CELLS) {
      const rows = [];
      for (let y = 0; y < hh; y++) {
        let row = "";
        const sy = Math.min(g.h - 1, Math.floor(((y + 0.5) * next) / before));
        for (let x = 0; x < w; x++) row += g.rows[sy][Math.min(g.w - 1, Math.floor(((x + 0.5) * next) / before))];
        rows.push(row);
      }
      setRows(rows);
    }
  }
  doc.cell_m = next;
  syncForm();
  changed();
});

for (const id of ["origin-x", "origin-y"]) {
  $(id).addEventListener("change", () => {
    const origin = [Number($("origin-x").value) || 0, Number($("origin-y").value) || 0];
    // The plan stays on the grid: its reference points move with the origin.
    const before = doc.origin_m || [0, 0];
    shiftReference(origin[0] - before[0], origin[1] - before[1]);
    if (origin[0] === 0 && origin[1] === 0 && doc.origin_m === undefined) return changed();
    doc.origin_m = origin;
    changed();
  });
}

$("y-axis").addEventListener("change", () => {
  const before = frame();
  const next = $("y-axis").value;
  if (next === "down" && doc.y_axis === undefined) return;
  // Keep the plan where it is on the grid.
  const grids = doc.floorplan ? doc.floorplan.reference.map((r) => before.grid(r.m)) : [];
  doc.y_axis = next;
  const after = frame();
  if (doc.floorplan) doc.floorplan.reference.forEach((r, i) => (r.m = after.world(grids[i]).map((v) => fixed(v, 3))));
  changed();
});

function shiftReference(dx, dy) {
  if (!doc.floorplan) return;
  for (const r of doc.floorplan.reference) r.m = [fixed(r.m[0] + dx, 3), fixed(r.m[1] + dy, 3)];
}

function resize(w, hh) {
  if (!(w > 0 && hh > 0) || w * hh > MAX_AUTO_CELLS) return;
  const g = grid();
  if (!g.rows && doc.width_m) {
    doc.width_m = fixed(w * doc.cell_m, 6);
    doc.height_m = fixed(hh * doc.cell_m, 6);
    return changed();
  }
  const rows = [];
  for (let y = 0; y < hh; y++) {
    const old = g.rows && y < g.h ? g.rows[y] : "";
    rows.push((old + ".".repeat(w)).slice(0, w));
  }
  setRows(rows);
  syncForm();
  changed();
}

$("resize").addEventListener("click", () => resize(Math.round(Number($("cols").value)), Math.round(Number($("rows").value))));

$("fit-grid").addEventListener("click", () => {
  if (!image) return;
  const m = imageMatrix();
  const corners = [[0, 0], [image.width, 0], [0, image.height], [image.width, image.height]].map((p) => applyMatrix(m, p));
  resize(Math.ceil(Math.max(...corners.map((p) => p[0])) - 1e-6), Math.ceil(Math.max(...corners.map((p) => p[1])) - 1e-6));
});

for (const id of ["labels-on", "first-row"]) {
  $(id).addEventListener("change", () => {
    if (!$("labels-on").checked) delete doc.labels;
    else doc.labels = { first_row: Math.max(0, Math.round(Number($("first-row").value) || 0)) };
    changed();
  });
}

$("token").addEventListener("change", () => setToken($("token").value.trim()));

// ---- the plan image ----

$("image-file").addEventListener("change", async () => {
  const file = $("image-file").files[0];
  if (!file) return;
  const name = file.name.replace(/[^A-Za-z0-9._-]/g, "_").replace(/^\.+/, "");
  try {
    const uploaded = await api(onFloor("/api/editor/image?name=" + encodeURIComponent(name)), { method: "PUT", bytes: await file.arrayBuffer() });
    image = uploaded;
    if (doc.floorplan) doc.floorplan.image = uploaded.name;
    measure = [];
    syncForm();
    changed();
    fitView();
    fill($("save-status"), `plan image ${uploaded.name} stored beside the site file`);
  } catch (e) {
    showSaveStatus(e.message, true);
  }
});

$("scale-apply").addEventListener("click", () => {
  const metres = Number($("scale-m").value);
  if (!image || measure.length !== 2 || !(metres > 0)) {
    showSaveStatus("open a plan image, click two points with Measure, and give their distance in metres", true);
    return;
  }
  const [a, b] = measure;
  const pxPerM = Math.hypot(b[0] - a[0], b[1] - a[1]) / metres;
  const f = frame();
  const sign = f.up ? -1 : 1;
  let atA;
  if (doc.floorplan) atA = f.world(applyMatrix(imageMatrix(), a));
  else atA = [f.origin[0] + a[0] / pxPerM, f.origin[1] + (sign * a[1]) / pxPerM];
  const atB = [atA[0] + (b[0] - a[0]) / pxPerM, atA[1] + (sign * (b[1] - a[1])) / pxPerM];
  doc.floorplan = {
    image: image.name,
    reference: [
      { px: a.map((v) => fixed(v, 1)), m: atA.map((v) => fixed(v, 3)) },
      { px: b.map((v) => fixed(v, 1)), m: atB.map((v) => fixed(v, 3)) },
    ],
  };
  measure = [];
  const g = grid();
  if (!g.w) {
    // A new site: a blocked grid over the whole plan, to paint the floor on.
    const c = Number(doc.cell_m) || 1;
    const w = Math.ceil(image.width / pxPerM / c);
    const hh = Math.ceil(image.height / pxPerM / c);
    if (w * hh <= MAX_AUTO_CELLS) setRows(Array.from({ length: hh }, () => ".".repeat(w)));
  }
  syncForm();
  changed();
  fitView();
});

// ---- pointer tools ----

function cellAt(g) {
  return [Math.floor(g[0]), Math.floor(g[1])];
}

function worldAt(g) {
  return frame().world(g).map((v) => fixed(round(v, 0.01), 2));
}

function paintAt(g, glyph, brush) {
  let grd = grid();
  if (!grd.rows) {
    if (!grd.w) return false;
    // An open floor becomes a map of open cells to paint on.
    setRows(Array.from({ length: grd.h }, () => "#".repeat(grd.w)));
    grd = grid();
  }
  const [cx, cy] = cellAt(g);
  const r = (brush - 1) / 2;
  let any = false;
  const rows = grd.rows.map((row) => [...row]);
  for (let y = cy - r; y <= cy + r; y++) {
    for (let x = cx - r; x <= cx + r; x++) {
      if (x >= 0 && y >= 0 && x < grd.w && y < grd.h && rows[y][x] !== glyph) {
        rows[y][x] = glyph;
        any = true;
      }
    }
  }
  if (any) setRows(rows.map((r) => r.join("")));
  return any;
}

function fillRect(a, b, glyph) {
  const grd = grid();
  if (!grd.rows) paintAt(a, glyph, 1);
  const rows = grid().rows.map((row) => [...row]);
  const [x0, x1] = [Math.min(a[0], b[0]), Math.max(a[0], b[0])];
  const [y0, y1] = [Math.min(a[1], b[1]), Math.max(a[1], b[1])];
  for (let y = Math.max(0, y0); y <= Math.min(rows.length - 1, y1); y++) {
    for (let x = Math.max(0, x0); x <= Math.min(rows[y].length - 1, x1); x++) rows[y][x] = glyph;
  }
  setRows(rows.map((r) => r.join("")));
}

svg.addEventListener("pointerdown", (e) => {
  if (e.button !== 0) return;
  const g = view.toGrid(e);
  const t = tool();
  const target = e.target.closest && e.target.closest("[data-kind]");
  if (t === "paint") {
    svg.setPointerCapture(e.pointerId);
    const glyph = $("glyph").value;
    if (e.shiftKey) painting = { rect: cellAt(g), glyph };
    else {
      painting = { glyph, brush: Number($("brush").value) };
      if (paintAt(g, glyph, painting.brush)) render();
    }
  } else if (t === "select" && target && (target.dataset.kind === "beacon" || target.dataset.kind === "place")) {
    select(target.dataset.kind, target.dataset.key);
    dragging = { kind: target.dataset.kind, key: target.dataset.key, moved: false };
    svg.setPointerCapture(e.pointerId);
  }
});

svg.addEventListener("pointermove", (e) => {
  const g = view.toGrid(e);
  const w = frame().world(g);
  const c = cellAt(g);
  fill($("cursor"), `${w[0].toFixed(2)}, ${w[1].toFixed(2)} m · cell [${c[0]}, ${c[1]}]`);
  if (painting && !painting.rect) {
    if (paintAt(g, painting.glyph, painting.brush)) render();
  } else if (painting && painting.rect) {
    const a = painting.rect;
    fill(view.layers.draft, s("rect", { class: "rect-draft", x: Math.min(a[0], c[0]), y: Math.min(a[1], c[1]), width: Math.abs(a[0] - c[0]) + 1, height: Math.abs(a[1] - c[1]) + 1 }));
  } else if (dragging) {
    dragging.moved = true;
    moveSelected(dragging, g);
    render();
  }
});

svg.addEventListener("pointerup", (e) => {
  if (painting) {
    if (painting.rect) fillRect(painting.rect, cellAt(view.toGrid(e)), painting.glyph);
    painting = null;
    syncForm();
    changed();
  }
  if (dragging) {
    const moved = dragging.moved;
    dragging = null;
    if (moved) {
      showSelected();
      changed();
    }
  }
});

function moveSelected(item, g) {
  if (item.kind === "beacon") {
    const b = doc.beacon.find((b) => b.id === item.key);
    if (b) {
      delete b.cell;
      b.pos = worldAt(g);
    }
  } else if (item.kind === "place") {
    doc.places[item.key] = cellAt(g);
  }
}

svg.addEventListener("click", (e) => {
  if (view.lastDragMoved && tool() === "pan") return;
  const g = view.toGrid(e);
  const t = tool();
  const target = e.target.closest && e.target.closest("[data-kind]");
  const pixel = applyMatrix(invertMatrix(imageMatrix()), g);
  if (t === "measure") {
    if (!image) return showSaveStatus("open a plan image first", true);
    measure = measure.length >= 2 ? [pixel] : [...measure, pixel];
    if (measure.length === 2) $("scale-m").focus();
    render();
  } else if (t === "corner") {
    if (!doc.floorplan) return showSaveStatus("set the scale first", true);
    // The clicked spot becomes the outer top-left corner of cell [0, 0].
    const here = frame().world(g);
    const origin = doc.origin_m || [0, 0];
    shiftReference(origin[0] - here[0], origin[1] - here[1]);
    changed();
  } else if (t === "obstacle" || t === "wall") {
    draft.push(worldAt(g));
    render();
  } else if (t === "beacon") {
    addBeacon(worldAt(g));
  } else if (t === "place") {
    addPlace(cellAt(g));
  } else if (t === "stop") {
    placeStop(cellAt(g));
  } else if (t === "select") {
    if (target && target.dataset.kind === "connector") chooseConnector(Number(target.dataset.key));
    else if (target) select(target.dataset.kind, target.dataset.key);
    else select(null);
  }
});

svg.addEventListener("dblclick", (e) => {
  if (tool() === "obstacle" || tool() === "wall") {
    e.preventDefault();
    finishDraft();
  }
});

document.addEventListener("keydown", (e) => {
  const typing = e.target instanceof HTMLInputElement || e.target instanceof HTMLSelectElement || e.target instanceof HTMLTextAreaElement;
  if (typing) return;
  if (e.key === "Enter") finishDraft();
  else if (e.key === "Escape") {
    draft = [];
    measure = [];
    render();
  } else if ((e.key === "Delete" || e.key === "Backspace") && selected) {
    e.preventDefault();
    removeItem(selected.kind, selected.key);
  }
});

for (const radio of document.querySelectorAll("input[name=tool]")) {
  radio.addEventListener("change", () => {
    draft = [];
    showToolOptions();
    render();
  });
}

function showToolOptions() {
  const t = tool();
  for (const el of document.querySelectorAll(".tool-options")) el.hidden = el.dataset.for !== t;
  svg.dataset.tool = t;
}

function finishDraft() {
  // A double-click also clicked twice: drop repeated points.
  const points = draft.filter((p, i) => i === 0 || p[0] !== draft[i - 1][0] || p[1] !== draft[i - 1][1]);
  if (tool() === "obstacle" && points.length >= 3) {
    (doc.obstacles ||= []).push({ polygon: points });
  } else if (tool() === "wall" && points.length >= 2) {
    const wall = { line: points };
    const t = Number($("wall-thickness").value);
    if (t > 0) wall.thickness_m = t;
    (doc.walls ||= []).push(wall);
  }
  draft = [];
  changed();
}

function addBeacon(pos) {
  const beacons = (doc.beacon ||= []);
  const last = beacons[beacons.length - 1];
  const minors = beacons.map((b) => b.minor);
  let n = beacons.length + 1;
  while (beacons.some((b) => b.id === "b" + n)) n++;
  // A heard beacon picked from the list keeps its own identity; otherwise
  // the next minor of the last beacon's UUID and major.
  const id = placing || {
    uuid: last ? last.uuid : randomUuid(),
    major: last ? last.major : 1,
    minor: minors.length ? Math.min(65535, Math.max(...minors) + 1) : 1,
  };
  placing = null;
  beacons.push({ id: "b" + n, uuid: id.uuid, major: id.major, minor: id.minor, pos });
  select("beacon", "b" + n);
  changed();
}

/** The heard beacons the document does not have yet (matched by UUID, major and minor). */
function unplacedHeard() {
  const has = new Set((doc.beacon || []).map((b) => `${String(b.uuid).toLowerCase()}/${b.major}/${b.minor}`));
  return heard.filter((b) => !has.has(`${b.uuid.toLowerCase()}/${b.major}/${b.minor}`));
}

function renderHeard() {
  const unplaced = doc ? unplacedHeard() : [];
  $("heard-box").hidden = heard.length === 0;
  fill($("heard-count"), String(unplaced.length));
  fill(
    $("heard"),
    unplaced.map((b) => {
      const picked = placing && placing.uuid === b.uuid && placing.major === b.major && placing.minor === b.minor;
      return h(
        "li",
        { class: picked ? "selected" : "" },
        h(
          "button",
          {
            type: "button",
            class: "link",
            title: `heard by ${b.observers.join(", ")}${b.more_observers ? " and more" : ""}`,
            onclick: () => {
              placing = { uuid: b.uuid, major: b.major, minor: b.minor };
              document.querySelector("input[name=tool][value=beacon]").checked = true;
              showToolOptions();
              renderHeard();
            },
          },
          `${b.uuid.slice(0, 8)}… ${b.major}/${b.minor} · ${b.count}× · ${b.rssi_median} dBm`,
        ),
      );
    }),
  );
}

/** What the gateway hears, when it serves this page (`gangway site edit` alone has no radio). */
async function loadHeard() {
  try {
    const report = await api("/api/heard");
    heard = report && Array.isArray(report.beacons) ? report.beacons : [];
  } catch {
    heard = [];
  }
  renderHeard();
}

function randomUuid() {
  const b = crypto.getRandomValues(new Uint8Array(16));
  b[6] = (b[6] & 0x0f) | 0x40;
  b[8] = (b[8] & 0x3f) | 0x80;
  const hex = [...b].map((x) => x.toString(16).padStart(2, "0")).join("");
  return `${hex.slice(0, 8)}-${hex.slice(8, 12)}-${hex.slice(12, 16)}-${hex.slice(16, 20)}-${hex.slice(20)}`;
}

function addPlace(cell) {
  const places = (doc.places ||= {});
  let name = $("place-name").value.trim();
  if (!name) {
    let n = Object.keys(places).length + 1;
    while (places["place " + n]) n++;
    name = "place " + n;
  }
  places[name] = cell;
  $("place-name").value = "";
  select("place", name);
  changed();
}

function removeItem(kind, key) {
  if (kind === "beacon") doc.beacon = doc.beacon.filter((b) => b.id !== key);
  else if (kind === "gateway") doc.gateway = doc.gateway.filter((g) => g.id !== key);
  else if (kind === "place") delete doc.places[key];
  else if (kind === "obstacle") doc.obstacles.splice(Number(key), 1);
  else if (kind === "wall") doc.walls.splice(Number(key), 1);
  for (const k of ["beacon", "gateway", "obstacles", "walls"]) if (doc[k] && doc[k].length === 0) delete doc[k];
  if (doc.places && Object.keys(doc.places).length === 0) delete doc.places;
  select(null);
  changed();
}

// ---- selection ----

function select(kind, key) {
  selected = kind ? { kind, key } : null;
  showSelected();
  render();
}

function numberInput(label, value, onChange, step = "any") {
  const input = h("input", { type: "number", step, value: value ?? "" });
  input.addEventListener("change", () => onChange(input.value === "" ? undefined : Number(input.value)));
  return h("label", {}, label + " ", input);
}

function textInput(label, value, onChange) {
  const input = h("input", { type: "text", value: value ?? "" });
  input.addEventListener("change", () => onChange(input.value));
  return h("label", {}, label + " ", input);
}

function showSelected() {
  const box = $("selected-form");
  $("selected").hidden = !selected;
  if (!selected) return fill(box);
  const { kind, key } = selected;
  const remove = h("button", { type: "button", onclick: () => removeItem(kind, key) }, "Delete");
  if (kind === "beacon" || kind === "gateway") {
    const a = (doc[kind] || []).find((b) => b.id === key);
    if (!a) return fill(box);
    const pos = a.pos || (a.cell ? frame().world([a.cell[0] + 0.5, a.cell[1] + 0.5]).map((v) => fixed(v, 2)) : [undefined, undefined]);
    const setPos = (i) => (v) => {
      const p = [...pos];
      p[i] = v;
      delete a.cell;
      a.pos = p;
      changed();
      showSelected();
    };
    const fields = [
      textInput("id", a.id, (v) => {
        a.id = v;
        selected.key = v;
        changed();
      }),
    ];
    if (kind === "beacon") {
      fields.push(
        textInput("uuid", a.uuid, (v) => {
          a.uuid = v.trim();
          changed();
        }),
        numberInput("major", a.major, (v) => ((a.major = v), changed()), 1),
        numberInput("minor", a.minor, (v) => ((a.minor = v), changed()), 1),
      );
    }
    fields.push(
      numberInput("x m", pos[0], setPos(0), 0.01),
      numberInput("y m", pos[1], setPos(1), 0.01),
      numberInput("height m", a.height_m, (v) => {
        if (v === undefined) delete a.height_m;
        else a.height_m = v;
        changed();
      }, 0.1),
    );
    if (kind === "beacon") {
      fields.push(
        numberInput("tx power dBm", a.tx_power, (v) => {
          if (v === undefined) delete a.tx_power;
          else a.tx_power = v;
          changed();
        }, 1),
      );
    }
    return fill(box, h("div", { class: "grid-form" }, fields), remove);
  }
  if (kind === "place") {
    const cell = doc.places[key];
    if (!cell) return fill(box);
    return fill(
      box,
      h(
        "div",
        { class: "grid-form" },
        textInput("name", key, (v) => {
          const name = v.trim();
          if (!name || name === key) return;
          delete doc.places[key];
          doc.places[name] = cell;
          selected.key = name;
          changed();
          showSelected();
        }),
        numberInput("column", cell[0], (v) => ((cell[0] = v), changed()), 1),
        numberInput("row", cell[1], (v) => ((cell[1] = v), changed()), 1),
      ),
      remove,
    );
  }
  const shape = kind === "obstacle" ? doc.obstacles[Number(key)] : doc.walls[Number(key)];
  if (!shape) return fill(box);
  const points = shape.polygon || shape.line;
  const fields = [h("p", {}, `${kind} with ${points.length} points`)];
  if (kind === "wall") {
    fields.push(
      numberInput("thickness m", shape.thickness_m, (v) => {
        if (!v) delete shape.thickness_m;
        else shape.thickness_m = v;
        changed();
      }, 0.05),
    );
  }
  fill(box, fields, remove);
}

// ---- drawing ----

function beaconGrid(a) {
  if (a.pos) return frame().grid(a.pos);
  if (a.cell) return [a.cell[0] + 0.5, a.cell[1] + 0.5];
  return null;
}

function render() {
  if (!doc) return;
  const g = grid();
  const m = imageMatrix();
  svg.classList.toggle("with-plan", !!image);
  drawFloorplan(view.layers.floorplan, image && image.url, m, image && image.width, image && image.height);
  const tiles = g.rows ? g.rows.join("") : "#".repeat(g.w * g.h);
  fill(view.layers.tiles, g.w ? tilePaths(g.w, g.h, tiles) : []);
  // Cells the obstacles and walls block, from the last check.
  const overlay = [];
  if (lastView && lastView.width === g.w && lastView.height === g.h) {
    const parts = [];
    for (let i = 0; i < tiles.length; i++) {
      if (tiles[i] !== "." && lastView.tiles[i] === ".") parts.push(`M${i % g.w} ${Math.floor(i / g.w)}h1v1h-1z`);
    }
    if (parts.length) overlay.push(s("path", { class: "shape-blocked", d: parts.join("") }));
  }
  fill(view.layers.overlay, overlay);
  fill(view.layers.grid, g.w ? gridLines(g.w, g.h) : []);
  const f = frame();
  const shapes = [];
  (doc.obstacles || []).forEach((o, i) => {
    const isSel = selected && selected.kind === "obstacle" && selected.key === String(i);
    shapes.push(s("polygon", { class: "obstacle" + (isSel ? " selected" : ""), "data-kind": "obstacle", "data-key": i, points: o.polygon.map((p) => f.grid(p).join(",")).join(" ") }));
  });
  (doc.walls || []).forEach((w, i) => {
    const isSel = selected && selected.kind === "wall" && selected.key === String(i);
    const width = Math.max((w.thickness_m || 0) / f.cellM, 0.12);
    shapes.push(s("polyline", { class: "wall" + (isSel ? " selected" : ""), "data-kind": "wall", "data-key": i, "stroke-width": width, points: w.line.map((p) => f.grid(p).join(",")).join(" ") }));
  });
  fill(view.layers.shapes, shapes);
  const anchors = [];
  for (const kind of ["beacon", "gateway"]) {
    for (const a of doc[kind] || []) {
      const at = beaconGrid(a);
      if (!at) continue;
      const marker = anchorMarker(kind, a.id, at, { "data-kind": kind, "data-key": a.id }, s("title", {}, `${kind} ${a.id}`));
      if (selected && selected.kind === kind && selected.key === a.id) marker.node.classList.add("selected");
      anchors.push(marker);
    }
  }
  const places = Object.entries(doc.places || {}).map(([name, cell]) => {
    const marker = placeMarker(name, cell, { "data-kind": "place", "data-key": name }, s("title", {}, name));
    if (selected && selected.kind === "place" && selected.key === name) marker.node.classList.add("selected");
    return marker;
  });
  const stops = stopMarkers();
  fill(view.layers.anchors, anchors.map((a) => a.node));
  fill(view.layers.places, places.map((p) => p.node), stops.map((c) => c.node));
  view.labels.set([...places, ...stops, ...anchors].map((m) => m.label));
  const draftParts = [];
  if (measure.length) {
    const pts = measure.map((p) => applyMatrix(m, p));
    if (pts.length === 2) draftParts.push(s("line", { class: "measure", x1: pts[0][0], y1: pts[0][1], x2: pts[1][0], y2: pts[1][1] }));
    for (const p of pts) draftParts.push(s("circle", { class: "measure-point", cx: p[0], cy: p[1], r: 0.25 }));
    if (measure.length === 2) {
      const px = Math.hypot(measure[1][0] - measure[0][0], measure[1][1] - measure[0][1]);
      fill($("scale-info"), `measured ${px.toFixed(1)} px: give the distance in metres and press Set scale`);
    }
  }
  if (draft.length) {
    const pts = draft.map((p) => f.grid(p).join(",")).join(" ");
    draftParts.push(s("polyline", { class: tool() === "wall" ? "wall draft" : "obstacle draft", points: pts }));
    for (const p of draft) {
      const [x, y] = f.grid(p);
      draftParts.push(s("circle", { class: "measure-point", cx: x, cy: y, r: 0.15 }));
    }
  }
  fill(view.layers.draft, draftParts);
  renderLists();
}

function renderLists() {
  const item = (kind, key, text) =>
    h(
      "li",
      { class: selected && selected.kind === kind && selected.key === String(key) ? "selected" : "" },
      h("button", { type: "button", class: "link", onclick: () => select(kind, String(key)) }, text),
      h("button", { type: "button", class: "remove", title: "delete", onclick: () => removeItem(kind, String(key)) }, "✕"),
    );
  const beacons = doc.beacon || [];
  fill($("beacons"), beacons.map((b) => item("beacon", b.id, `${b.id}  ${b.pos ? b.pos.join(", ") + " m" : b.cell ? "cell " + b.cell.join(", ") : "no position"}`)));
  fill($("beacon-count"), String(beacons.length));
  renderHeard();
  const places = Object.entries(doc.places || {});
  fill($("places"), places.map(([name, cell]) => item("place", name, `${name}  [${cell.join(", ")}]`)));
  fill($("place-count"), String(places.length));
  const shapes = [
    ...(doc.obstacles || []).map((o, i) => item("obstacle", i, `obstacle ${i + 1}: ${o.polygon.length} corners`)),
    ...(doc.walls || []).map((w, i) => item("wall", i, `wall ${i + 1}: ${w.line.length} points${w.thickness_m ? `, ${w.thickness_m} m` : ""}`)),
  ];
  fill($("shapes"), shapes);
  fill($("shape-count"), String(shapes.length));
}

// ---- connectors: a building's, in the building file ----
//
// Each floor's page edits that floor's stops; the building's connectors are
// kept in this tab (sessionStorage) until saved, so a connector's stops
// can be placed floor after floor. The gateway rewrites only the building
// file's [[connectors]] and checks the building as `gangway check` does.

const CONNECTORS_DRAFT = "gangway-connectors-draft";
let building = null; // { path, connectors, kinds, floors } on a building
let chosen = null; // index of the chosen connector

async function loadConnectors(opened) {
  if (!opened.floors || opened.floors.length < 2) return;
  const got = await api("/api/editor/connectors");
  building = { path: got.path, connectors: got.connectors, kinds: got.kinds, floors: opened.floors.map((f) => f.name) };
  const draft = JSON.parse(sessionStorage.getItem(CONNECTORS_DRAFT) || "null");
  if (draft && draft.path === got.path) {
    building.connectors = draft.connectors;
    chosen = draft.chosen;
    showConnectorsStatus("changed in this tab, not saved yet", true);
  }
  $("connectors-box").hidden = false;
  $("stop-tool").hidden = false;
  $("connectors-save").disabled = access.read_only;
  showConnectorProblems(got.problems);
  renderConnectors();
  render();
}

function connectorsChanged() {
  sessionStorage.setItem(CONNECTORS_DRAFT, JSON.stringify({ path: building.path, connectors: building.connectors, chosen }));
  showConnectorsStatus("changed, not saved yet", true);
  renderConnectors();
  render();
}

function stopHere(c) {
  return c.stops.find((stop) => stop.floor === floor);
}

function chooseConnector(i) {
  chosen = i;
  renderConnectors();
  render();
}

function addConnector() {
  let n = building.connectors.length + 1;
  while (building.connectors.some((c) => c.id === "connector " + n)) n++;
  building.connectors.push({ id: "connector " + n, kind: "lift", stops: [] });
  chosen = building.connectors.length - 1;
}

/** The chosen connector (a new one when none is) stops on `cell` of this floor. */
function placeStop(cell) {
  if (!building) return;
  if (chosen === null || !building.connectors[chosen]) addConnector();
  const c = building.connectors[chosen];
  const here = stopHere(c);
  if (here) here.cell = cell;
  else c.stops.push({ floor, cell });
  c.stops.sort((a, b) => building.floors.indexOf(a.floor) - building.floors.indexOf(b.floor));
  connectorsChanged();
}

function removeConnector(i) {
  building.connectors.splice(i, 1);
  chosen = null;
  connectorsChanged();
}

function stopMarkers() {
  if (!building) return [];
  return building.connectors.flatMap((c, i) => {
    const here = stopHere(c);
    if (!here) return [];
    const to = c.stops.filter((stop) => stop.floor !== floor).map((stop) => stop.floor);
    const marker = connectorMarker({ id: c.id, kind: c.kind, cell: here.cell, to }, { "data-kind": "connector", "data-key": i });
    if (i === chosen) marker.node.classList.add("selected");
    return [marker];
  });
}

function renderConnectors() {
  const list = building.connectors.map((c, i) =>
    h(
      "li",
      { class: i === chosen ? "selected" : "", "data-connector": c.id },
      h("button", { type: "button", class: "link", onclick: () => chooseConnector(i) }, `${c.id} · ${c.kind} · ${c.stops.map((stop) => stop.floor).join(", ") || "no stops"}`),
      h("button", { type: "button", class: "remove", title: "delete", onclick: () => removeConnector(i) }, "✕"),
    ),
  );
  fill($("connectors"), list);
  fill($("connector-count"), String(building.connectors.length));
  const c = building.connectors[chosen];
  if (!c) return fill($("connector-form"));
  const kind = building.kinds.find((k) => k.kind === c.kind) || building.kinds[0];
  const kinds = h(
    "select",
    { id: "connector-kind", onchange: (e) => ((c.kind = e.target.value), connectorsChanged()) },
    building.kinds.map((k) => h("option", { value: k.kind, selected: k.kind === c.kind }, k.step_free ? `${k.kind} (step-free)` : k.kind)),
  );
  const seconds = (key, label, fallback) => {
    const field = numberInput(label, c[key], (v) => {
      if (v === undefined) delete c[key];
      else c[key] = v;
      connectorsChanged();
    }, 1);
    field.querySelector("input").placeholder = String(fallback);
    return field;
  };
  const stops = c.stops.map((stop) =>
    h(
      "li",
      { class: stop.floor === floor ? "selected" : "" },
      `${stop.floor} [${stop.cell.join(", ")}]`,
      h("button", { type: "button", class: "remove", title: "remove this stop", onclick: () => ((c.stops = c.stops.filter((other) => other !== stop)), connectorsChanged()) }, "✕"),
    ),
  );
  fill(
    $("connector-form"),
    h(
      "div",
      { class: "grid-form" },
      textInput("id", c.id, (v) => ((c.id = v.trim()), connectorsChanged())),
      h("label", {}, "kind ", kinds),
      seconds("s_per_level", "s per level", kind.s_per_level),
      seconds("wait_s", "wait s", kind.wait_s),
    ),
    h("ul", { class: "items" }, stops),
    stopHere(c) ? null : h("p", { class: "hint" }, `No stop on ${floor}: pick the Connector tool and click its cell.`),
  );
}

function showConnectorsStatus(message, bad = false) {
  fill($("connectors-status"), h("span", { class: bad ? "bad" : "ok" }, message));
}

function showConnectorProblems(problems) {
  fill($("connector-problems"), problems.map((p) => h("li", {}, p)));
}

$("connector-add").addEventListener("click", () => {
  addConnector();
  connectorsChanged();
});

$("connectors-save").addEventListener("click", async () => {
  $("connectors-save").disabled = true;
  showConnectorsStatus(served ? "saving, then reloading the gateway…" : "saving…");
  try {
    const result = await api("/api/editor/connectors", { method: "PUT", json: { connectors: building.connectors } });
    sessionStorage.removeItem(CONNECTORS_DRAFT);
    showConnectorProblems([]);
    showConnectorsStatus(result.message, result.applied === false);
  } catch (e) {
    showConnectorsStatus(e.message, true);
  } finally {
    $("connectors-save").disabled = access.read_only;
  }
});

// ---- checking and saving ----

function scheduleCheck() {
  clearTimeout(checkTimer);
  fill($("check-summary"), "checking…");
  checkTimer = setTimeout(check, CHECK_DELAY_MS);
}

async function check() {
  const seq = ++checkSeq;
  try {
    const result = await api(onFloor("/api/editor/check"), { method: "POST", json: { doc } });
    if (seq !== checkSeq) return;
    showToml(result.toml);
    if (result.ok) {
      lastView = result.view;
      const v = result.view;
      fill($("check-summary"), h("span", { class: "ok" }, `ok: ${v.width}×${v.height} cells, ${v.walkable} walkable, ${v.beacons.length} beacons, ${v.places.length} places`));
      showProblems([]);
      render();
    } else {
      fill($("check-summary"), h("span", { class: "bad" }, `${result.problems.length} problem${result.problems.length === 1 ? "" : "s"}: not saved until fixed`));
      showProblems(result.problems);
    }
  } catch (e) {
    if (seq === checkSeq) showProblems([e.message]);
  }
}

function showProblems(problems) {
  fill($("problems"), problems.map((p) => h("li", {}, p)));
}

function showSaveStatus(message, bad = false) {
  fill($("save-status"), h("span", { class: bad ? "bad" : "ok" }, message));
}

/** The site file as it would be saved, shown and offered as a download. */
let downloadUrl = "";
function showToml(toml) {
  fill($("toml"), toml);
  if (downloadUrl) URL.revokeObjectURL(downloadUrl);
  downloadUrl = URL.createObjectURL(new Blob([toml], { type: "application/toml" }));
  $("download").href = downloadUrl;
}

$("save").addEventListener("click", async () => {
  $("save").disabled = true;
  showSaveStatus(served ? "saving, then reloading the gateway…" : "saving…");
  try {
    const result = await api(onFloor("/api/editor/site"), { method: "PUT", json: { doc } });
    showToml(result.toml);
    // `applied`: true, the gateway serves it now; false, it does not
    // (refused, or saved elsewhere); null, no gateway serves this file here.
    showSaveStatus(result.message, result.applied === false);
  } catch (e) {
    showSaveStatus(e.message, true);
    $("toml").closest("details").open = true;
  } finally {
    $("save").disabled = access.read_only;
  }
});

/** How often the list of heard beacons is refreshed (the gateway renews it every stats tick). */
const HEARD_REFRESH_MS = 30_000;

showToolOptions();
load()
  .then(() => {
    loadHeard();
    setInterval(loadHeard, HEARD_REFRESH_MS);
  })
  .catch((e) => showProblems([e.message]));
