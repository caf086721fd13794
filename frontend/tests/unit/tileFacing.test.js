import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { AWAY_COS, boxNormal, FACING_FLOOR, facesAway, facingFactor, installFacingError } from '../../src/viewer/tileFacing.js';

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

describe('facesAway', () => {
  const identity = [1, 0, 0, 0, 1, 0, 0, 0, 1]; // the obverse: outward axis -z
  const reverse = [-1, 0, 0, 0, 1, 0, 0, 0, -1]; // 180 degrees about y: outward +z
  const left = [0, 0, 1, 0, 1, 0, -1, 0, 0]; // an edge turned 90 degrees about y: outward axis +x

  it('is true only for a face whose outward axis turns more than 120 degrees from the camera', () => {
    const obverseView = [0, 0, -1]; // toward a camera in front of the obverse
    expect(facesAway(identity, obverseView)).toBe(false);
    expect(facesAway(reverse, obverseView)).toBe(true);
    expect(facesAway(left, obverseView)).toBe(false); // edge-on: drawn
    const a = (110 * Math.PI) / 180; // 110 degrees from the obverse's axis: still drawn
    expect(facesAway(identity, [Math.sin(a), 0, -Math.cos(a)])).toBe(false);
    const b = (130 * Math.PI) / 180;
    expect(facesAway(identity, [Math.sin(b), 0, -Math.cos(b)])).toBe(true);
    expect(facesAway(identity, [Math.sin(b), 0, -Math.cos(b)], -0.7)).toBe(false);
    expect(AWAY_COS).toBe(-0.5);
  });
});

describe('installFacingError', () => {
  // The smallest TilesRenderer it needs: a base error of 10, one camera, the update event.
  function fakeTiles(camera) {
    const listeners = {};
    return {
      cameras: [camera],
      group: new THREE.Group(),
      calculateTileViewError: (tile, target) => {
        target.error = 10;
      },
      addEventListener: (type, f) => {
        listeners[type] = f;
      },
      update() {
        listeners['update-before']?.();
      },
    };
  }
  const box = [0, 0, 0, 5, 0, 0, 0, 5, 0, 0, 0, 1]; // third axis: the scan's +z
  const dhTile = { level: 0, x: 0, y: 0, pixel_step: 4 };
  const tile = (rotation, extras = { dh_tile: dhTile }) => ({ boundingVolume: { box }, engineData: { transform: rotation }, extras });
  const obverse = tile(new THREE.Matrix4());
  const reverse = tile(new THREE.Matrix4().makeRotationY(Math.PI));
  const edge = tile(new THREE.Matrix4().makeRotationY(Math.PI / 2));
  // An orthographic camera in front of the obverse, looking along +z (as its scan did).
  const camera = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.1, 100);
  camera.position.set(0, 0, -10);
  camera.lookAt(0, 0, 0);

  it('scales the error by the facing; with skipAway a face turned away asks for nothing', () => {
    const tiles = fakeTiles(camera);
    installFacingError(tiles, { skipAway: true });
    tiles.update();
    const error = (t) => {
      const target = { error: 0 };
      tiles.calculateTileViewError(t, target);
      return target.error;
    };
    expect(error(obverse)).toBeCloseTo(10, 9);
    expect(error(edge)).toBeCloseTo(10 * FACING_FLOOR, 9);
    expect(error(reverse)).toBe(0);
    // the tablet's own tiles (its root, its references to the faces' tilesets) bound every
    // face: never skipped
    expect(error(tile(new THREE.Matrix4().makeRotationY(Math.PI), {}))).toBeCloseTo(10, 9);
  });

  it('keeps a face turned away at its facing error without skipAway (a face model)', () => {
    const tiles = fakeTiles(camera);
    installFacingError(tiles);
    tiles.update();
    const target = { error: 0 };
    tiles.calculateTileViewError(tile(new THREE.Matrix4().makeRotationY(Math.PI)), target);
    expect(target.error).toBeCloseTo(10, 9);
  });
});
