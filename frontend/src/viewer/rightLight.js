/**
 * The right light for a region: the raking light that gives its wedges the most contrast,
 * from the region's normals, and the region shaded under eight raking lights (RTIViewer's
 * multi-light view). Pure functions on arrays of unit normals (model frame; light.js'
 * convention).
 *
 * Contrast: the variance over the region of the Lambertian shading max(0, n·l) — what the
 * eye sees of the wedges under that light (a light along the wedges' common slope makes them
 * all equally bright: low variance; a raking light across them lights one wall and shadows
 * the other: high variance). The lights searched rake over the region's mean plane: elevation
 * e ∈ [10°, 45°] above the plane whose normal is the region's mean normal m, every azimuth.
 * A light at local azimuth α, elevation e is l = cos e (sin α b₉₀ + cos α b₀) + sin e m, with
 * b₀ the model's φ = 0 direction (+y, the image's bottom) made orthogonal to m and
 * b₉₀ = m × b₀, so that for m = (0, 0, −1) (a face seen from its camera) local and model
 * azimuths coincide and elevation e is polar angle 90° − e.
 */
import { lightAngles } from './light.js';

export const ELEVATIONS_DEG = Object.freeze([10, 15, 20, 25, 30, 35, 40, 45]);
export const AZIMUTH_STEP_DEG = 5;
const DEG = Math.PI / 180;
/** At most this many normals enter the search (an even subsample of larger regions). */
export const MAX_NORMALS = 4096;

const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => {
  const n = Math.hypot(a[0], a[1], a[2]);
  return n > 0 ? [a[0] / n, a[1] / n, a[2] / n] : null;
};

/**
 * Decode normals.png pixels (RGBA bytes, RGB = (n + 1)/2) inside a circle of the crop.
 * @param {Uint8ClampedArray | Uint8Array} rgba width × height × 4
 * @param {number} width
 * @param {number} height
 * @param {{cx: number, cy: number, r: number} | null} circle in crop pixels (null: all)
 * @returns {Float32Array} 3N unit normals (pixels with alpha 0 or a zero vector are skipped)
 */
export function decodeNormals(rgba, width, height, circle = null) {
  const out = [];
  for (let y = 0; y < height; y++) {
    for (let x = 0; x < width; x++) {
      if (circle && Math.hypot(x + 0.5 - circle.cx, y + 0.5 - circle.cy) > circle.r) continue;
      const i = 4 * (y * width + x);
      if (rgba[i + 3] === 0) continue;
      const n = unit([(rgba[i] / 255) * 2 - 1, (rgba[i + 1] / 255) * 2 - 1, (rgba[i + 2] / 255) * 2 - 1]);
      if (n && Math.hypot(rgba[i] - 128, rgba[i + 1] - 128, rgba[i + 2] - 128) > 8) out.push(...n);
    }
  }
  return Float32Array.from(out);
}

/** The region's mean normal m and the basis b₀, b₉₀ of its plane (module docstring). */
export function regionBasis(normals) {
  const sum = [0, 0, 0];
  for (let i = 0; i < normals.length; i += 3) {
    sum[0] += normals[i];
    sum[1] += normals[i + 1];
    sum[2] += normals[i + 2];
  }
  const m = unit(sum);
  if (!m) throw new RangeError('the region has no normals');
  // b₀: the model's +y made orthogonal to m (or +x when m is along y).
  const ref = Math.abs(m[1]) < 0.95 ? [0, 1, 0] : [1, 0, 0];
  const b0 = unit(ref.map((v, k) => v - dot(ref, m) * m[k]));
  // For m = (0, 0, −1): b₀ = +y, b₉₀ = m × b₀ = +x, so φ = 90° lights from the right as in light.js.
  return { m, b0, b90: unit(cross(m, b0)) };
}

/** The unit light at local azimuth α and elevation e (degrees) over a region's plane. */
export function localLight(basis, azimuthDeg, elevationDeg) {
  const a = azimuthDeg * DEG;
  const e = elevationDeg * DEG;
  const { m, b0, b90 } = basis;
  return [0, 1, 2].map((k) => Math.cos(e) * (Math.sin(a) * b90[k] + Math.cos(a) * b0[k]) + Math.sin(e) * m[k]);
}

/** Variance of max(0, n·l) over the normals (3N array). */
export function shadingVariance(normals, l) {
  const n = normals.length / 3;
  if (!n) return 0;
  let s = 0;
  let s2 = 0;
  for (let i = 0; i < normals.length; i += 3) {
    const v = Math.max(0, normals[i] * l[0] + normals[i + 1] * l[1] + normals[i + 2] * l[2]);
    s += v;
    s2 += v * v;
  }
  const mean = s / n;
  return Math.max(0, s2 / n - mean * mean);
}

function subsample(normals) {
  const n = normals.length / 3;
  if (n <= MAX_NORMALS) return normals;
  const out = new Float32Array(MAX_NORMALS * 3);
  for (let j = 0; j < MAX_NORMALS; j++) {
    const i = Math.floor((j * n) / MAX_NORMALS);
    out.set(normals.subarray(3 * i, 3 * i + 3), 3 * j);
  }
  return out;
}

/**
 * The light of most contrast for a region: a grid search over local azimuths (every
 * AZIMUTH_STEP_DEG) and ELEVATIONS_DEG.
 * @param {Float32Array} normals 3N unit normals, model frame
 * @returns {{azimuthDeg: number, polarDeg: number, localAzimuthDeg: number,
 *   elevationDeg: number, contrast: number, direction: number[], basis: object}}
 *   azimuthDeg, polarDeg: the light in the model's frame (what viewer.setLight takes)
 */
export function bestLight(normals, { elevations = ELEVATIONS_DEG, azimuthStepDeg = AZIMUTH_STEP_DEG } = {}) {
  if (!(normals?.length >= 3)) throw new RangeError('the region has no normals');
  const basis = regionBasis(normals);
  const sample = subsample(normals);
  let best = null;
  for (const e of elevations) {
    for (let a = 0; a < 360; a += azimuthStepDeg) {
      const l = localLight(basis, a, e);
      const c = shadingVariance(sample, l);
      if (!best || c > best.contrast + 1e-12) best = { localAzimuthDeg: a, elevationDeg: e, contrast: c, direction: l };
    }
  }
  return { ...best, ...lightAngles(best.direction), basis };
}

/**
 * Eight raking lights around the region at one elevation, the first at `startDeg` (local
 * azimuth), every 45°: RTIViewer's multi-light strip.
 * @returns {{localAzimuthDeg: number, elevationDeg: number, azimuthDeg: number, polarDeg: number, direction: number[]}[]}
 */
export function rakingSet(basis, elevationDeg, startDeg = 0, count = 8) {
  return Array.from({ length: count }, (_, k) => {
    const localAzimuthDeg = (startDeg + (360 * k) / count) % 360;
    const direction = localLight(basis, localAzimuthDeg, elevationDeg);
    return { localAzimuthDeg, elevationDeg, direction, ...lightAngles(direction) };
  });
}

/**
 * A crop shaded under a light: RGBA bytes of albedo × (ambient + max(0, n·l)) (clay grey
 * without albedo); pixels without a normal stay transparent.
 * @param {Uint8ClampedArray} normalsRgba crop of normals.png
 * @param {Uint8ClampedArray | null} albedoRgba the same crop of albedo.png (sRGB), or null
 * @param {number[]} l unit light, model frame
 * @param {{ambient?: number, rotation?: number[] | null}} [options] rotation: 3×3 row-major
 *   turning the crop's normals into the model frame (a whole tablet's face), or null
 * @returns {Uint8ClampedArray}
 */
export function shadeCrop(normalsRgba, albedoRgba, l, { ambient = 0.15, rotation = null } = {}) {
  const out = new Uint8ClampedArray(normalsRgba.length);
  for (let i = 0; i < normalsRgba.length; i += 4) {
    if (normalsRgba[i + 3] === 0) continue;
    let n = [(normalsRgba[i] / 255) * 2 - 1, (normalsRgba[i + 1] / 255) * 2 - 1, (normalsRgba[i + 2] / 255) * 2 - 1];
    if (rotation) n = [0, 1, 2].map((r) => rotation[3 * r] * n[0] + rotation[3 * r + 1] * n[1] + rotation[3 * r + 2] * n[2]);
    const u = unit(n);
    if (!u) continue;
    const s = ambient + Math.max(0, dot(u, l));
    for (let k = 0; k < 3; k++) out[i + k] = (albedoRgba ? albedoRgba[i + k] : 190) * s;
    out[i + 3] = 255;
  }
  return out;
}
