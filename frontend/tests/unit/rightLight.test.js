import { describe, expect, it } from 'vitest';
import { lightDirection } from '../../src/viewer/light.js';
import {
  bestLight,
  decodeNormals,
  localLight,
  rakingSet,
  regionBasis,
  shadeCrop,
  shadingVariance,
} from '../../src/viewer/rightLight.js';

/** Normals of V-grooves running along y (walls tilted ±t about y): n = (±sin t, 0, −cos t). */
function groovesAlongY(t = 0.4, count = 200) {
  const out = new Float32Array(count * 3);
  for (let i = 0; i < count; i++) out.set([(i % 2 ? 1 : -1) * Math.sin(t), 0, -Math.cos(t)], 3 * i);
  return out;
}

function rotateZ(normals, deg) {
  const a = (deg * Math.PI) / 180;
  const out = new Float32Array(normals.length);
  for (let i = 0; i < normals.length; i += 3) {
    const [x, y, z] = normals.subarray(i, i + 3);
    out.set([Math.cos(a) * x - Math.sin(a) * y, Math.sin(a) * x + Math.cos(a) * y, z], i);
  }
  return out;
}

describe('the right light', () => {
  it('on a face seen from its camera, local and model angles coincide', () => {
    const basis = regionBasis(Float32Array.of(0, 0, -1));
    for (const [a, e] of [[0, 10], [90, 30], [225, 45]]) {
      const l = localLight(basis, a, e);
      const want = lightDirection(a, 90 - e);
      for (let k = 0; k < 3; k++) expect(l[k]).toBeCloseTo(want[k], 12);
    }
  });

  it('lights grooves across them, as low as their walls are steep', () => {
    for (const turn of [0, 30, 75]) {
      const n = rotateZ(groovesAlongY(), turn);
      const best = bestLight(n);
      // Grooves along y (turned by `turn`) are lit from ±x turned the same way: φ = 90° or
      // 270° (x = sinφ) minus the turn (rotating x toward y lowers φ).
      const across = [(90 - turn + 360) % 360, (270 - turn + 360) % 360];
      const off = Math.min(...across.map((a) => Math.abs(((best.azimuthDeg - a + 540) % 360) - 180)));
      expect(off).toBeLessThanOrEqual(5);
      // Walls at ±t: the lit wall gets sin(t + e), the other max(0, sin(e − t)); their
      // difference peaks at e ≈ t (22.9°): the far wall just dark, the near one brightest.
      expect([20, 25]).toContain(best.elevationDeg);
      // Along the grooves the two walls are lit alike: far less contrast.
      const along = localLight(best.basis, best.localAzimuthDeg + 90, best.elevationDeg);
      expect(shadingVariance(n, along)).toBeLessThan(best.contrast / 10);
    }
  });

  it('gives shallow wedges the lowest light searched (10°)', () => {
    expect(bestLight(groovesAlongY(0.1)).elevationDeg).toBe(10);
  });

  it('refuses a region without normals', () => {
    expect(() => bestLight(new Float32Array(0))).toThrow(RangeError);
  });

  it('decodes normals.png inside the circle only, skipping empty pixels', () => {
    const w = 4;
    const h = 4;
    const rgba = new Uint8ClampedArray(w * h * 4);
    for (let i = 0; i < w * h; i++) rgba.set([128, 128, 0, 255], 4 * i); // n = (0, 0, −1)
    rgba.set([0, 0, 0, 0], 0); // off the tablet
    expect(decodeNormals(rgba, w, h).length / 3).toBe(15);
    const inCircle = decodeNormals(rgba, w, h, { cx: 2, cy: 2, r: 1 });
    expect(inCircle.length / 3).toBe(4);
    expect(inCircle[2]).toBeCloseTo(-1, 2);
  });

  it('offers eight raking lights 45° apart, starting at the proposal', () => {
    const basis = regionBasis(Float32Array.of(0, 0, -1));
    const set = rakingSet(basis, 20, 30);
    expect(set.map((s) => Math.round(s.azimuthDeg))).toEqual([30, 75, 120, 165, 210, 255, 300, 345]);
    for (const s of set) expect(s.polarDeg).toBeCloseTo(70, 9);
  });

  it('shades a crop: the wall facing the light bright, the other at ambient', () => {
    const nrm = new Uint8ClampedArray([255, 128, 128, 255, 0, 128, 128, 255, 0, 0, 0, 0]); // +x, −x, none
    const out = shadeCrop(nrm, null, [1, 0, 0], { ambient: 0.1 });
    expect(out[0]).toBeGreaterThan(150);
    expect(out[4]).toBe(Math.round(190 * 0.1));
    expect(out[11]).toBe(0);
  });
});
