import { describe, expect, it } from 'vitest';
import {
  annotationsOfSign,
  canAnnotate,
  canEdit,
  centroid,
  normaliseReference,
  regionBody,
  uvToPixel,
} from '../../src/viewer/annotations.js';

describe('uvToPixel', () => {
  it('inverts u = (c + 0.5)/W, v = (r + 0.5)/H', () => {
    expect(uvToPixel([(10 + 0.5) / 200, (20 + 0.5) / 100], 200, 100)).toEqual([10, 20]);
    expect(uvToPixel([0, 0], 4, 4)).toEqual([-0.5, -0.5]);
  });
  it('refuses an empty grid', () => {
    expect(() => uvToPixel([0.5, 0.5], 0, 10)).toThrow(RangeError);
  });
});

describe('normaliseReference', () => {
  it('writes references as the API does', () => {
    expect(normaliseReference('  O  2 3 ')).toBe('o 2 3');
    expect(normaliseReference("r 3' 1")).toBe("r 3' 1");
    expect(normaliseReference('be 4a 10')).toBe('be 4a 10');
  });
  it('returns null for what is not a reference', () => {
    for (const bad of ['', 'o 2', 'x 2 3', 'o 0 1', 'o 2 0', 'o two 1', null]) expect(normaliseReference(bad)).toBeNull();
  });
});

describe('who may annotate and edit', () => {
  const tablet = { institution_id: 7 };
  const mine = { creatorId: 3 };
  it('lets the author, the holding institution staff and admins edit', () => {
    expect(canEdit({ id: 3, role: 'reader' }, mine, tablet)).toBe(true);
    expect(canEdit({ id: 4, role: 'reader' }, mine, tablet)).toBe(false);
    expect(canEdit({ id: 5, role: 'staff', institution_id: 7 }, mine, tablet)).toBe(true);
    expect(canEdit({ id: 6, role: 'staff', institution_id: 8 }, mine, tablet)).toBe(false);
    expect(canEdit({ id: 9, role: 'admin' }, mine, tablet)).toBe(true);
    expect(canEdit(null, mine, tablet)).toBe(false);
  });
  it('lets signed-in users annotate', () => {
    expect(canAnnotate(null)).toBe(false);
    expect(canAnnotate({ role: 'reader' })).toBe(true);
  });
});

describe('regions', () => {
  const picks = [
    { point: [1.123456, 2, 3], uv: [0.5 / 10, 0.5 / 10], part: 'obverse' },
    { point: [2, 2, 3], uv: [1.5 / 10, 0.5 / 10], part: 'obverse' },
    { point: [2, 3, 3], uv: [1.5 / 10, 1.5 / 10], part: 'obverse' },
  ];
  it('sends only millimetres for a face model', () => {
    expect(regionBody(picks, { whole: false, gridOf: () => null })).toEqual({
      polygon_mm: [
        [1.1235, 2, 3],
        [2, 2, 3],
        [2, 3, 3],
      ],
    });
  });
  it('adds the face image grid for a whole tablet when every point is on one face', () => {
    const body = regionBody(picks, { whole: true, gridOf: () => ({ width: 10, height: 10 }) });
    expect(body.image_face).toBe('obverse');
    expect(body.polygon_px).toEqual([
      [0, 0],
      [1, 0],
      [1, 1],
    ]);
    const across = regionBody([...picks.slice(0, 2), { ...picks[2], part: 'top' }], { whole: true, gridOf: () => ({ width: 10, height: 10 }) });
    expect(across.polygon_px).toBeUndefined();
  });
  it('finds a sign’s annotations and a region’s centre', () => {
    const items = [{ reference: { text: 'o 1 1' } }, { reference: { text: 'o 1 2' } }];
    expect(annotationsOfSign(items, 'o 1 2')).toEqual([items[1]]);
    expect(centroid([[0, 0, 0], [2, 0, 0], [1, 3, 0]])).toEqual([1, 1, 0]);
  });
});
