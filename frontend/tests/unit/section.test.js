import { describe, expect, it } from 'vitest';
import { chainSegments, gridSectionSegments, planeThroughLine, sectionSegments, sectionSvg, toPlane } from '../../src/viewer/section.js';

/** An axis-aligned box (12 triangles, indexed) of the given size centred at the origin. */
function box([sx, sy, sz]) {
  const p = [];
  for (const x of [-sx / 2, sx / 2]) for (const y of [-sy / 2, sy / 2]) for (const z of [-sz / 2, sz / 2]) p.push(x, y, z);
  const v = (x, y, z) => x * 4 + y * 2 + z;
  const quads = [
    [v(0, 0, 0), v(0, 1, 0), v(0, 1, 1), v(0, 0, 1)],
    [v(1, 0, 0), v(1, 0, 1), v(1, 1, 1), v(1, 1, 0)],
    [v(0, 0, 0), v(0, 0, 1), v(1, 0, 1), v(1, 0, 0)],
    [v(0, 1, 0), v(1, 1, 0), v(1, 1, 1), v(0, 1, 1)],
    [v(0, 0, 0), v(1, 0, 0), v(1, 1, 0), v(0, 1, 0)],
    [v(0, 0, 1), v(0, 1, 1), v(1, 1, 1), v(1, 0, 1)],
  ];
  const index = quads.flatMap(([a, b, c, d]) => [a, b, c, a, c, d]);
  return { positions: Float32Array.from(p), index: Uint32Array.from(index) };
}

describe('sections', () => {
  it('the plane holds the drawn line and the viewing direction', () => {
    const pl = planeThroughLine([0, 0, 0], [10, 0, 3], [0, 0, 1]);
    expect(pl.u).toEqual([1, 0, 0]); // the line as seen (its depth component dropped)
    expect(pl.v).toEqual([0, 0, 1]);
    expect(Math.abs(pl.normal[1])).toBeCloseTo(1, 12);
    expect(() => planeThroughLine([0, 0, 0], [0, 0, 5], [0, 0, 1])).toThrow(/line of sight/);
  });

  it('cuts a 30 × 20 × 6 mm box across its middle into one closed 30 × 6 mm rectangle', () => {
    const { positions, index } = box([30, 20, 6]);
    const plane = planeThroughLine([-20, 0.3, 0], [20, 0.3, 0], [0, 0, 1]);
    const segs = sectionSegments(positions, index, plane);
    const lines = chainSegments(segs);
    expect(lines).toHaveLength(1);
    const flat = toPlane(lines, plane)[0];
    const xs = flat.map((p) => p[0]);
    const ys = flat.map((p) => p[1]);
    expect(Math.max(...xs) - Math.min(...xs)).toBeCloseTo(30, 4);
    expect(Math.max(...ys) - Math.min(...ys)).toBeCloseTo(6, 4);
    // Closed: the outline ends where it starts.
    expect(flat[0][0]).toBeCloseTo(flat[flat.length - 1][0], 4);
    expect(flat[0][1]).toBeCloseTo(flat[flat.length - 1][1], 4);
    // The perimeter of the rectangle, 2·(30 + 6) mm.
    let perimeter = 0;
    for (let i = 1; i < flat.length; i++) perimeter += Math.hypot(flat[i][0] - flat[i - 1][0], flat[i][1] - flat[i - 1][1]);
    expect(perimeter).toBeCloseTo(72, 3);
  });

  it('joins the segments of an unindexed mesh (vertices repeated per triangle) too', () => {
    const { positions, index } = box([30, 20, 6]);
    const flat = Float32Array.from(Array.from(index).flatMap((i) => [...positions.subarray(3 * i, 3 * i + 3)]));
    const plane = planeThroughLine([-20, 0.3, 0.1], [20, -0.2, 0.1], [0.1, 0, 1]);
    expect(chainSegments(sectionSegments(flat, null, plane))).toHaveLength(1);
  });

  it('cuts only the given index ranges (the shown faces of a whole tablet)', () => {
    const { positions, index } = box([30, 20, 6]);
    const plane = planeThroughLine([-20, 0.3, 0], [20, 0.3, 0], [0, 0, 1]);
    // Triangles 0–3: the two x faces (quads 0 and 1); the line crosses both triangles of
    // each quad: 4 segments of the whole cut's 8 (the z faces' 4 are left out).
    expect(sectionSegments(positions, index, plane).length).toBe(8 * 6);
    expect(sectionSegments(positions, index, plane, [{ start: 0, count: 12 }]).length).toBe(4 * 6);
  });

  it('a plane through a vertex gives no outline of its own for the point it cuts there', () => {
    // Recorded in the browser: a plane 2e-7 mm off a row of vertices of the synthetic face;
    // the triangle touching the plane at the vertex (1.6, 16) gave a segment of 1.6e-6 mm.
    const segs = Float32Array.from([
      1.5999983549118042, 16.000001907348633, -0.2582945227622986, 0, 16.000001907348633, 0,
      3.199998378753662, 16.000001907348633, -0.4987374544143677, 1.600000023841858, 16.000001907348633, -0.2582947909832001,
      1.5999983549118042, 16.000001907348633, -0.2582945227622986, 1.600000023841858, 16.000001907348633, -0.2582947909832001,
    ]);
    const lines = chainSegments(segs);
    expect(lines).toHaveLength(1);
    expect(lines[0]).toHaveLength(3);
  });

  it('a plane that misses the model cuts nothing, and the SVG says so', () => {
    const { positions, index } = box([30, 20, 6]);
    const plane = planeThroughLine([-20, 15, 0], [20, 15, 0], [0, 0, 1]);
    expect(sectionSegments(positions, index, plane).length).toBe(0);
    expect(() => sectionSvg([])).toThrow(/does not cut/);
  });

  it('exports an SVG at true scale (mm) with a scale bar and an escaped title', () => {
    const svg = sectionSvg([[[0, 0], [30, 0], [30, 6], [0, 6], [0, 0]]], { title: 'P1 <obverse> & co' });
    const width = Number(svg.match(/width="([\d.]+)mm"/)[1]);
    expect(width).toBeCloseTo(30 + 2 * 0.08 * 30, 6);
    expect(svg).toContain('>5 mm<'); // niceStep(30 / 4) = 5
    expect(svg).toContain('P1 &lt;obverse&gt; &amp; co');
    const rect = svg.match(/<rect x="[\d.]+" y="[\d.]+" width="([\d.]+)"/);
    expect(Number(rect[1])).toBe(5);
  });
});

describe('sections of the full-resolution heights', () => {
  /** A rows × cols grid of heights h(r, c) µm, 1 mm pixels unless given. */
  const grid = (rows, cols, h, pixelSizeUm = 1000) => {
    const heightUm = new Float32Array(rows * cols);
    for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) heightUm[r * cols + c] = h(r, c);
    return { heightUm, rows, cols, pixelSizeUm };
  };
  const length = (line) => line.slice(1).reduce((acc, p, i) => acc + Math.hypot(...p.map((v, k) => v - line[i][k])), 0);

  it('a vertical plane cuts a flat face along the whole grid, at the plane', () => {
    const g = grid(5, 11, () => 0);
    const lines = chainSegments(gridSectionSegments(g, { origin: [3.5, 0, 0], normal: [1, 0, 0] }));
    expect(lines).toHaveLength(1);
    expect(length(lines[0])).toBeCloseTo(4, 5); // rows 0…4 at 1 mm
    for (const p of lines[0]) expect(p[0]).toBeCloseTo(3.5, 5);
  });

  it('a level plane cuts a slope where the height equals its depth', () => {
    // h = 100·c µm (0.1 mm per column of 50 µm), plane z = −0.5 mm: at h = 500 µm, c = 5.
    const g = grid(8, 20, (r, c) => 100 * c, 50);
    const segs = gridSectionSegments(g, { origin: [0, 0, -0.5], normal: [0, 0, 1] });
    const lines = chainSegments(segs);
    expect(lines).toHaveLength(1);
    for (const p of lines[0]) {
      expect(p[0]).toBeCloseTo(5 * 0.05, 6);
      expect(p[2]).toBeCloseTo(-0.5, 6);
    }
    expect(length(lines[0])).toBeCloseTo(7 * 0.05, 6);
  });

  it('does not cut across holes, honours row0 and takes its points to the model frame', () => {
    const g = grid(6, 9, (r, c) => (c === 4 ? Number.NaN : 0));
    const plane = { origin: [0, 2.5 + 10, 0], normal: [0, 1, 0] }; // y = 12.5 mm: row 12.5
    const toModel = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 100, 0, 0, 1]; // +100 mm in x
    const lines = chainSegments(gridSectionSegments(g, plane, { row0: 10, toModel }));
    expect(lines).toHaveLength(2); // columns 0–3 and 5–8, the hole between them
    const xs = lines.flat().map((p) => p[0]).sort((a, b) => a - b);
    expect(xs[0]).toBeCloseTo(100, 6);
    expect(xs[xs.length - 1]).toBeCloseTo(108, 6);
    for (const p of lines.flat()) expect(p[1]).toBeCloseTo(12.5, 6);
  });

  it('splits a saddle cell by its centre, cutting off the corners on the other side', () => {
    // Level plane z = 0: the signed distance is −h/1000 mm. Row-major h = −1, 1, 2, −1 mm,
    // so round the cell (top-left, top-right, bottom-right, bottom-left) +1, −1, +1, −2:
    // a saddle whose centre (−0.25) is negative, so the two positive corners are cut off.
    const g = { heightUm: Float32Array.from([-1000, 1000, 2000, -1000]), rows: 2, cols: 2, pixelSizeUm: 1000 };
    const segs = Array.from(gridSectionSegments(g, { origin: [0, 0, 0], normal: [0, 0, 1] }));
    expect(segs.length).toBe(12); // two segments
    const ends = [segs.slice(0, 6), segs.slice(6)].map((q) => [q.slice(0, 3), q.slice(3)]);
    // The top-left corner (0, 0) is cut off by the top edge (y = 0) and the left edge (x = 0).
    const cutsTopLeft = ends.some(([a, b]) => [a, b].some((p) => p[1] === 0) && [a, b].some((p) => p[0] === 0));
    expect(cutsTopLeft).toBe(true);
    for (const [a, b] of ends) for (const p of [a, b]) expect(p[2]).toBeCloseTo(0, 6);
  });

  it('agrees with the cut of the same surface triangulated at full resolution', () => {
    const rows = 40;
    const cols = 60;
    const s = 100; // µm
    const g = grid(rows, cols, (r, c) => 800 * Math.exp(-((c - 30) ** 2 + (r - 20) ** 2) / 200) + 5 * c, s);
    const positions = new Float32Array(rows * cols * 3);
    for (let r = 0; r < rows; r++) {
      for (let c = 0; c < cols; c++) positions.set([(c * s) / 1000, (r * s) / 1000, -g.heightUm[r * cols + c] / 1000], 3 * (r * cols + c));
    }
    const index = [];
    for (let r = 0; r + 1 < rows; r++) {
      for (let c = 0; c + 1 < cols; c++) {
        const a = r * cols + c;
        index.push(a, a + cols, a + 1, a + 1, a + cols, a + cols + 1);
      }
    }
    const plane = planeThroughLine([0.3, 0.4, -0.2], [5.5, 3.1, -0.2], [0.2, -0.1, 1]);
    const fromGrid = chainSegments(gridSectionSegments(g, plane));
    const fromMesh = chainSegments(sectionSegments(positions, Uint32Array.from(index), plane));
    expect(fromGrid).toHaveLength(1);
    const lg = length(fromGrid[0]);
    expect(lg).toBeGreaterThan(4);
    expect(Math.abs(lg - length(fromMesh[0])) / lg).toBeLessThan(0.01);
  });
});

describe('the rows a plane can cut', () => {
  it('spans the rows where the plane crosses the box, widened by a row, clamped', async () => {
    const { boxCorners, planeRowSpan } = await import('../../src/viewer/section.js');
    const corners = boxCorners({ min: [0, 0, -5], max: [10, 8, 0] });
    expect(corners[0]).toEqual([0, 0, -5]);
    expect(corners[7]).toEqual([10, 8, 0]);
    // A plane y = 3 mm (normal along y): rows about 3 mm / 0.1 mm = 30.
    expect(planeRowSpan({ origin: [0, 3, 0], normal: [0, 1, 0] }, corners, 100, 80)).toEqual([29, 32]);
    // Tilted in y–z: from y = 2 at z = 0 to y = 3 at z = −5.
    const n = [0, 5, 1].map((v) => v / Math.hypot(5, 1));
    expect(planeRowSpan({ origin: [0, 2, 0], normal: n }, corners, 100, 80)).toEqual([19, 32]);
    // A plane holding the y axis crosses every row; one outside the box none.
    expect(planeRowSpan({ origin: [4, 0, 0], normal: [1, 0, 0] }, corners, 100, 80)).toEqual([0, 80]);
    expect(planeRowSpan({ origin: [0, 20, 0], normal: [0, 1, 0] }, corners, 100, 80)).toBeNull();
  });
});
