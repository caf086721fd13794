/**
 * The photographs of a whole tablet: each face keeps its scan's photographs under
 * `faces/<label>/photos/` (worker/register/io.py), their lights in THAT face's scan frame.
 * These pure functions say which face is in view, turn the viewer's light (tablet frame) into
 * the face's scan frame, and place the face's image grid in the tablet frame (for the swipe).
 *
 * Frames: transforms.json gives X_tablet = R · X_scan + t (mm; worker/register/run.py), the
 * scan frame of SCAN_BUNDLE.md (x right, y down, z away from the camera: a scan's camera looks
 * along +z, so the face it photographed faces −z). R is a rotation: its inverse is Rᵀ.
 */
import { faceAssetPrefix } from './assets.js';

/** Unit vector from a face toward its scan's camera, in its scan frame. */
const TOWARD_CAMERA_SCAN = [0, 0, -1];

function isMatrix3(m) {
  return Array.isArray(m) && m.length === 3 && m.every((r) => Array.isArray(r) && r.length === 3 && r.every(Number.isFinite));
}

/**
 * The faces of a whole tablet from its transforms.json and report.json: one record per scan,
 * in the order of transforms.json. A scan whose transform is malformed is left out.
 * @param {{scans?: Record<string, {rotation: number[][], translation_mm: number[]}>}} transforms
 * @param {{faces?: Record<string, {face?: string, pixel_size_um?: number, assets?: string}>, pixel_size_um?: number}} [report]
 * @returns {Array<{label: string, face: string|null, prefix: string, rotation: number[][],
 *   translationMm: number[], pixelMm: number|null}>} prefix: the face's asset folder with '/'
 */
export function faceFrames(transforms, report = {}) {
  const out = [];
  for (const [label, t] of Object.entries(transforms?.scans ?? {})) {
    const tr = t?.translation_mm;
    if (!isMatrix3(t?.rotation) || !Array.isArray(tr) || tr.length !== 3 || !tr.every(Number.isFinite)) continue;
    const info = report?.faces?.[label] ?? {};
    const pixelUm = Number(info.pixel_size_um ?? report?.pixel_size_um);
    out.push({
      label,
      face: typeof info.face === 'string' ? info.face : null,
      prefix: `${typeof info.assets === 'string' ? info.assets : faceAssetPrefix(label)}/`,
      rotation: t.rotation.map((r) => [...r]),
      translationMm: [...tr],
      pixelMm: pixelUm > 0 ? pixelUm / 1000 : null,
    });
  }
  return out;
}

/** R · v (tablet frame from scan frame, a direction). */
export function scanToTabletDir(face, v) {
  const R = face.rotation;
  return [0, 1, 2].map((i) => R[i][0] * v[0] + R[i][1] * v[1] + R[i][2] * v[2]);
}

/** Rᵀ · v: a tablet-frame direction (the viewer's light) in the face's scan frame. */
export function tabletToScanDir(face, v) {
  const R = face.rotation;
  return [0, 1, 2].map((j) => R[0][j] * v[0] + R[1][j] * v[1] + R[2][j] * v[2]);
}

/** R · p + t: a point of the face's scan frame (mm) in the tablet frame. */
export function scanToTabletPoint(face, p) {
  const r = scanToTabletDir(face, p);
  return r.map((v, i) => v + face.translationMm[i]);
}

/**
 * The face the camera looks at most squarely: the one whose direction toward its own scan's
 * camera (R · (0, 0, −1)) is closest to the direction toward the viewer's camera (−viewDir).
 * @param {Array<{rotation: number[][]}>} faces from {@link faceFrames}
 * @param {number[]} viewDir the direction the viewer's camera looks in (tablet frame, any length)
 * @returns {{face: object, cosine: number} | null} cosine: of the angle between the two
 */
export function faceInView(faces, viewDir) {
  const n = Math.hypot(...viewDir);
  if (!(n > 0)) throw new RangeError('viewDir must be a non-zero vector');
  let best = null;
  for (const face of faces ?? []) {
    const out = scanToTabletDir(face, TOWARD_CAMERA_SCAN);
    const cosine = -(out[0] * viewDir[0] + out[1] * viewDir[1] + out[2] * viewDir[2]) / n;
    if (!best || cosine > best.cosine) best = { face, cosine };
  }
  return best;
}

/**
 * The face (of {@link faceFrames}) a picked part names: model.glb's parts are named by the
 * scan's label, a streamed tablet's tiles by the face's asset folder (tiles' `dh_face`, the
 * label with unsafe characters replaced, assets.faceAssetPrefix), so either matches.
 * @param {Array<{label: string, prefix: string}>} faces
 * @param {string | null | undefined} part
 */
export function faceOfPart(faces, part) {
  if (part == null) return null;
  const prefix = `${faceAssetPrefix(part)}/`;
  return faces.find((f) => f.label === part) ?? faces.find((f) => f.prefix === prefix) ?? null;
}
