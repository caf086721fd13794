import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { groupOfPoint, groupVertexSpans, planeToFace, pointsOnOneFace, transformPoint } from '../../src/viewer/faceGrids.js';

describe('a whole tablet\'s faces as image grids', () => {
  it('finds each group\'s vertices and the face a point lies on', () => {
    // Two parts: vertices 0–2 around x = 0, vertices 3–5 around x = 10.
    const positions = Float32Array.from([0, 0, 0, 1, 0, 0, 0, 1, 0, 10, 0, 0, 11, 0, 0, 10, 1, 0]);
    const index = Uint32Array.from([0, 1, 2, 3, 4, 5]);
    const spans = groupVertexSpans(index, [{ start: 0, count: 3 }, { start: 3, count: 3 }]);
    expect(spans).toEqual([[0, 2], [3, 5]]);
    expect(groupOfPoint(positions, spans, [0.4, 0.3, 0])).toBe(0);
    expect(groupOfPoint(positions, spans, [10.6, 0.2, 0])).toBe(1);
    // A hidden face is not a candidate.
    expect(groupOfPoint(positions, spans, [10.6, 0.2, 0], (g) => g !== 1)).toBe(0);
    expect(groupOfPoint(positions, spans, [1, 1, 1], () => false)).toBe(-1);
  });

  it('takes a model point and a plane into the face\'s scan frame and back', () => {
    const toModel = new THREE.Matrix4().makeRotationY(0.7).setPosition(5, -2, 3);
    const toFace = toModel.clone().invert();
    const p = [1.5, 2.5, -0.25];
    const m = transformPoint(toModel.elements, p);
    const back = transformPoint(toFace.elements, m);
    back.forEach((v, i) => expect(v).toBeCloseTo(p[i], 12));
    const plane = { origin: [5, 0, 3], normal: [Math.SQRT1_2, 0, Math.SQRT1_2] };
    const f = planeToFace(plane, toModel.elements, toFace.elements);
    // A point of the model-frame plane lies on the face-frame plane.
    const onPlane = [5 + 2, 7, 3 - 2];
    const q = transformPoint(toFace.elements, onPlane);
    const d = f.normal.reduce((acc, n, k) => acc + n * (q[k] - f.origin[k]), 0);
    expect(d).toBeCloseTo(0, 10);
    expect(Math.hypot(...f.normal)).toBeCloseTo(1, 12);
  });

  it('reads a line on one face, and says why not across two', () => {
    const shift = new THREE.Matrix4().makeTranslation(-10, 0, 0).elements;
    const faces = [{ name: 'obverse', toFace: new THREE.Matrix4().elements }, { name: 'reverse', toFace: shift }];
    const faceOf = (p) => (p[0] < 5 ? 0 : 1);
    const on = pointsOnOneFace([[11, 1, 0], [12, 2, 0]], faceOf, faces);
    expect(on.face).toBe(1);
    expect(on.points).toEqual([[1, 1, 0], [2, 2, 0]]);
    expect(() => pointsOnOneFace([[1, 1, 0], [12, 2, 0]], faceOf, faces)).toThrow(/two faces \(obverse, reverse\)/);
    expect(() => pointsOnOneFace([[1, 1, 0]], () => -1, faces)).toThrow(/not on any face/);
  });
});

describe('a streamed face not loaded yet', () => {
  it('is refused by name rather than read in an unknown frame', () => {
    const faces = [{ name: 'obverse', toFace: null }];
    expect(() => pointsOnOneFace([[0, 0, 0], [1, 0, 0]], () => 0, faces)).toThrow(/obverse is not loaded yet/);
  });
});

describe("a point's texture coordinates on its face's grid", () => {
  it('is the uv model.glb gives the pixel there, through the face transform', async () => {
    const { faceUvOfPoint } = await import('../../src/viewer/faceGrids.js');
    // A face turned 180° about y and 12 mm behind (x → 20 − x, z → 12 − z).
    const toModel = new THREE.Matrix4().set(-1, 0, 0, 20, 0, 1, 0, 0, 0, 0, -1, 12, 0, 0, 0, 1);
    const toFace = toModel.clone().invert().elements;
    // Pixel (r, c) = (30, 40) at 250 µm: (10, 7.5) mm in the face frame, x = 20 − 10 in the model.
    const [u, v] = faceUvOfPoint(toFace, [10, 7.5, 11], 250, 80, 60);
    expect(u).toBeCloseTo((40 + 0.5) / 80, 12);
    expect(v).toBeCloseTo((30 + 0.5) / 60, 12);
    expect(() => faceUvOfPoint(toFace, [0, 0, 0], 0, 80, 60)).toThrow(RangeError);
  });
});
