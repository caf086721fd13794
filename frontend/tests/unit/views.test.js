import { describe, expect, it } from 'vitest';
import { availableViews, canonicalView, screenRight, unavailableViewReason, VIEW_NAMES } from '../../src/viewer/views.js';

const box = { min: [0, 0, -8], max: [60, 40, 2] };

describe('canonical views', () => {
  it('shows the obverse as scanned: camera at −z looking along +z, x right, y down', () => {
    const v = canonicalView('obverse', box, { aspect: 1.5 });
    expect(v.target).toEqual([30, 20, -3]);
    expect(v.position[0]).toBe(30);
    expect(v.position[1]).toBe(20);
    expect(v.position[2]).toBeLessThan(-8);
    expect(v.up).toEqual([0, -1, 0]);
    expect(screenRight([0, 0, 1], v.up)).toEqual([1, 0, 0]);
  });
  it('turns the tablet over its bottom edge for the reverse', () => {
    const v = canonicalView('reverse', box);
    expect(v.position[2]).toBeGreaterThan(2);
    expect(v.up).toEqual([0, 1, 0]); // the obverse's bottom edge (+y) is at the top
  });
  it('fits the box: a wide box in a square viewport is framed by its width', () => {
    const v = canonicalView('obverse', box, { aspect: 1, margin: 0 });
    expect(v.halfHeight).toBeCloseTo(30, 12);
    const w = canonicalView('obverse', box, { aspect: 2, margin: 0 });
    expect(w.halfHeight).toBeCloseTo(20, 12);
  });
  it('puts the camera outside the box for every view and rejects unknown names', () => {
    for (const name of VIEW_NAMES) {
      const v = canonicalView(name, box);
      const inside = v.position.every((p, i) => p >= box.min[i] && p <= box.max[i]);
      expect(inside).toBe(false);
    }
    expect(() => canonicalView('side', box)).toThrow(/name/);
  });
});

describe('edges sit around the obverse like the fat-cross layout', () => {
  it('puts the obverse side of each edge next to the obverse', () => {
    const dirOf = (v) => v.target.map((t, i) => t - v.position[i]).map((x) => Math.sign(x));
    const right = (name) => {
      const v = canonicalView(name, box);
      return screenRight(dirOf(v), v.up);
    };
    expect(right('top')).toEqual([1, 0, 0]);
    expect(right('bottom')).toEqual([1, 0, 0]);
    expect(right('reverse')).toEqual([1, 0, 0]);
    expect(right('left')).toEqual([0, 0, -1]); // obverse (−z) on the right of the left edge
    expect(right('right')).toEqual([0, 0, 1]);
  });
});

describe('available views', () => {
  it('a whole tablet has all six, a face model only its scanned side', () => {
    expect(availableViews('tablet')).toEqual(VIEW_NAMES);
    expect(availableViews('face')).toEqual(['obverse']);
    expect(() => availableViews('other')).toThrow(/kind/);
  });
  it('says why the reverse of a face model is not offered', () => {
    expect(unavailableViewReason('reverse', 'obverse')).toMatch(/obverse scan.*mirrored.*whole tablet/);
  });
});
