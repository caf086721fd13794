/**
 * Measuring on the model: distances between picked points and height profiles along a line.
 * Pure helpers plus a small click-to-pick tool bound to a viewer.
 */

/** Euclidean distance in mm between two points given in mm. */
export function distanceMm(a, b) {
  return Math.hypot(a[0] - b[0], a[1] - b[1], a[2] - b[2]);
}

/**
 * Pixel size (µm) of the image grid, from the mesh itself: vertex x = c·s/1000 mm and
 * u = (c + 0.5)/W (docs/architecture.md), so x is linear in u with slope W·s/1000; a least-
 * squares fit over the vertices recovers s. Used when the model's report has no pixel size.
 * @param {ArrayLike<number>} positions xyz triples (mm)
 * @param {ArrayLike<number>} uvs uv pairs
 * @param {number} cols image width W in pixels
 * @returns {number} s in µm
 */
export function pixelSizeFromMesh(positions, uvs, cols) {
  const n = Math.min(positions.length / 3, uvs.length / 2);
  if (!(n >= 2)) throw new RangeError('positions and uvs must describe at least two vertices');
  let su = 0;
  let sx = 0;
  let suu = 0;
  let sux = 0;
  for (let i = 0; i < n; i++) {
    const u = uvs[2 * i];
    const x = positions[3 * i];
    su += u;
    sx += x;
    suu += u * u;
    sux += u * x;
  }
  const varU = suu - (su * su) / n;
  if (!(varU > 0)) throw new RangeError('the mesh spans no width in u');
  const slope = (sux - (su * sx) / n) / varU; // mm per unit u = W·s/1000
  return (slope * 1000) / cols;
}

/**
 * Click-to-pick tool: collects points on the model; after two clicks calls `onDone`.
 * A press that moves more than a few pixels is a drag (orbiting), not a pick.
 * @param {ReturnType<import('./viewer.js').createViewer>} viewer
 * @param {HTMLCanvasElement} canvas
 * @param {{onPoint?: (points: number[][]) => void, onDone: (points: number[][]) => void}} handlers
 */
export function createPicker(viewer, canvas, { onPoint = () => {}, onDone }) {
  let points = [];
  let active = false;
  let downAt = null;

  const down = (e) => {
    if (active && e.button === 0) downAt = [e.clientX, e.clientY];
  };
  const up = (e) => {
    if (!active || !downAt) return;
    const moved = Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]);
    downAt = null;
    if (moved > 4) return;
    const hit = viewer.pick(e.clientX, e.clientY);
    if (!hit) return;
    points = points.length >= 2 ? [hit.point] : [...points, hit.point];
    viewer.setMarks(points);
    onPoint(points);
    if (points.length === 2) onDone(points);
  };
  canvas.addEventListener('pointerdown', down);
  canvas.addEventListener('pointerup', up);

  return {
    start() {
      active = true;
      points = [];
      viewer.clearMarks();
      canvas.classList.add('picking');
    },
    stop() {
      active = false;
      points = [];
      viewer.clearMarks();
      canvas.classList.remove('picking');
    },
    get active() {
      return active;
    },
    dispose() {
      canvas.removeEventListener('pointerdown', down);
      canvas.removeEventListener('pointerup', up);
    },
  };
}
