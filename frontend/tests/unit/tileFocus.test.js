import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { boxScreenRect, distanceToRect, focusComparator, installCursorPriority } from '../../src/viewer/tileFocus.js';

// A 10 × 10 × 2 box centred at (5, 5, 0), seen by an orthographic camera showing x, y in
// [0, 20] on a 200 × 100 px viewport (10 px per unit across, 5 px per unit down).
const box = [5, 5, 0, 5, 0, 0, 0, 5, 0, 0, 0, 1];
function orthoCamera() {
  const cam = new THREE.OrthographicCamera(0, 20, 20, 0, 0.1, 100);
  cam.position.set(0, 0, 10);
  cam.updateMatrixWorld();
  cam.updateProjectionMatrix();
  return cam;
}
function toClip(cam) {
  return cam.projectionMatrix.clone().multiply(cam.matrixWorldInverse).elements;
}

describe('boxScreenRect', () => {
  it('is the bounds of the projected corners, CSS px with y down', () => {
    const r = boxScreenRect(box, toClip(orthoCamera()), 200, 100);
    [0, 50, 100, 100].forEach((v, i) => expect(r[i]).toBeCloseTo(v, 9));
  });

  it('is null for a corner behind a perspective camera, or a malformed box', () => {
    const cam = new THREE.PerspectiveCamera(60, 2, 0.1, 100);
    cam.position.set(5, 5, 0.5); // inside the box's depth span
    cam.updateMatrixWorld();
    expect(boxScreenRect(box, toClip(cam), 200, 100)).toBeNull();
    expect(boxScreenRect([1, 2, 3], toClip(orthoCamera()), 200, 100)).toBeNull();
  });
});

describe('distanceToRect', () => {
  it('is 0 inside or on the rectangle, the Euclidean distance outside', () => {
    expect(distanceToRect(5, 5, [0, 0, 10, 10])).toBe(0);
    expect(distanceToRect(10, 0, [0, 0, 10, 10])).toBe(0);
    expect(distanceToRect(13, 14, [0, 0, 10, 10])).toBe(5);
    expect(distanceToRect(-2, 5, [0, 0, 10, 10])).toBe(2);
  });
});

describe('focusComparator', () => {
  const renderer = {};
  const tile = (used, key, error) => ({ traversal: { used, error }, internal: { renderer }, key });
  const base = (a, b) => (a.traversal.error === b.traversal.error ? 0 : a.traversal.error > b.traversal.error ? 1 : -1);
  const cmp = focusComparator(base, (t) => t.key);
  // PriorityQueue sorts with the comparator and pops from the end: the last item runs first.
  const order = (items) => items.slice().sort(cmp).reverse();

  it('runs the tiles nearest the focus first, whatever their error', () => {
    const far = tile(true, 300, 9);
    const near = tile(true, 0, 1);
    const mid = tile(true, 40, 5);
    expect(order([far, near, mid])).toEqual([near, mid, far]);
  });

  it('keeps the renderer order for ties, for unused tiles against used, keyless tiles and other renderers', () => {
    const a = tile(true, 10, 2);
    const b = tile(true, 10, 7);
    expect(cmp(a, b)).toBe(-1); // equal keys: the base (b's larger error first)
    const unused = tile(false, 0, 9);
    const used = tile(true, 500, 1);
    expect(cmp(unused, used)).toBe(base(unused, used)); // "used" is decided by the base
    expect(cmp(tile(true, null, 1), tile(true, 0, 5))).toBe(-1);
    const other = { ...tile(true, 0, 1), internal: { renderer: {} } };
    expect(cmp(other, tile(true, 100, 5))).toBe(-1);
  });
});

describe('installCursorPriority', () => {
  // The smallest TilesRenderer it needs: two queues with the renderer's comparator and a group.
  function fakeRenderer() {
    const base = (a, b) => (a.traversal.error > b.traversal.error ? 1 : a.traversal.error < b.traversal.error ? -1 : 0);
    return {
      downloadQueue: { priorityCallback: base },
      parseQueue: { priorityCallback: base },
      group: new THREE.Group(),
    };
  }
  // Two parents side by side: x in [0, 10] and [10, 20]; each child keyed by its parent's box.
  function family(tiles, cx) {
    const parent = { boundingVolume: { box: [cx, 5, 0, 5, 0, 0, 0, 5, 0, 0, 0, 1] }, engineData: { transform: new THREE.Matrix4() } };
    return { parent, traversal: { used: true, error: 1 }, internal: { renderer: tiles } };
  }

  it('orders queued tiles by their parent box\'s distance from the cursor, once per queue', () => {
    const tiles = fakeRenderer();
    const focus = installCursorPriority(tiles);
    // A second renderer on the same shared queues: not wrapped twice.
    installCursorPriority({ ...fakeRenderer(), downloadQueue: tiles.downloadQueue, parseQueue: tiles.parseQueue });
    const cmp = tiles.downloadQueue.priorityCallback;
    expect(cmp.dhFocus).toBe(true);
    const left = family(tiles, 5);
    const right = family(tiles, 15);
    const cam = orthoCamera();
    focus.setFocus({ x: 150, y: 80 }, cam, 200, 100); // over the right parent
    expect(cmp(right, left)).toBe(1);
    focus.setFocus({ x: 20, y: 80 }, cam, 200, 100); // over the left one: keys recomputed
    expect(cmp(right, left)).toBe(-1);
    focus.setFocus(null, cam, 200, 100); // no cursor: the base order (equal errors)
    expect(cmp(right, left)).toBe(0);
  });
});
