import { describe, expect, it } from 'vitest';
import {
  distanceUncertaintyAxesMm,
  distanceUncertaintyMm,
  fmtUm,
  formatDistance,
  mergeTrustMeta,
  profileUncertainty,
  sigmaAlongLine,
  sigmaAt,
  TRUST_LAYERS,
  trustLegend,
} from '../../src/viewer/trust.js';
import { bandPath } from '../../src/viewer/chart.js';
import { profileToCsv } from '../../src/viewer/profile.js';

/** σ_h = 2 + 0.1·c µm on a 50 × 40 grid of 50 µm pixels (NaN in column 0). */
function grid() {
  const cols = 50;
  const rows = 40;
  const sigmaUm = new Float32Array(cols * rows);
  for (let r = 0; r < rows; r++) for (let c = 0; c < cols; c++) sigmaUm[r * cols + c] = c === 0 ? NaN : 2 + 0.1 * c;
  return { sigmaUm, cols, rows, pixelSizeUm: 50 };
}

describe('trust: the ± of measurements', () => {
  it('reads σ_h bilinearly at a point in mm, NaN next to a hole', () => {
    const g = grid();
    expect(sigmaAt(g, [0.5, 1.0])).toBeCloseTo(2 + 0.1 * 10, 5); // 0.5 mm = column 10
    expect(sigmaAt(g, [0.525, 1.0])).toBeCloseTo(2 + 0.1 * 10.5, 5);
    expect(sigmaAt(g, [0.02, 1.0])).toBeNaN();
    expect(sigmaAt(g, [10, 1.0])).toBeNaN(); // off the grid
  });

  it('a flat distance carries the grid resolution, a vertical one the heights', () => {
    // Flat: only the half-pixel positions of both ends count: s = 50 µm.
    expect(distanceUncertaintyMm([0, 0, 0], [10, 0, 0], 5, 7, 50)).toBeCloseTo(0.05, 10);
    // Straight down (|Δz| = d): σ_a + σ_b.
    expect(distanceUncertaintyMm([0, 0, 0], [0, 0, 1], 5, 7, 50)).toBeCloseTo(0.012, 10);
    // 45°: both, weighted by cos 45°.
    const pm = distanceUncertaintyMm([0, 0, 0], [1, 0, 1], 5, 7, 50);
    expect(pm).toBeCloseTo((Math.SQRT1_2 * 12 + Math.SQRT1_2 * 50) / 1000, 10);
    expect(distanceUncertaintyMm([0, 0, 0], [1, 0, 1], NaN, 7, 50)).toBeNaN();
  });

  it('samples σ along a profile line and summarises it over the samples with a height', () => {
    const g = grid();
    const s = sigmaAlongLine(g, [0.5, 1], [1.5, 1], 21);
    expect(s.length).toBe(21);
    expect(s[0]).toBeCloseTo(3, 5);
    expect(s[20]).toBeCloseTo(5, 5); // 1.5 mm = column 30
    const h = Float64Array.from(s, (_, i) => (i === 20 ? NaN : 100));
    const u = profileUncertainty(h, s);
    expect(u.maxUm).toBeCloseTo(s[19], 6); // the last sample has no height
    expect(u.medianUm).toBeCloseTo(3.95, 5); // columns 10 … 29
    expect(profileUncertainty([NaN], [1])).toBeNull();
  });

  it('formats a distance with its ± in µm below 0.1 mm', () => {
    expect(formatDistance(32.012, 0.0123)).toBe('32.01 mm ± 12 µm');
    expect(formatDistance(32.012, 0.25)).toBe('32.01 ± 0.25 mm');
    expect(formatDistance(32.012, NaN)).toBe('32.01 mm');
    expect(fmtUm(123.4)).toBe('123 µm');
  });

  it('draws the band h ± σ as one polygon per run of finite samples', () => {
    const p = { distanceMm: [0, 1, 2, 3, 4], heightUm: [10, 11, NaN, 12, 13], sigmaUm: [1, 1, 1, 2, 2] };
    const d = bandPath(p, (x) => x * 10, (y) => -y);
    const polys = d.split('Z').filter(Boolean);
    expect(polys).toHaveLength(2);
    expect(polys[0]).toBe('M0.0,-11.0L10.0,-12.0L10.0,-10.0L0.0,-9.0');
    expect(polys[1]).toBe('M30.0,-14.0L40.0,-15.0L40.0,-11.0L30.0,-10.0');
  });

  it('writes σ as a third CSV column when the profile has it', () => {
    const csv = profileToCsv({ distanceMm: [0, 1], heightUm: [5, NaN], sigmaUm: [2, 3] });
    expect(csv.trim().split('\n').filter((l) => !l.startsWith('#'))).toEqual(['distance_mm,height_um,sigma_um', '0.0000,5.00,2.00', '1.0000,,3.00']);
  });

  it('has a legend for every layer: classes with their share, ramps in µm', () => {
    const meta = { uncertainty_scale_um: 20, disagreement_scale_um: 50, class_fraction: { 1: 0.7, 3: 0.3 } };
    const sources = trustLegend('sources', meta);
    expect(sources.kind).toBe('classes');
    expect(sources.entries.map((e) => e.fraction)).toEqual([0.7, null, 0.3, null, null]);
    expect(trustLegend('uncertainty', meta)).toMatchObject({ kind: 'ramp', lo: '0 µm', hi: '≥ 20 µm' });
    expect(trustLegend('disagreement', meta).hi).toBe('≥ 50 µm');
    expect(TRUST_LAYERS).toEqual(['sources', 'uncertainty', 'disagreement']);
    expect(() => trustLegend('bogus')).toThrow(RangeError);
  });
});

describe('trust of a whole tablet', () => {
  it('weighs each face\'s class shares by its tablet pixels and keeps the largest tops', () => {
    const m = mergeTrustMeta([
      { pixels: 300, class_fraction: { 1: 1, 2: 0, 3: 0, 4: 0, 5: 0 }, uncertainty_scale_um: 5, disagreement_scale_um: 20 },
      { pixels: 100, class_fraction: { 1: 0, 2: 0, 3: 1, 4: 0, 5: 0 }, uncertainty_scale_um: 10, disagreement_scale_um: 20 },
    ]);
    expect(m.class_fraction['1']).toBeCloseTo(0.75, 12);
    expect(m.class_fraction['3']).toBeCloseTo(0.25, 12);
    expect(m.uncertainty_scale_um).toBe(10);
    expect(m.disagreement_scale_um).toBe(20);
    expect(m.faces).toBe(2);
    // The legend reads it as a face model's trust.json.
    const legend = trustLegend('sources', m);
    expect(legend.entries[2].fraction).toBeCloseTo(0.25, 12);
    expect(trustLegend('uncertainty', m).hi).toBe('≥ 10 µm');
    expect(mergeTrustMeta([])).toEqual({});
  });
});

describe('the ± of a distance across faces', () => {
  it('is the face model\'s ± when both ends are seen along z, and follows each face\'s axis', () => {
    const a = [1, 2, -0.5];
    const b = [4, 6, -1.7];
    const z = [0, 0, 1];
    const same = distanceUncertaintyAxesMm(a, b, [
      { sigmaUm: 3, axis: z, pixelSizeUm: 50 },
      { sigmaUm: 7, axis: z, pixelSizeUm: 50 },
    ]);
    expect(same).toBeCloseTo(distanceUncertaintyMm(a, b, 3, 7, 50), 12);
    // A 10 mm line along x, its end b on a face seen along x (an edge): b's height error
    // lies along the line (all of σ_b counts), a's across it (none of σ_a does).
    const pm = distanceUncertaintyAxesMm([0, 0, 0], [10, 0, 0], [
      { sigmaUm: 100, axis: z, pixelSizeUm: 40 },
      { sigmaUm: 5, axis: [-1, 0, 0], pixelSizeUm: 40 },
    ]);
    expect(pm).toBeCloseTo((20 + 5) / 1000, 12);
    expect(Number.isNaN(distanceUncertaintyAxesMm(a, b, [{ sigmaUm: NaN, axis: z, pixelSizeUm: 50 }, { sigmaUm: 1, axis: z, pixelSizeUm: 50 }]))).toBe(true);
  });
});
