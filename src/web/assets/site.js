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
 * matrix [a, b, c, d, e, f] (src/site/floorplan.rs does the same). */
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
  constructor(svg, { panWithLeft = () => true } = {}) {
    this.svg = svg;
    this.box = [0, 0, 10, 10];
    this.panWithLeft = panWithLeft;
    this.layers = {};
    for (const name of ["floorplan", "tiles", "overlay", "grid", "shapes", "heat", "route", "trails", "anchors", "places", "devices", "draft"]) {
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
  }

  setBox([x, y, w, hh]) {
    // Keep the aspect of the element so a unit stays square.
    const aspect = this.svg.clientHeight / Math.max(1, this.svg.clientWidth) || 1;
    hh = w * aspect;
    this.box = [x, y, w, hh];
    this.svg.setAttribute("viewBox", `${x} ${y} ${w} ${hh}`);
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

/** Draws a site view (`/api/site`, `/api/editor/check`): tiles, grid lines,
 * beacons, gateways and places. `withPlan` tints the tiles so the plan
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
      anchors.push(
        s(
          "g",
          { class: "anchor " + kind, transform: `translate(${a.grid[0]} ${a.grid[1]})` },
          s("circle", { r: 0.32 }),
          s("text", { class: "anchor-id", y: -0.45 }, a.id),
          s("title", {}, `${kind} ${a.id} at ${a.m[0].toFixed(2)}, ${a.m[1].toFixed(2)} m`),
        ),
      );
    }
  }
  fill(view.layers.anchors, anchors);
  fill(
    view.layers.places,
    site.places.map((p) =>
      s(
        "g",
        { class: "place", "data-place": p.name, transform: `translate(${p.cell[0] + 0.5} ${p.cell[1] + 0.5})` },
        s("rect", { x: -0.42, y: -0.42, width: 0.84, height: 0.84, rx: 0.15 }),
        s("text", { class: "place-name", y: 1.05 }, p.name),
        s("title", {}, p.label ? `${p.name} (${p.label})` : p.name),
      ),
    ),
  );
}
