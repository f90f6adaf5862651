// Shared by the pages: the API client, element helpers, the site's metric
// frame, and the plan view (an SVG in grid units with pan and zoom).
//
// Nothing here builds HTML from strings: every name or id (which may come
// from the air or the broker) goes into the page as a text node or an
// attribute value, never as markup.

const SVG_NS = "http://www.w3.org/2000/svg";
const TOKEN_KEY = "gangway-web-token";

/** The write token the user gave this tab (sessionStorage), if any. */
export function token() {
  return sessionStorage.getItem(TOKEN_KEY) || "";
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** Calls the gateway's API; throws an Error carrying the server's message. */
export async function api(path, { method = "GET", json, bytes } = {}) {
  const headers = {};
  let body;
  if (json !== undefined) {
    headers["Content-Type"] = "application/json";
    body = JSON.stringify(json);
  } else if (bytes !== undefined) {
    headers["Content-Type"] = "application/octet-stream";
    body = bytes;
  }
  if (method !== "GET" && token()) headers["Authorization"] = "Bearer " + token();
  const response = await fetch(path, { method, headers, body });
  const kind = response.headers.get("Content-Type") || "";
  const data = kind.startsWith("application/json") ? await response.json() : await response.text();
  if (!response.ok) {
    const message = data && data.error ? data.error.message : String(data);
    const error = new Error(message || response.statusText);
    error.status = response.status;
    error.code = data && data.error ? data.error.code : undefined;
    throw error;
  }
  return data;
}

/** An HTML element: `attrs` are attributes (or `on*` listeners); strings
 * among `children` become text nodes. */
export function h(tag, attrs = {}, ...children) {
  return build(document.createElement(tag), attrs, children);
}

/** An SVG element, like `h`. */
export function s(tag, attrs = {}, ...children) {
  return build(document.createElementNS(SVG_NS, tag), attrs, children);
}

function build(node, attrs, children) {
  for (const [key, value] of Object.entries(attrs)) {
    if (value === undefined || value === null || value === false) continue;
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === undefined || child === null || child === false) continue;
    node.append(typeof child === "string" || typeof child === "number" ? document.createTextNode(String(child)) : child);
  }
  return node;
}

/** Replaces the children of `node`. */
export function fill(node, ...children) {
  node.replaceChildren();
  build(node, {}, children);
  return node;
}

/** The site's metric frame: grid units (cell [x, y] spans x..x+1, y..y+1,
 * y down) to world metres and back, as in src/site.rs. */
export class Frame {
  constructor(cellM, originM = [0, 0], yAxis = "down") {
    this.cellM = cellM;
    this.origin = originM || [0, 0];
    this.up = yAxis === "up";
  }
  world([gx, gy]) {
    const [ox, oy] = this.origin;
    return [ox + gx * this.cellM, this.up ? oy - gy * this.cellM : oy + gy * this.cellM];
  }
  grid([x, y]) {
    const [ox, oy] = this.origin;
    return [(x - ox) / this.cellM, this.up ? (oy - y) / this.cellM : (y - oy) / this.cellM];
  }
}

/** The similarity taking pixels `from[i]` to grid units `to[i]`, as an SVG
 * matrix [a, b, c, d, e, f] (crates/core/src/site/floorplan.rs does the same). */
export function similarity(from, to) {
  const dz = [from[1][0] - from[0][0], from[1][1] - from[0][1]];
  const dw = [to[1][0] - to[0][0], to[1][1] - to[0][1]];
  const norm = dz[0] * dz[0] + dz[1] * dz[1];
  const sr = (dw[0] * dz[0] + dw[1] * dz[1]) / norm;
  const si = (dw[1] * dz[0] - dw[0] * dz[1]) / norm;
  const tr = to[0][0] - (sr * from[0][0] - si * from[0][1]);
  const ti = to[0][1] - (si * from[0][0] + sr * from[0][1]);
  return [sr, si, -si, sr, tr, ti];
}

export function applyMatrix([a, b, c, d, e, f], [x, y]) {
  return [a * x + c * y + e, b * x + d * y + f];
}

export function invertMatrix([a, b, c, d, e, f]) {
  const det = a * d - b * c;
  return [d / det, -b / det, -c / det, a / det, (c * f - d * e) / det, (b * e - a * f) / det];
}

/** Glyph classes of the tile layer. */
export const TILE_CLASSES = { "#": "open", ".": "blocked", s: "stairs", e: "elevator", d: "door", n: "narrow" };

/** One SVG path per tile kind, each cell a unit square (runs of a row
 * merged), so a 10,000-cell floor is a handful of elements. */
export function tilePaths(width, height, tiles) {
  const runs = {};
  for (let y = 0; y < height; y++) {
    let x = 0;
    while (x < width) {
      const glyph = tiles[y * width + x];
      let end = x + 1;
      while (end < width && tiles[y * width + end] === glyph) end++;
      (runs[glyph] ||= []).push(`M${x} ${y}h${end - x}v1h${x - end}z`);
      x = end;
    }
  }
  return Object.entries(runs).map(([glyph, parts]) =>
    s("path", { class: "tile " + (TILE_CLASSES[glyph] || "unknown"), d: parts.join("") }),
  );
}

/** Grid lines over a width × height grid, one path. */
export function gridLines(width, height) {
  const parts = [];
  for (let x = 0; x <= width; x++) parts.push(`M${x} 0v${height}`);
  for (let y = 0; y <= height; y++) parts.push(`M0 ${y}h${width}`);
  return s("path", { class: "gridlines", d: parts.join("") });
}

/** A pannable, zoomable SVG drawn in grid units. Drag with the middle
 * button (or the left one when `panWithLeft()` says so) to pan; the wheel
 * zooms about the pointer. */
export class PlanView {
  constructor(svg, { panWithLeft = () => true, overlays = [] } = {}) {
    this.svg = svg;
    this.box = [0, 0, 10, 10];
    this.panWithLeft = panWithLeft;
    this.labels = new Labels(this, overlays);
    this.listeners = [];
    this.layers = {};
    for (const name of ["floorplan", "tiles", "overlay", "grid", "shapes", "heat", "route", "anchors", "places", "draft"]) {
      this.layers[name] = s("g", { class: "layer-" + name });
      svg.append(this.layers[name]);
    }
    let drag = null;
    svg.addEventListener("pointerdown", (e) => {
      if (e.button === 1 || (e.button === 0 && this.panWithLeft(e))) {
        drag = { x: e.clientX, y: e.clientY, box: [...this.box], id: e.pointerId, moved: false };
        svg.setPointerCapture(e.pointerId);
      }
    });
    svg.addEventListener("pointermove", (e) => {
      if (!drag || drag.id !== e.pointerId) return;
      const scale = this.box[2] / svg.clientWidth;
      const dx = (e.clientX - drag.x) * scale;
      const dy = (e.clientY - drag.y) * scale;
      if (Math.abs(e.clientX - drag.x) + Math.abs(e.clientY - drag.y) > 3) drag.moved = true;
      this.setBox([drag.box[0] - dx, drag.box[1] - dy, drag.box[2], drag.box[3]]);
    });
    const end = (e) => {
      if (drag && drag.id === e.pointerId) {
        this.lastDragMoved = drag.moved;
        drag = null;
      }
    };
    svg.addEventListener("pointerup", end);
    svg.addEventListener("pointercancel", end);
    svg.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        const [gx, gy] = this.toGrid(e);
        const k = Math.exp(Math.sign(e.deltaY) * 0.15);
        const [x, y, w, hh] = this.box;
        this.setBox([gx - (gx - x) * k, gy - (gy - y) * k, w * k, hh * k]);
      },
      { passive: false },
    );
    new ResizeObserver(() => this.setBox(this.box)).observe(svg);
    // The keyboard: arrows pan, + and - zoom about the centre.
    svg.setAttribute("tabindex", "0");
    svg.addEventListener("keydown", (e) => {
      const [x, y, w, hh] = this.box;
      const step = w / 8;
      const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
      if (moves[e.key]) {
        this.setBox([x + moves[e.key][0], y + moves[e.key][1], w, hh]);
      } else if (e.key === "+" || e.key === "=" || e.key === "-") {
        const k = e.key === "-" ? 1.25 : 0.8;
        this.setBox([x + (w * (1 - k)) / 2, y + (hh * (1 - k)) / 2, w * k, hh * k]);
      } else {
        return;
      }
      e.preventDefault();
    });
  }

  setBox([x, y, w, hh]) {
    // Keep the aspect of the element so a unit stays square.
    const aspect = this.svg.clientHeight / Math.max(1, this.svg.clientWidth) || 1;
    hh = w * aspect;
    this.box = [x, y, w, hh];
    this.svg.setAttribute("viewBox", `${x} ${y} ${w} ${hh}`);
    this.labels.schedule();
    for (const listener of this.listeners) listener();
  }

  /** Calls `listener` whenever the view pans, zooms or resizes. */
  onChange(listener) {
    this.listeners.push(listener);
  }

  /** Shows the rectangle [x0, y0]..[x1, y1] (grid units) whole. */
  fit(x0, y0, x1, y1) {
    const margin = 0.04 * Math.max(x1 - x0, y1 - y0);
    const aspect = this.svg.clientHeight / Math.max(1, this.svg.clientWidth) || 1;
    let w = x1 - x0 + 2 * margin;
    let hh = y1 - y0 + 2 * margin;
    if (hh / w > aspect) w = hh / aspect;
    this.setBox([(x0 + x1) / 2 - w / 2, (y0 + y1) / 2 - (w * aspect) / 2, w, w * aspect]);
  }

  /** Grid units under a pointer event. */
  toGrid(e) {
    const point = this.svg.createSVGPoint();
    point.x = e.clientX;
    point.y = e.clientY;
    const p = point.matrixTransform(this.svg.getScreenCTM().inverse());
    return [p.x, p.y];
  }

  /** Grid units per screen pixel (for sizes that stay readable). */
  unitsPerPixel() {
    return this.box[2] / Math.max(1, this.svg.clientWidth);
  }
}

/** Draws the floor-plan image under the grid. */
export function drawFloorplan(layer, url, matrix, width, height) {
  if (!url) return fill(layer);
  return fill(
    layer,
    s("image", { href: url, x: 0, y: 0, width, height, transform: `matrix(${matrix.join(" ")})`, preserveAspectRatio: "none" }),
  );
}

/** Marker sizes, grid units: a place's square (half side) and an anchor's circle. */
export const PLACE_HALF = 0.42;
export const ANCHOR_R = 0.32;

/** A beacon or gateway marker at `at` (grid units), its id as a label. */
export function anchorMarker(kind, id, at, attrs = {}, ...children) {
  const label = s("text", { class: "anchor-id label" }, id);
  const node = s("g", { class: "anchor " + kind, transform: `translate(${at[0]} ${at[1]})`, ...attrs }, s("circle", { r: ANCHOR_R }), label, ...children);
  return { node, label: { node: label, at, r: ANCHOR_R, px: 11, weight: 400, rank: kind === "gateway" ? 1 : 2 } };
}

/** A place marker on `cell`, its name as a label. */
export function placeMarker(name, cell, attrs = {}, ...children) {
  const at = [cell[0] + 0.5, cell[1] + 0.5];
  const label = s("text", { class: "place-name label" }, name);
  const node = s(
    "g",
    { class: "place", transform: `translate(${at[0]} ${at[1]})`, ...attrs },
    s("rect", { x: -PLACE_HALF, y: -PLACE_HALF, width: 2 * PLACE_HALF, height: 2 * PLACE_HALF, rx: 0.15 }),
    label,
    ...children,
  );
  return { node, label: { node: label, at, r: PLACE_HALF, px: 13, weight: 600, rank: 0 } };
}

/** A connector's stop (stairs, a lift…) on `cell`: its kind and the floors
 * it goes to as a label. `attrs` are the marker's own (the editor's). */
export function connectorMarker(c, attrs = {}) {
  const at = [c.cell[0] + 0.5, c.cell[1] + 0.5];
  const name = c.id === c.kind ? c.kind : `${c.kind} ${c.id}`;
  const to = c.to.length ? ` → ${c.to.join(", ")}` : "";
  const label = s("text", { class: "connector-name label" }, name + to);
  const r = PLACE_HALF;
  const node = s(
    "g",
    { class: "connector " + c.kind, transform: `translate(${at[0]} ${at[1]})`, ...attrs },
    s("path", { d: `M0 ${-r * 1.3} L${r * 1.3} 0 L0 ${r * 1.3} L${-r * 1.3} 0 Z` }),
    label,
    s("title", {}, c.to.length ? `${name}, to floor ${c.to.join(", ")}` : `${name}, on no other floor yet`),
  );
  return { node, label: { node: label, at, r: r * 1.3, px: 12, weight: 600, rank: 0 } };
}

/** Draws a site view (`/api/site`, `/api/editor/check`): tiles, grid lines,
 * beacons, gateways, places and, on a building's floor, its connectors. `withPlan` tints the tiles so the plan
 * shows through. */
export function drawSite(view, site, { withPlan = false } = {}) {
  view.svg.classList.toggle("with-plan", withPlan);
  fill(view.layers.tiles, tilePaths(site.width, site.height, site.tiles));
  fill(view.layers.grid, gridLines(site.width, site.height));
  const anchors = [];
  for (const [list, kind] of [
    [site.beacons, "beacon"],
    [site.gateways, "gateway"],
  ]) {
    for (const a of list) {
      if (!a.grid) continue;
      anchors.push(anchorMarker(kind, a.id, a.grid, {}, s("title", {}, `${kind} ${a.id} at ${a.m[0].toFixed(2)}, ${a.m[1].toFixed(2)} m`)));
    }
  }
  const places = site.places.map((p) => placeMarker(p.name, p.cell, { "data-place": p.name }, s("title", {}, p.label ? `${p.name} (${p.label})` : p.name)));
  fill(view.layers.anchors, anchors.map((a) => a.node));
  const connectors = (site.connectors || []).map(connectorMarker);
  fill(view.layers.places, places.map((p) => p.node), connectors.map((c) => c.node));
  view.labels.set([...places, ...connectors, ...anchors].map((m) => m.label));
}

/** Where a label may go around its marker, as unit offsets (x, y) of the
 * gap: below, above, right, left, then the diagonals. */
const LABEL_SPOTS = [[0, 1], [0, -1], [1, 0], [-1, 0], [1, 1], [-1, 1], [1, -1], [-1, -1]];

/** Labels of the plan's markers (place names, beacon ids), laid out in
 * screen pixels at a constant size whatever the zoom: each goes to the
 * first spot around its marker that overlaps no other label, no marker and
 * no overlay (the legend), and stays inside the view; farther out with a
 * leader line if the near spots are taken; hidden if none is free (a
 * hidden beacon id shows on hover, in the marker's title, and when zoomed
 * in). Places first, then gateways, then beacons. */
class Labels {
  constructor(view, overlays) {
    this.view = view;
    this.overlays = overlays;
    this.items = [];
    this.queued = false;
    this.widths = new Map();
    this.context = document.createElement("canvas").getContext("2d");
  }

  set(items) {
    this.items = items.slice().sort((a, b) => a.rank - b.rank);
    this.schedule();
  }

  schedule() {
    if (this.queued) return;
    this.queued = true;
    requestAnimationFrame(() => {
      this.queued = false;
      this.layout();
    });
  }

  width(text, px, weight) {
    const key = `${weight} ${px} ${text}`;
    let w = this.widths.get(key);
    if (w === undefined) {
      if (!this.family) this.family = getComputedStyle(this.view.svg).fontFamily || "sans-serif";
      this.context.font = `${weight} ${px}px ${this.family}`;
      w = this.context.measureText(text).width;
      this.widths.set(key, w);
    }
    return w;
  }

  layout() {
    const svg = this.view.svg;
    const width = svg.clientWidth;
    const height = svg.clientHeight;
    if (!width || !height) return;
    const upp = this.view.unitsPerPixel();
    const [bx, by] = this.view.box;
    const taken = new BoxIndex(64);
    const frame = svg.getBoundingClientRect();
    for (const overlay of this.overlays) {
      const r = overlay.getBoundingClientRect();
      if (r.width && r.height) taken.add([r.left - frame.left, r.top - frame.top, r.right - frame.left, r.bottom - frame.top]);
    }
    const screen = this.items.map((it) => [(it.at[0] - bx) / upp, (it.at[1] - by) / upp, Math.max(it.r / upp, 3)]);
    for (const [x, y, r] of screen) {
      if (x > -r && y > -r && x < width + r && y < height + r) taken.add([x - r, y - r, x + r, y + r]);
    }
    this.items.forEach((it, i) => {
      const [x, y, r] = screen[i];
      const text = it.node.textContent;
      const w = this.width(text, it.px, it.weight) + 2;
      const h = it.px * 1.2;
      let spot = null;
      if (text && x >= 0 && y >= 0 && x <= width && y <= height) {
        for (const far of [0, 1]) {
          for (const [dx, dy] of LABEL_SPOTS) {
            const gap = far ? 2.5 * h : 3;
            const cx = x + dx * (r + gap + w / 2);
            const cy = y + dy * (r + gap + h / 2);
            const box = [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2];
            if (box[0] < 1 || box[1] < 1 || box[2] > width - 1 || box[3] > height - 1 || taken.hits(box)) continue;
            spot = { cx, cy, box, far };
            break;
          }
          if (spot) break;
        }
      }
      const node = it.node;
      if (!spot) {
        setAttr(node, "visibility", "hidden");
        this.leader(it, null);
        return;
      }
      taken.add(spot.box);
      setAttr(node, "visibility", "visible");
      setAttr(node, "x", round((spot.cx - x) * upp));
      setAttr(node, "y", round((spot.cy - y) * upp));
      setAttr(node, "font-size", round(it.px * upp));
      this.leader(it, spot.far ? [(spot.cx - x) * upp, (spot.cy - y) * upp, r * upp] : null);
    });
  }

  /** The line from a marker to a label placed away from it (relative units). */
  leader(it, to) {
    if (!to) {
      if (it.line) it.line.setAttribute("visibility", "hidden");
      return;
    }
    if (!it.line) {
      it.line = s("line", { class: "leader" });
      it.node.before(it.line);
    }
    const [lx, ly, r] = to;
    const d = Math.hypot(lx, ly) || 1;
    setAttr(it.line, "visibility", "visible");
    setAttr(it.line, "x1", round((lx / d) * r));
    setAttr(it.line, "y1", round((ly / d) * r));
    setAttr(it.line, "x2", round(lx * 0.8));
    setAttr(it.line, "y2", round(ly * 0.8));
    setAttr(it.line, "stroke-width", round(this.view.unitsPerPixel()));
  }
}

function round(v) {
  return String(Math.round(v * 1000) / 1000);
}

/** Sets an attribute only when it changes (each set costs style work). */
function setAttr(node, name, value) {
  if (node.getAttribute(name) !== value) node.setAttribute(name, value);
}

/** Boxes [x0, y0, x1, y1] in a grid of buckets, for overlap tests. */
class BoxIndex {
  constructor(size) {
    this.size = size;
    this.buckets = new Map();
  }
  *keys([x0, y0, x1, y1]) {
    const k = this.size;
    for (let i = Math.floor(x0 / k); i <= Math.floor(x1 / k); i++) {
      for (let j = Math.floor(y0 / k); j <= Math.floor(y1 / k); j++) yield i * 100003 + j;
    }
  }
  add(box) {
    for (const key of this.keys(box)) {
      let list = this.buckets.get(key);
      if (!list) this.buckets.set(key, (list = []));
      list.push(box);
    }
  }
  hits(box) {
    for (const key of this.keys(box)) {
      for (const b of this.buckets.get(key) || []) {
        if (box[0] < b[2] && b[0] < box[2] && box[1] < b[3] && b[1] < box[3]) return true;
      }
    }
    return false;
  }
}
