import { describe, expect, it } from 'vitest';
import { chainSegments, planeThroughLine, sectionSegments, sectionSvg, toPlane } from '../../src/viewer/section.js';

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
