/**
 * Tiles under the cursor first (issue 19: full detail under the cursor ≤ 2 s after a zoom).
 *
 * 3d-tiles-renderer 0.5.3 orders its download and parse queues by "used this frame", then by
 * screen-space error (coarse first), then by distance from the camera: after a wheel zoom every
 * tile of the new view competes alike, and the one the reader points at may come last. This
 * puts a focus term between the first two: among used tiles, those nearer the cursor on screen
 * load and parse first (the foveated / "focus of attention" order of view-dependent streaming:
 * Potree's and Cesium's `foveatedScreenSpaceError` prefer tiles near the screen's centre; here
 * the centre is where the zoom went, the cursor).
 *
 * The key of a tile is the screen distance (CSS px) from the cursor to its PARENT's bounding
 * box, not its own: with REPLACE refinement and `loadAncestors` (the renderer's default) a
 * parent stays drawn until all its children have loaded (traverseFunctions.js
 * `allChildrenLoaded`), so the tile under the cursor shows its detail once its siblings have
 * loaded too; the parent's key gives the whole family the same rank.
 *
 * The queues are the renderer's shared module objects (one for every TilesRenderer, and a
 * whole tablet's external tilesets share its renderer): the comparator is installed once per
 * queue and finds each tile's focus through its own renderer (`tile.internal.renderer`);
 * tiles of renderers without a focus, or of two different renderers, keep the renderer's order.
 */

/**
 * Screen rectangle [x0, y0, x1, y1] (CSS px, y down) of a 3D Tiles `box` under a column-major
 * 4×4 matrix taking the box's frame to clip space, or null when a corner is behind the camera
 * (its projection is not a bound) or the box is malformed.
 * @param {number[]} box 12 numbers: centre, then three half-axis vectors
 * @param {ArrayLike<number>} toClip column-major 4×4
 * @param {number} width viewport width, CSS px
 * @param {number} height viewport height, CSS px
 * @returns {number[] | null}
 */
export function boxScreenRect(box, toClip, width, height) {
  if (!Array.isArray(box) || box.length !== 12) return null;
  const m = toClip;
  let x0 = Infinity;
  let y0 = Infinity;
  let x1 = -Infinity;
  let y1 = -Infinity;
  for (let i = 0; i < 8; i++) {
    const sx = i & 1 ? 1 : -1;
    const sy = i & 2 ? 1 : -1;
    const sz = i & 4 ? 1 : -1;
    const px = box[0] + sx * box[3] + sy * box[6] + sz * box[9];
    const py = box[1] + sx * box[4] + sy * box[7] + sz * box[10];
    const pz = box[2] + sx * box[5] + sy * box[8] + sz * box[11];
    const w = m[3] * px + m[7] * py + m[11] * pz + m[15];
    if (!(w > 0)) return null;
    const cx = (m[0] * px + m[4] * py + m[8] * pz + m[12]) / w;
    const cy = (m[1] * px + m[5] * py + m[9] * pz + m[13]) / w;
    // NDC → CSS pixels (y down).
    const x = ((cx + 1) / 2) * width;
    const y = ((1 - cy) / 2) * height;
    x0 = Math.min(x0, x);
    x1 = Math.max(x1, x);
    y0 = Math.min(y0, y);
    y1 = Math.max(y1, y);
  }
  return [x0, y0, x1, y1];
}

/**
 * Distance (px) from a point to a rectangle [x0, y0, x1, y1]; 0 inside or on it.
 * @param {number} x
 * @param {number} y
 * @param {number[]} rect
 */
export function distanceToRect(x, y, rect) {
  const dx = Math.max(rect[0] - x, 0, x - rect[2]);
  const dy = Math.max(rect[1] - y, 0, y - rect[3]);
  return Math.hypot(dx, dy);
}

/**
 * A queue comparator (3d-tiles-renderer's convention: > 0 means `a` runs first) that puts,
 * among tiles equally "used", the one with the smaller focus key first, and otherwise keeps
 * `base`'s order.
 * @param {(a: any, b: any) => number} base the renderer's comparator
 * @param {(tile: any) => number | null} keyOf a tile's focus key (px), null when it has none
 */
export function focusComparator(base, keyOf) {
  const compare = (a, b) => {
    const ua = a?.traversal?.used;
    const ub = b?.traversal?.used;
    if (ua === undefined || ub === undefined || ua !== ub || a.internal?.renderer !== b.internal?.renderer) return base(a, b);
    const ka = keyOf(a);
    const kb = keyOf(b);
    if (ka === null || kb === null || ka === kb) return base(a, b);
    return ka < kb ? 1 : -1;
  };
  compare.dhFocus = true;
  return compare;
}

/** renderer → {x, y, width, height, toClip (per update), frame, keys: WeakMap tile → key} */
const focusByRenderer = new WeakMap();

function parentBox(tile) {
  const p = tile.parent;
  const box = p?.boundingVolume?.box;
  return box ? { box, transform: (p.engineData ?? p.cached)?.transform ?? null } : null;
}

/** The focus key of a tile for its renderer's current focus, cached per renderer update. */
function focusKey(tile) {
  const renderer = tile?.internal?.renderer;
  const f = renderer && focusByRenderer.get(renderer);
  if (!f || !f.active) return null;
  if (f.keysFrame !== f.frame) {
    f.keys = new WeakMap();
    f.keysFrame = f.frame;
  }
  if (f.keys.has(tile)) return f.keys.get(tile);
  let key = null;
  const pb = parentBox(tile);
  if (pb) {
    const m = f.toClip;
    const toClip = pb.transform ? multiply(m, pb.transform.elements ?? pb.transform) : m;
    const rect = boxScreenRect(pb.box, toClip, f.width, f.height);
    key = rect ? distanceToRect(f.x, f.y, rect) : null;
  }
  f.keys.set(tile, key);
  return key;
}

/** a · b of two column-major 4×4 matrices (arrays). */
function multiply(a, b) {
  const out = new Array(16);
  for (let c = 0; c < 4; c++) {
    for (let r = 0; r < 4; r++) {
      out[c * 4 + r] = a[r] * b[c * 4] + a[4 + r] * b[c * 4 + 1] + a[8 + r] * b[c * 4 + 2] + a[12 + r] * b[c * 4 + 3];
    }
  }
  return out;
}

function wrap(queue) {
  if (!queue || queue.priorityCallback?.dhFocus || typeof queue.priorityCallback !== 'function') return;
  queue.priorityCallback = focusComparator(queue.priorityCallback, focusKey);
}

/**
 * Make a TilesRenderer's download and parse queues prefer the tiles near a focus point.
 * `setFocus(point)` before each update: {x, y} in CSS px of the viewport (the cursor), with
 * the camera and the viewport's size; null to drop the focus (the renderer's own order).
 * @param {import('3d-tiles-renderer/three').TilesRenderer} tiles
 */
export function installCursorPriority(tiles) {
  wrap(tiles.downloadQueue);
  wrap(tiles.parseQueue);
  const f = { active: false, x: 0, y: 0, width: 1, height: 1, toClip: null, frame: 0, keysFrame: -1, keys: null };
  focusByRenderer.set(tiles, f);
  return {
    /**
     * @param {{x: number, y: number} | null} point CSS px from the viewport's top left
     * @param {import('three').Camera} camera
     * @param {number} width viewport width, CSS px
     * @param {number} height
     */
    setFocus(point, camera, width, height) {
      f.active = Boolean(point) && width > 0 && height > 0;
      if (!f.active) return;
      camera.updateMatrixWorld();
      // Tile boxes are in the renderer group's frame: clip = P · V · group.
      const e = camera.projectionMatrix.clone().multiply(camera.matrixWorldInverse).multiply(tiles.group.matrixWorld);
      f.toClip = e.elements;
      f.x = point.x;
      f.y = point.y;
      f.width = width;
      f.height = height;
      f.frame++;
    },
  };
}
