/**
 * Sections: a plane cut through the model's mesh (a face model or the whole tablet), its
 * outline as polylines in the plane, and an SVG drawing of it at true scale with a scale bar
 * (GigaMesh's and 3DHOP's sections). Pure functions on triangle arrays in mm.
 *
 * The plane is drawn by the reader as a line on screen: it holds the two picked points and
 * the viewing direction, so it cuts the tablet straight down the line as seen. Where the
 * full-resolution heights are at hand (a face model's height.npy, a streamed face's rows, a
 * whole tablet's faces/<label>/height.npy) the plane cuts them ({@link gridSectionSegments});
 * the decimated mesh ({@link sectionSegments}) only when they are not.
 */
import { niceStep } from './profile.js';

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const unit = (a) => {
  const n = Math.hypot(a[0], a[1], a[2]);
  return n > 0 ? a.map((v) => v / n) : null;
};

/**
 * The plane through a and b (mm) that holds the viewing direction.
 * @returns {{origin: number[], normal: number[], u: number[], v: number[]}} u along a → b
 *   (as seen), v = the viewing direction made orthogonal to u (depth into the tablet), the
 *   plane's 2-D axes; normal = u × v
 */
export function planeThroughLine(a, b, viewDir) {
  const d = unit(viewDir);
  if (!d) throw new RangeError('viewDir must be a non-zero vector');
  const ab = sub(b, a);
  const u = unit(sub(ab, d.map((x) => x * dot(ab, d))));
  if (!u) throw new RangeError('the two points lie on one line of sight: draw a line across the view');
  const v = unit(sub(d, u.map((x) => x * dot(d, u))));
  return { origin: [...a], normal: unit(cross(u, v)), u, v };
}

/**
 * Segments where the plane cuts the triangles: [x0, y0, z0, x1, y1, z1, …] (mm).
 * @param {ArrayLike<number>} positions xyz per vertex
 * @param {ArrayLike<number> | null} index three vertex indices per triangle (null: unindexed)
 * @param {{origin: number[], normal: number[]}} plane
 * @param {{start: number, count: number}[]} [ranges] index ranges to cut (draw groups of the
 *   visible faces); default all
 * @returns {Float32Array}
 */
export function sectionSegments(positions, index, plane, ranges = null) {
  const nVert = positions.length / 3;
  const dist = new Float64Array(nVert);
  const o = plane.origin;
  const n = plane.normal;
  for (let i = 0; i < nVert; i++) {
    dist[i] = (positions[3 * i] - o[0]) * n[0] + (positions[3 * i + 1] - o[1]) * n[1] + (positions[3 * i + 2] - o[2]) * n[2];
  }
  const total = index ? index.length : nVert;
  const spans = ranges ?? [{ start: 0, count: total }];
  const out = [];
  const at = (i0, j0) => {
    // The point where edge i–j crosses the plane, computed from its lower vertex index, so
    // the two triangles sharing the edge give bit-identical points (chainSegments joins them).
    const [i, j] = i0 < j0 ? [i0, j0] : [j0, i0];
    const t = dist[i] / (dist[i] - dist[j]);
    for (let k = 0; k < 3; k++) out.push(positions[3 * i + k] + t * (positions[3 * j + k] - positions[3 * i + k]));
  };
  for (const { start, count } of spans) {
    const end = Math.min(start + count, total);
    for (let f = start; f + 2 < end; f += 3) {
      const ia = index ? index[f] : f;
      const ib = index ? index[f + 1] : f + 1;
      const ic = index ? index[f + 2] : f + 2;
      // A vertex exactly on the plane counts as on its positive side (no double segments).
      const sa = dist[ia] >= 0;
      const sb = dist[ib] >= 0;
      const sc = dist[ic] >= 0;
      if (sa === sb && sb === sc) continue;
      // The lone vertex, and the edges from it to the other two.
      const [lone, p, q] = sa === sb ? [ic, ia, ib] : sa === sc ? [ib, ic, ia] : [ia, ib, ic];
      at(lone, p);
      at(lone, q);
    }
  }
  return Float32Array.from(out);
}

/**
 * Segments where the plane cuts a height grid at full resolution (marching squares on the
 * signed distance to the plane, Lorensen & Cline 1987 in 2-D): the surface between four
 * neighbouring pixels, each at (c·s, r·s, −h)/1000 mm (SCAN_BUNDLE.md), crosses the plane
 * where the distance changes sign along the cell's edges, at the linear interpolation of the
 * two pixels. A cell with a pixel off the tablet (NaN) is not cut (no guessing across holes).
 * A cell crossed on all four edges (a saddle) is split by the sign at its centre (the mean of
 * its corners). Same output as {@link sectionSegments}; an edge's point is computed from its
 * lower pixel index, so the two cells sharing it give bit-identical points.
 * @param {{heightUm: ArrayLike<number>, rows: number, cols: number, pixelSizeUm: number}} grid
 * @param {{origin: number[], normal: number[]}} plane in the grid's (scan) frame, mm
 * @param {{row0?: number, toModel?: ArrayLike<number> | null}} [options] row0: the grid's
 *   first row in the full image (a block of rows read by heightRows.js); toModel: a 4×4
 *   column-major matrix taking the output to the model's frame (a whole tablet's face)
 * @returns {Float32Array}
 */
export function gridSectionSegments(grid, plane, { row0 = 0, toModel = null } = {}) {
  const { heightUm, rows, cols, pixelSizeUm } = grid;
  if (!(pixelSizeUm > 0)) throw new RangeError(`pixelSizeUm must be > 0, got ${pixelSizeUm}`);
  if (heightUm.length !== rows * cols) throw new RangeError(`heightUm has ${heightUm.length} values, expected ${rows * cols}`);
  const s = pixelSizeUm / 1000;
  const [ox, oy, oz] = plane.origin;
  const [nx, ny, nz] = plane.normal;
  const f = new Float64Array(rows * cols);
  for (let r = 0; r < rows; r++) {
    const y = (r + row0) * s - oy;
    for (let c = 0; c < cols; c++) {
      const i = r * cols + c;
      f[i] = nx * (c * s - ox) + ny * y + nz * (-heightUm[i] / 1000 - oz); // NaN off the tablet
    }
  }
  const out = [];
  const point = (i0, j0) => {
    const [i, j] = i0 < j0 ? [i0, j0] : [j0, i0];
    const t = f[i] / (f[i] - f[j]);
    const ri = Math.floor(i / cols);
    const rj = Math.floor(j / cols);
    const ci = i - ri * cols;
    const cj = j - rj * cols;
    const p = [
      (ci + t * (cj - ci)) * s,
      (ri + t * (rj - ri) + row0) * s,
      -(heightUm[i] + t * (heightUm[j] - heightUm[i])) / 1000,
    ];
    const q = toModel ? apply(toModel, p) : p;
    out.push(q[0], q[1], q[2]);
  };
  for (let r = 0; r + 1 < rows; r++) {
    for (let c = 0; c + 1 < cols; c++) {
      // Corners in turn round the cell: top-left, top-right, bottom-right, bottom-left.
      const k = [r * cols + c, r * cols + c + 1, (r + 1) * cols + c + 1, (r + 1) * cols + c];
      const v = k.map((i) => f[i]);
      if (!v.every(Number.isFinite)) continue;
      const pos = v.map((x) => x >= 0); // a pixel on the plane counts as on its positive side
      const crossed = [0, 1, 2, 3].filter((e) => pos[e] !== pos[(e + 1) % 4]);
      if (crossed.length === 2) {
        point(k[crossed[0]], k[(crossed[0] + 1) % 4]);
        point(k[crossed[1]], k[(crossed[1] + 1) % 4]);
      } else if (crossed.length === 4) {
        const centre = (v[0] + v[1] + v[2] + v[3]) / 4 >= 0;
        // Centre on the side of corners 0 and 2: they join through it, and corners 1 and 3 are
        // cut off, each by the two edges next to it (edges 0, 1 and 2, 3; edge e runs from
        // corner e to e + 1); else corners 0 and 2 are (edges 3, 0 and 1, 2).
        const pairs = centre === pos[0] ? [[0, 1], [2, 3]] : [[3, 0], [1, 2]];
        for (const [e1, e2] of pairs) {
          point(k[e1], k[(e1 + 1) % 4]);
          point(k[e2], k[(e2 + 1) % 4]);
        }
      }
    }
  }
  return Float32Array.from(out);
}

function apply(m, [x, y, z]) {
  return [
    m[0] * x + m[4] * y + m[8] * z + m[12],
    m[1] * x + m[5] * y + m[9] * z + m[13],
    m[2] * x + m[6] * y + m[10] * z + m[14],
  ];
}

/**
 * Join segments that share end points into polylines (ends within `tolMm` are one point).
 * @param {Float32Array} segments from {@link sectionSegments}
 * @returns {number[][][]} polylines of [x, y, z] points; a closed outline repeats its first point
 */
export function chainSegments(segments, tolMm = 1e-4) {
  const key = (p) => p.map((v) => Math.round(v / tolMm)).join(',');
  const segs = [];
  for (let i = 0; i < segments.length; i += 6) {
    const s = [Array.from(segments.subarray(i, i + 3)), Array.from(segments.subarray(i + 3, i + 6))];
    // A plane through a vertex cuts the triangles around it in points: no outline of their own.
    if (key(s[0]) !== key(s[1])) segs.push(s);
  }
  const ends = new Map(); // key → [segment index, end]
  segs.forEach((s, i) => {
    for (const e of [0, 1]) {
      const k = key(s[e]);
      if (!ends.has(k)) ends.set(k, []);
      ends.get(k).push([i, e]);
    }
  });
  const used = new Uint8Array(segs.length);
  const next = (point, from) => (ends.get(key(point)) ?? []).find(([i]) => !used[i] && i !== from);
  const lines = [];
  for (let s = 0; s < segs.length; s++) {
    if (used[s]) continue;
    used[s] = 1;
    const line = [segs[s][0], segs[s][1]];
    for (const dir of [1, -1]) {
      let tip = dir === 1 ? line[line.length - 1] : line[0];
      for (;;) {
        const hit = next(tip, -1);
        if (!hit) break;
        const [i, e] = hit;
        used[i] = 1;
        tip = segs[i][1 - e];
        if (dir === 1) line.push(tip);
        else line.unshift(tip);
      }
    }
    lines.push(line);
  }
  return lines;
}

/** Polylines in the plane's 2-D axes (mm): s along u, t along v (depth as seen). */
export function toPlane(lines, plane) {
  return lines.map((line) => line.map((p) => {
    const d = sub(p, plane.origin);
    return [dot(d, plane.u), dot(d, plane.v)];
  }));
}

const esc = (s) => String(s).replace(/[<>&"]/g, (c) => ({ '<': '&lt;', '>': '&gt;', '&': '&amp;', '"': '&quot;' })[c]);

/**
 * The section as a standalone SVG at true scale (1 user unit = 1 mm, width and height in mm,
 * so it prints at 1:1) with a scale bar of 1-2-5 × 10^k mm and a caption.
 * @param {number[][][]} lines2d from {@link toPlane}
 * @param {{title?: string, note?: string}} [about]
 * @returns {string}
 */
export function sectionSvg(lines2d, about = {}) {
  const pts = lines2d.flat();
  if (!pts.length) throw new RangeError('the plane does not cut the model');
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of pts) {
    x0 = Math.min(x0, x);
    y0 = Math.min(y0, y);
    x1 = Math.max(x1, x);
    y1 = Math.max(y1, y);
  }
  const span = Math.max(x1 - x0, y1 - y0, 1e-3);
  const pad = 0.08 * span;
  const bar = niceStep(Math.max((x1 - x0) / 4, 1e-3));
  const font = Math.max(span / 40, 0.2);
  const width = x1 - x0 + 2 * pad;
  const height = y1 - y0 + 2 * pad + 4 * font;
  const f = (v) => Number(v.toFixed(4));
  const paths = lines2d
    .filter((l) => l.length > 1)
    .map((l) => `<path d="M${l.map(([x, y]) => `${f(x - x0 + pad)},${f(y - y0 + pad)}`).join('L')}"/>`)
    .join('\n    ');
  const by = y1 - y0 + pad + 1.5 * font;
  const label = bar >= 1 ? `${bar} mm` : `${Math.round(bar * 1000)} µm`;
  return `<?xml version="1.0" encoding="UTF-8"?>
<svg xmlns="http://www.w3.org/2000/svg" width="${f(width)}mm" height="${f(height)}mm" viewBox="0 0 ${f(width)} ${f(height)}">
  <title>${esc(about.title ?? 'Section')}</title>
  <desc>${esc(about.note ?? 'Plane section of the model; 1 unit = 1 mm')}</desc>
  <g fill="none" stroke="#000" stroke-width="${f(span / 500)}" stroke-linejoin="round">
    ${paths}
  </g>
  <g class="scalebar">
    <rect x="${f(pad)}" y="${f(by)}" width="${f(bar)}" height="${f(font / 3)}" fill="#000"/>
    <text x="${f(pad + bar + font / 2)}" y="${f(by + font / 3)}" font-size="${f(font)}" font-family="sans-serif">${label}</text>
  </g>
</svg>
`;
}

/**
 * The eight corners of a box {min, max} (mm), corner i taking max along x when bit 0 of i is
 * set, along y for bit 1, along z for bit 2 (so the box's edges join corners one bit apart).
 * @param {{min: number[], max: number[]}} box
 * @returns {number[][]}
 */
export function boxCorners({ min, max }) {
  return Array.from({ length: 8 }, (_, i) => [0, 1, 2].map((k) => (i & (1 << k) ? max[k] : min[k])));
}

/**
 * The rows of an image grid where a plane can meet a solid: the y extent of the plane's cut
 * through a parallelepiped (the tablet's box taken into a face's scan frame, corners as
 * {@link boxCorners} orders them), in rows of pixel size s (row r at y = r·s, SCAN_BUNDLE.md),
 * widened by one row either side for the cells that straddle its ends and clamped to the
 * grid. What a streamed whole tablet's section reads of each face's heights (heightRows.js):
 * the rows the cut may pass, not the whole face.
 * @param {{origin: number[], normal: number[]}} plane in the face's frame, mm
 * @param {number[][]} corners 8 points, mm
 * @param {number} pixelSizeUm
 * @param {number} rows the grid's height H
 * @returns {[number, number] | null} [r0, r1) or null when the plane misses the solid
 */
export function planeRowSpan(plane, corners, pixelSizeUm, rows) {
  if (!(pixelSizeUm > 0)) throw new RangeError(`pixelSizeUm must be > 0, got ${pixelSizeUm}`);
  if (corners.length !== 8) throw new RangeError(`expected 8 corners, got ${corners.length}`);
  const d = corners.map((c) => dot(sub(c, plane.origin), plane.normal));
  let lo = Infinity;
  let hi = -Infinity;
  for (let i = 0; i < 8; i++) {
    if (d[i] === 0) {
      lo = Math.min(lo, corners[i][1]);
      hi = Math.max(hi, corners[i][1]);
    }
    for (const bit of [1, 2, 4]) {
      const j = i | bit;
      if (j === i || d[i] * d[j] >= 0) continue; // the edge i–j does not cross the plane
      const t = d[i] / (d[i] - d[j]);
      const y = corners[i][1] + t * (corners[j][1] - corners[i][1]);
      lo = Math.min(lo, y);
      hi = Math.max(hi, y);
    }
  }
  if (!(hi >= lo)) return null;
  const s = pixelSizeUm / 1000;
  const r0 = Math.max(0, Math.floor(lo / s) - 1);
  const r1 = Math.min(rows, Math.ceil(hi / s) + 2);
  return r1 > r0 ? [r0, r1] : null;
}
