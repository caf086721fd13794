/**
 * A whole tablet's faces as image grids: which face a model point lies on, and where it lies
 * on that face's own grid. Each face of the whole-tablet model is a glTF node whose mesh is in
 * its scan frame (SCAN_BUNDLE.md: pixel (r, c) at (c·s, r·s) µm, z = −h) under the node's
 * scan → tablet transform (worker/register/run.py), so a model point X (mm) is at
 * T⁻¹·X in the face's scan frame and its height, σ_h and trust are read there, on the face's
 * full-resolution maps (`faces/<label>/height.npy`, `uncertainty_um.npy`) as on a face model.
 * Pure functions.
 */

/**
 * The vertex span of each draw group of a merged geometry (mergeGeometries keeps each part's
 * vertices together, in order): [first, last] vertex index per group.
 * @param {ArrayLike<number> | null} index the geometry's index (null: unindexed)
 * @param {{start: number, count: number}[]} groups draw groups (index ranges)
 * @returns {[number, number][]}
 */
export function groupVertexSpans(index, groups) {
  return groups.map(({ start, count }) => {
    if (!index) return [start, start + count - 1];
    let lo = Infinity;
    let hi = -Infinity;
    for (let i = start; i < start + count; i++) {
      const v = index[i];
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
    return [lo, hi];
  });
}

/**
 * The group (face) whose nearest vertex is nearest to a point: the face a picked point lies
 * on (a pick lands on a triangle, its vertices are the face's). -1 when no group has a vertex.
 * @param {ArrayLike<number>} positions xyz per vertex (mm)
 * @param {[number, number][]} spans from {@link groupVertexSpans}
 * @param {number[]} point [x, y, z] mm
 * @param {(group: number) => boolean} [usable] groups to consider (e.g. the shown faces)
 */
export function groupOfPoint(positions, spans, point, usable = () => true) {
  let best = -1;
  let bestD = Infinity;
  spans.forEach(([lo, hi], g) => {
    if (!usable(g)) return;
    for (let i = lo; i <= hi; i++) {
      const dx = positions[3 * i] - point[0];
      const dy = positions[3 * i + 1] - point[1];
      const dz = positions[3 * i + 2] - point[2];
      const d = dx * dx + dy * dy + dz * dz;
      if (d < bestD) {
        bestD = d;
        best = g;
      }
    }
  });
  return best;
}

/**
 * A point through a 4×4 matrix given column-major (three.js' Matrix4.elements).
 * @param {ArrayLike<number>} m 16 numbers
 * @param {number[]} p [x, y, z]
 */
export function transformPoint(m, p) {
  const [x, y, z] = p;
  const w = m[3] * x + m[7] * y + m[11] * z + m[15] || 1;
  return [
    (m[0] * x + m[4] * y + m[8] * z + m[12]) / w,
    (m[1] * x + m[5] * y + m[9] * z + m[13]) / w,
    (m[2] * x + m[6] * y + m[10] * z + m[14]) / w,
  ];
}

/**
 * A plane n·X = n·o of the model frame in a face's scan frame, with X_model = T·X_face (T
 * rigid: rotation R, translation t): normal Rᵀn, through T⁻¹·o.
 * @param {{origin: number[], normal: number[]}} plane model frame
 * @param {ArrayLike<number>} toModel T, column-major
 * @param {ArrayLike<number>} toFace T⁻¹, column-major
 * @returns {{origin: number[], normal: number[]}}
 */
export function planeToFace(plane, toModel, toFace) {
  const n = plane.normal;
  const m = toModel;
  // Rᵀn: the columns of R (m[0..2], m[4..6], m[8..10]) dotted with n.
  const normal = [0, 4, 8].map((c) => m[c] * n[0] + m[c + 1] * n[1] + m[c + 2] * n[2]);
  return { origin: transformPoint(toFace, plane.origin), normal };
}

/**
 * The two ends of a line on one face, in its scan frame: what a profile or a ± on the whole
 * tablet reads that face's grid with. Throws a RangeError the page shows when the ends lie on
 * two faces (each face has its own grid; a line across the seam has no one profile).
 * @param {number[][]} points model mm
 * @param {(point: number[]) => number} faceOf the face index of a point (-1: none)
 * @param {{name: string, toFace: ArrayLike<number>}[]} faces
 * @returns {{face: number, points: number[][]}}
 */
export function pointsOnOneFace(points, faceOf, faces) {
  const idx = points.map(faceOf);
  if (idx.some((i) => i < 0 || !faces[i])) throw new RangeError('a point is not on any face');
  if (idx.some((i) => i !== idx[0])) {
    throw new RangeError(
      `the ends lie on two faces (${faces[idx[0]].name}, ${faces[idx.find((i) => i !== idx[0])].name}): each face has its own height grid, pick both on one`,
    );
  }
  const face = faces[idx[0]];
  // A streamed tablet's face has its frame once a tile of it has loaded (tiles.js faceFrame).
  if (!face.toFace) throw new RangeError(`the face ${face.name} is not loaded yet`);
  return { face: idx[0], points: points.map((p) => transformPoint(face.toFace, p)) };
}

/**
 * Texture coordinates of a model point on a face's image grid (u = (c + ½)/W, v = (r + ½)/H
 * with pixel (r, c) at (c·s, r·s) in the face's scan frame, SCAN_BUNDLE.md): what a pick on
 * model.glb's face gives as its uv, for a streamed tablet whose hits carry a tile's own uv.
 * @param {ArrayLike<number>} toFace the face's T⁻¹, column-major
 * @param {number[]} point model mm
 * @param {number} pixelSizeUm s
 * @param {number} widthPx W
 * @param {number} heightPx H
 * @returns {[number, number]}
 */
export function faceUvOfPoint(toFace, point, pixelSizeUm, widthPx, heightPx) {
  if (!(pixelSizeUm > 0 && widthPx > 0 && heightPx > 0)) throw new RangeError('the face grid needs a pixel size and a size');
  const [x, y] = transformPoint(toFace, point);
  return [((x * 1000) / pixelSizeUm + 0.5) / widthPx, ((y * 1000) / pixelSizeUm + 0.5) / heightPx];
}
