import { describe, expect, it } from 'vitest';
import { boxNormal, FACING_FLOOR, facingFactor } from '../../src/viewer/tileFacing.js';

describe('facingFactor', () => {
  it('is |cos| of the angle between normal and line of sight, within [floor, 1]', () => {
    expect(facingFactor([0, 0, 1], [0, 0, -1])).toBe(1); // face-on, either side
    const c = Math.cos((60 * Math.PI) / 180);
    expect(facingFactor([0, 0, 1], [0, Math.sin(Math.PI / 3), c])).toBeCloseTo(0.5, 12);
    expect(facingFactor([1, 0, 0], [0, 0, 1])).toBe(FACING_FLOOR); // edge-on
    expect(facingFactor([1, 0, 0], [0, 0, 1], 0.3)).toBe(0.3);
  });
});

describe('boxNormal', () => {
  const box = [5, 5, 0.1, 5, 0, 0, 0, 5, 0, 0, 0, 0.2]; // a flat tile: the third axis is z

  it('is the box third half-axis, unit length', () => {
    expect(boxNormal(box)).toEqual([0, 0, 1]);
  });

  it('turns with the tile transform (column-major, as 3D Tiles and three.js)', () => {
    // 90 degrees about x (y to z, z to -y), scaled by 1/1000 (mm to m) and moved
    const s = 1e-3;
    const m = [s, 0, 0, 0, 0, 0, s, 0, 0, -s, 0, 0, 7, 8, 9, 1];
    const n = boxNormal(box, m);
    expect(n[0]).toBeCloseTo(0, 12);
    expect(n[1]).toBeCloseTo(-1, 12);
    expect(n[2]).toBeCloseTo(0, 12);
  });

  it('is null for a missing or degenerate box', () => {
    expect(boxNormal(undefined)).toBeNull();
    expect(boxNormal([0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 0])).toBeNull();
  });
});
