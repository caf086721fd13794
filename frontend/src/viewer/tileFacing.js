/**
 * Screen-space error scaled by how a tile faces the camera (issue 19: a whole tablet's edges,
 * edge-on from the obverse, loaded their finest level for a few screen pixels).
 *
 * 3d-tiles-renderer measures a tile's error as geometricError / (size of a screen pixel at the
 * tile), which ignores the angle θ between the surface's normal and the line of sight. But the
 * tiles' maps are sampled with isotropic mip-mapping (no anisotropic filtering is asked for):
 * the GPU picks the mip level from the larger axis of a pixel's footprint in the texture, which
 * is 1/|cos θ| texels per texel seen face-on (OpenGL ES 3.0 §3.8.10, the scale factor ρ as the
 * maximum of the derivatives; Heckbert, "Fundamentals of texture mapping and image warping",
 * 1989, §3.5). Detail finer than |cos θ| of the face-on need is averaged away on screen, so a
 * tile's error is multiplied by |cos θ| (at least `floor`, so edge-on tiles still refine a few
 * levels and their silhouette stays fair).
 *
 * The normal of a tile is the third axis of its bounding box: the worker writes boxes in the
 * scan frame, axis-aligned, the third axis along the scan's viewing direction (docs/tiles.md),
 * so this is the face's mean normal, taken through the tile's transform (a whole tablet's face
 * turned into the tablet frame).
 */
import * as THREE from 'three';

/** Smallest factor: an edge-on tile refines as if seen face-on 8 times farther. */
export const FACING_FLOOR = 1 / 8;

/**
 * |cos θ| between a unit normal and a unit viewing direction, at least `floor`.
 * @param {ArrayLike<number>} normal unit vector
 * @param {ArrayLike<number>} viewDir unit vector
 * @param {number} [floor]
 */
export function facingFactor(normal, viewDir, floor = FACING_FLOOR) {
  const c = Math.abs(normal[0] * viewDir[0] + normal[1] * viewDir[1] + normal[2] * viewDir[2]);
  return Math.min(1, Math.max(floor, c));
}

/**
 * Unit normal (in the tileset's frame) of a 3D Tiles `box` bounding volume's third half-axis
 * under a 4×4 column-major transform, or null if the box is degenerate or missing.
 * @param {number[]} box 12 numbers: centre, then three half-axis vectors
 * @param {ArrayLike<number>} [transform] column-major 4×4 (the tile's accumulated transform)
 */
export function boxNormal(box, transform = null) {
  if (!Array.isArray(box) || box.length !== 12) return null;
  let [x, y, z] = [box[9], box[10], box[11]];
  if (transform) {
    const m = transform;
    [x, y, z] = [m[0] * x + m[4] * y + m[8] * z, m[1] * x + m[5] * y + m[9] * z, m[2] * x + m[6] * y + m[10] * z];
  }
  const n = Math.hypot(x, y, z);
  return n > 0 ? [x / n, y / n, z / n] : null;
}

/**
 * Make a TilesRenderer scale each tile's view error by {@link facingFactor} (its first camera).
 * Wraps the instance's calculateTileViewError (plugins can only raise the error, not lower it).
 * With `skipAway` (a whole tablet, whose faces turned away are not drawn: tiles.js), a tile
 * whose face turns away ({@link facesAway}: the box's third axis is the scan's +z, the surface
 * faces −z) has error 0: nothing finer than what is loaded is asked for there (a face's own
 * tiles, those with `extras.dh_tile`; not the tablet's root nor its references to the faces).
 * @param {import('3d-tiles-renderer/three').TilesRenderer} tiles
 * @param {{floor?: number, skipAway?: boolean}} [options]
 */
export function installFacingError(tiles, { floor = FACING_FLOOR, skipAway = false } = {}) {
  const base = tiles.calculateTileViewError.bind(tiles);
  const toGroup = new THREE.Matrix4();
  const dir = new THREE.Vector3();
  const eye = new THREE.Vector3();
  const centre = new THREE.Vector3();
  const view = [0, 0, 1];
  let ortho = true;
  let ready = false;

  // Once per update: the first camera's direction (orthographic) or position (perspective),
  // in the renderer group's frame, where the tiles' transforms and boxes are.
  tiles.addEventListener('update-before', () => {
    const camera = tiles.cameras[0];
    ready = Boolean(camera);
    if (!ready) return;
    camera.updateMatrixWorld();
    toGroup.copy(tiles.group.matrixWorld).invert();
    ortho = Boolean(camera.isOrthographicCamera);
    if (ortho) {
      camera.getWorldDirection(dir).transformDirection(toGroup);
    } else {
      eye.setFromMatrixPosition(camera.matrixWorld).applyMatrix4(toGroup);
    }
  });

  tiles.calculateTileViewError = (tile, target) => {
    base(tile, target);
    if (!ready || !(target.error > 0) || !Number.isFinite(target.error)) return;
    const data = tile.engineData ?? tile.cached;
    const transform = data?.transform?.elements ?? null;
    let n = data?.dhNormal;
    if (n === undefined) {
      n = boxNormal(tile.boundingVolume?.box, transform);
      if (data) data.dhNormal = n;
    }
    if (!n) return;
    if (ortho) {
      view[0] = dir.x;
      view[1] = dir.y;
      view[2] = dir.z;
    } else {
      const b = tile.boundingVolume.box;
      centre.set(b[0], b[1], b[2]);
      if (transform) centre.applyMatrix4(data.transform);
      centre.sub(eye).normalize();
      view[0] = centre.x;
      view[1] = centre.y;
      view[2] = centre.z;
    }
    // view runs from the camera to the tile; the face's outward axis is −n: it turns away
    // when (−n)·(−view) = n·view < AWAY_COS. Only a face's own tiles (dh_tile): the tablet's
    // root and its references to the faces' tilesets bound every face.
    if (skipAway && tile.extras?.dh_tile && n[0] * view[0] + n[1] * view[1] + n[2] * view[2] < AWAY_COS) {
      target.error = 0;
      return;
    }
    target.error *= facingFactor(n, view, floor);
  };
}

/**
 * Cosine above which a whole tablet's face is drawn: its outward axis may turn up to 120° from
 * the direction toward the camera. A face turned further away lies behind the faces toward
 * the camera (a tablet is near convex) and is not drawn: from the obverse the reverse
 * (as many triangles as the obverse) is skipped, and SwiftShader's cost of a frame grows with
 * its triangles, not only its pixels (docs/benchmarks.md, "Streaming speed, session 8").
 */
export const AWAY_COS = -0.5;

/**
 * Whether a whole tablet's face turns away from the camera.
 * @param {ArrayLike<number>} rotation the face's scan → world rotation, column-major 3×3 (a
 *   scan looks along its +z at a surface facing −z: the face's outward axis is −(third column))
 * @param {ArrayLike<number>} towardCamera unit vector from the tablet toward the camera
 * @param {number} [minCos]
 */
export function facesAway(rotation, towardCamera, minCos = AWAY_COS) {
  const r = rotation;
  const c = -(r[6] * towardCamera[0] + r[7] * towardCamera[1] + r[8] * towardCamera[2]);
  return c < minCos;
}
