import { describe, expect, it } from 'vitest';
import { applyEnhance, checkEnhance, defaultEnhance, describeEnhance, LENS_MODES, lensToDevice } from '../../src/viewer/enhance.js';
import { SHADING_MODES } from '../../src/viewer/permalink.js';

const uniforms = () => {
  const vec = { x: 0, y: 0, set(x, y) { this.x = x; this.y = y; } };
  return Object.fromEntries(
    ['uNormalUnsharp', 'uLumaUnsharp', 'uUnsharpRadius', 'uLensMode', 'uLensRadius'].map((k) => [k, { value: 0 }]).concat([['uLensCentre', { value: vec }]]),
  );
};

describe('enhancements and the lens', () => {
  it('clamps strengths and radius, and names a bad field', () => {
    const e = checkEnhance({ normalUnsharp: 20, lumaUnsharp: -1, radiusPx: 0 });
    expect(e).toMatchObject({ normalUnsharp: 8, lumaUnsharp: 0, radiusPx: 1, lens: null });
    expect(() => checkEnhance({ normalUnsharp: NaN })).toThrow(/normalUnsharp/);
    expect(() => checkEnhance({ lens: { mode: 'wireframe', x: 1, y: 1, radius: 5 } })).toThrow(/lens mode/);
    // Every shading mode can be shown in the lens, the ones with maps of their own included.
    expect(LENS_MODES).toEqual(SHADING_MODES);
    for (const mode of ['curvature', 'accessibility', 'quality']) {
      expect(checkEnhance({ lens: { mode, x: 1, y: 1, radius: 5 } }).lens.mode).toBe(mode);
    }
    expect(() => checkEnhance({ lens: { mode: 'trust', x: 1, y: 1, radius: 0 } })).toThrow(/radius/);
  });

  it('says in a screenshot how it was enhanced', () => {
    expect(describeEnhance(defaultEnhance())).toBe('');
    expect(describeEnhance({ normalUnsharp: 1.5, lumaUnsharp: 0, radiusPx: 8, lens: { mode: 'trust', x: 1, y: 1, radius: 9 } })).toBe(
      'normals unsharp-masked (k = 1.5, r = 8 px); lens: trust',
    );
  });

  it('puts the lens in device pixels from the bottom-left corner', () => {
    expect(lensToDevice({ x: 100, y: 50, radius: 40 }, { pixelRatio: 2, canvasHeight: 600 })).toEqual({
      centre: [200, 1100],
      radius: 80,
    });
  });

  it('sets the uniforms, and switches the lens off', () => {
    const u = uniforms();
    applyEnhance(u, { ...defaultEnhance(), normalUnsharp: 2, lens: { mode: 'trust', x: 10, y: 20, radius: 30 } }, { pixelRatio: 1, canvasHeight: 100 }, { trust: 8 });
    expect(u.uNormalUnsharp.value).toBe(2);
    expect(u.uLensMode.value).toBe(8);
    expect([u.uLensCentre.value.x, u.uLensCentre.value.y, u.uLensRadius.value]).toEqual([10, 80, 30]);
    applyEnhance(u, defaultEnhance(), { pixelRatio: 1, canvasHeight: 100 }, { trust: 8 });
    expect(u.uLensMode.value).toBe(-1);
    expect(u.uLensRadius.value).toBe(0);
  });
});
