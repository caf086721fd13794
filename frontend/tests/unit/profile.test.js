import { describe, expect, it } from 'vitest';
import { encodeNpyFloat32, parseNpy } from '../../src/viewer/npy.js';
import {
  bilinearHeight,
  niceStep,
  niceTicks,
  profileToCsv,
  sampleProfile,
} from '../../src/viewer/profile.js';

/** A plane h = a + b·x_mm + c·y_mm on a cols × rows grid of pixel size s µm. */
function planeGrid({ cols, rows, pixelSizeUm, a, b, c }) {
  const heightUm = new Float32Array(cols * rows);
  for (let r = 0; r < rows; r++) {
    for (let col = 0; col < cols; col++) {
      heightUm[r * cols + col] = a + (b * col * pixelSizeUm) / 1000 + (c * r * pixelSizeUm) / 1000;
    }
  }
  return { heightUm, cols, rows, pixelSizeUm };
}

describe('profile sampling', () => {
  it('reproduces a plane exactly: bilinear interpolation is exact on linear fields', () => {
    const g = planeGrid({ cols: 120, rows: 80, pixelSizeUm: 50, a: 100, b: 30, c: -20 });
    const p = sampleProfile(g, [0.5, 0.5], [5.5, 3.0], { samples: 101 });
    expect(p.lengthMm).toBeCloseTo(Math.hypot(5, 2.5), 12);
    for (let i = 0; i < 101; i++) {
      const t = i / 100;
      const x = 0.5 + 5 * t;
      const y = 0.5 + 2.5 * t;
      // float32 storage of values ≤ ~300 µm: relative error 6e-8, i.e. < 1e-4 µm
      expect(p.heightUm[i]).toBeCloseTo(100 + 30 * x - 20 * y, 3);
      expect(p.distanceMm[i]).toBeCloseTo(t * p.lengthMm, 12);
    }
  });

  it('samples one point per pixel by default and maps mm to pixels with the pixel size', () => {
    const g = planeGrid({ cols: 200, rows: 10, pixelSizeUm: 25, a: 0, b: 1000, c: 0 });
    // from x = 1 mm to x = 3 mm: 2 mm / 25 µm = 80 pixels → 81 samples; h = 1000 µm/mm · x
    const p = sampleProfile(g, [1, 0.1], [3, 0.1]);
    expect(p.heightUm.length).toBe(81);
    expect(p.heightUm[0]).toBeCloseTo(1000, 2);
    expect(p.heightUm[80]).toBeCloseTo(3000, 2);
  });

  it('returns NaN off the grid and next to holes, never a guess', () => {
    const g = planeGrid({ cols: 10, rows: 10, pixelSizeUm: 100, a: 5, b: 0, c: 0 });
    g.heightUm[5 * 10 + 5] = Number.NaN;
    expect(bilinearHeight(g.heightUm, 10, 10, 5.5, 5.5)).toBeNaN();
    expect(bilinearHeight(g.heightUm, 10, 10, 2.5, 2.5)).toBeCloseTo(5, 6);
    expect(bilinearHeight(g.heightUm, 10, 10, -0.1, 2)).toBeNaN();
    expect(bilinearHeight(g.heightUm, 10, 10, 9, 9)).toBeCloseTo(5, 6); // last pixel is inside
    const p = sampleProfile(g, [0, 0.2], [2, 0.2], { samples: 11 }); // x up to 20 px: beyond 9
    expect(Number.isNaN(p.heightUm[10])).toBe(true);
    expect(p.heightUm[0]).toBeCloseTo(5, 6);
  });

  it('rejects bad arguments by name', () => {
    const g = planeGrid({ cols: 4, rows: 4, pixelSizeUm: 10, a: 0, b: 0, c: 0 });
    expect(() => sampleProfile({ ...g, pixelSizeUm: 0 }, [0, 0], [1, 1])).toThrow(/pixelSizeUm/);
    expect(() => sampleProfile({ ...g, cols: 5 }, [0, 0], [1, 1])).toThrow(/heightUm/);
    expect(() => sampleProfile(g, [0, 0], [1, 1], { samples: 1 })).toThrow(/samples/);
  });

  it('writes CSV with its units and empty fields for NaN', () => {
    const csv = profileToCsv({ distanceMm: [0, 0.5], heightUm: [12.345, Number.NaN] });
    expect(csv).toBe(
      '# units: distance_mm: millimetres along the line; height_um: micrometres toward the camera\n' +
        'distance_mm,height_um\n0.0000,12.35\n0.5000,\n',
    );
  });
});

describe('height.npy', () => {
  it('round-trips a float32 grid with NaN through the .npy format', () => {
    const data = new Float32Array([1.5, Number.NaN, -3, 4e3, 0, 7]);
    const parsed = parseNpy(encodeNpyFloat32(data, [2, 3]));
    expect(parsed.shape).toEqual([2, 3]);
    expect(parsed.dtype).toBe('<f4');
    expect(Array.from(parsed.data)).toEqual(Array.from(data));
  });
  it('refuses other files with a clear message', () => {
    expect(() => parseNpy(new TextEncoder().encode('not numpy at all').buffer)).toThrow(/magic/);
  });
});

describe('nice ticks', () => {
  it('uses 1-2-5 steps', () => {
    expect(niceStep(0.7)).toBeCloseTo(0.5, 12);
    expect(niceStep(3.1)).toBe(2);
    expect(niceStep(99)).toBe(50);
    expect(niceTicks(0, 10, 5)).toEqual([0, 2, 4, 6, 8, 10]);
    expect(niceTicks(-120, 130, 5)).toEqual([-100, -50, 0, 50, 100]);
  });
});
