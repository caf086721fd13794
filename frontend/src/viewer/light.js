/**
 * The light convention of SCAN_BUNDLE.md ("Frame of reference"), in one place.
 *
 * The scan frame: x right (image columns), y DOWN (image rows), z AWAY from the camera.
 * A source at azimuth φ and polar angle θ lies in direction
 *     l = (sin θ sin φ, sin θ cos φ, −cos θ)
 * from the surface (the Digital Hammurabi paper, Eq. 2). φ = 0° lights from +y (the bottom
 * edge of the image), φ = 90° from +x (the right edge); θ = 0° is straight from the camera.
 *
 * Pure functions, no three.js: vectors are plain [x, y, z] arrays.
 */

const DEG = Math.PI / 180;

/**
 * Largest polar angle the viewer lets a light reach: anywhere on the sphere (θ > 90° lights
 * from behind the view plane, so the reverse and the edges of a whole tablet can be lit).
 */
export const MAX_POLAR_DEG = 180;

/** Largest polar angle a drag on the light widget's disc (the front hemisphere) gives. */
export const DISC_MAX_POLAR_DEG = 89;

/** Polar angle of the raking presets: low enough to throw every wedge into relief. */
export const RAKING_POLAR_DEG = 75;

/**
 * Unit light direction in the scan frame.
 * @param {number} azimuthDeg φ in degrees (any real; taken modulo 360)
 * @param {number} polarDeg θ in degrees, in [0, 180] (over 90: from behind the view plane)
 * @returns {[number, number, number]} l, |l| = 1
 */
export function lightDirection(azimuthDeg, polarDeg) {
  if (!Number.isFinite(azimuthDeg)) throw new RangeError(`azimuthDeg must be finite, got ${azimuthDeg}`);
  if (!Number.isFinite(polarDeg) || polarDeg < 0 || polarDeg > MAX_POLAR_DEG) {
    throw new RangeError(`polarDeg must lie in [0, ${MAX_POLAR_DEG}], got ${polarDeg}`);
  }
  const phi = azimuthDeg * DEG;
  const theta = polarDeg * DEG;
  return [Math.sin(theta) * Math.sin(phi), Math.sin(theta) * Math.cos(phi), -Math.cos(theta)];
}

/**
 * Inverse of {@link lightDirection}: azimuth in [0, 360) and polar angle in [0, 180].
 * @param {[number, number, number]} l any non-zero vector (normalised here)
 * @returns {{azimuthDeg: number, polarDeg: number}}
 */
export function lightAngles(l) {
  const n = Math.hypot(l[0], l[1], l[2]);
  if (!(n > 0)) throw new RangeError('l must be a non-zero vector');
  const [x, y, z] = [l[0] / n, l[1] / n, l[2] / n];
  const polarDeg = Math.acos(Math.min(1, Math.max(-1, -z))) / DEG;
  let azimuthDeg = Math.atan2(x, y) / DEG;
  if (azimuthDeg < 0) azimuthDeg += 360;
  if (Math.hypot(x, y) < 1e-12) azimuthDeg = 0;
  return { azimuthDeg, polarDeg };
}

/** Azimuth wrapped into [0, 360). */
export function wrapAzimuth(azimuthDeg) {
  const a = azimuthDeg % 360;
  return a < 0 ? a + 360 : a;
}

/** Polar angle clamped to the range the viewer allows, [0, MAX_POLAR_DEG]. */
export function clampPolar(polarDeg) {
  return Math.min(MAX_POLAR_DEG, Math.max(0, polarDeg));
}

/**
 * The light-direction widget is a disc: the hemisphere of directions seen from the camera,
 * drawn with x right and y down like the image. A direction projects to the point
 * (l_x, l_y) = sin θ (sin φ, cos φ), so φ = 0 sits at the bottom of the disc (light from the
 * bottom edge) and φ = 90° at the right.
 * @param {number} dx horizontal offset from the disc centre, in disc radii (right positive)
 * @param {number} dy vertical offset, in disc radii (DOWN positive, like the image rows)
 * @returns {{azimuthDeg: number, polarDeg: number}}
 */
export function discToAngles(dx, dy) {
  const r = Math.min(1, Math.hypot(dx, dy));
  // The disc is the hemisphere facing the camera: a drag reaches a grazing light at most
  // (lights from behind come from the arrow keys or the "behind" control).
  const polarDeg = Math.min(DISC_MAX_POLAR_DEG, Math.asin(r) / DEG);
  let azimuthDeg = r > 0 ? Math.atan2(dx, dy) / DEG : 0;
  if (azimuthDeg < 0) azimuthDeg += 360;
  return { azimuthDeg, polarDeg };
}

/** Inverse of {@link discToAngles}: the disc point [dx, dy] (radii, y down) of a light. */
export function anglesToDisc(azimuthDeg, polarDeg) {
  const [x, y] = lightDirection(azimuthDeg, polarDeg);
  return [x, y];
}

/** The eight raking presets: azimuths 0, 45, …, 315° at {@link RAKING_POLAR_DEG}. */
export const RAKING_PRESETS = Object.freeze(
  [0, 45, 90, 135, 180, 225, 270, 315].map((azimuthDeg) =>
    Object.freeze({ azimuthDeg, polarDeg: RAKING_POLAR_DEG, label: compassLabel(azimuthDeg) }),
  ),
);

/** Which image edge a light comes from, for labels ("bottom", "bottom-right", …). */
export function compassLabel(azimuthDeg) {
  const names = ['bottom', 'bottom-right', 'right', 'top-right', 'top', 'top-left', 'left', 'bottom-left'];
  return names[Math.round(wrapAzimuth(azimuthDeg) / 45) % 8];
}

/**
 * A light given relative to a camera, in the world (scan or tablet) frame. The camera's own
 * frame is the scan frame's convention seen through that camera: x = screen right, y = screen
 * DOWN, z = the viewing direction, so the angles mean on any view what they mean on a scan
 * (φ = 0: from the bottom of the screen; θ = 0: from the camera).
 * @param {number} azimuthDeg φ relative to the camera
 * @param {number} polarDeg θ relative to the camera, [0, 180]
 * @param {{right: number[], up: number[], dir: number[]}} camera unit screen-right, screen-up
 *   and viewing direction in the world frame
 * @returns {[number, number, number]} unit light direction in the world frame
 */
export function cameraLightToWorld(azimuthDeg, polarDeg, { right, up, dir }) {
  const [x, y, z] = lightDirection(azimuthDeg, polarDeg);
  const out = [0, 1, 2].map((i) => right[i] * x - up[i] * y + dir[i] * z);
  const n = Math.hypot(...out);
  return out.map((v) => v / n);
}

/**
 * The world-frame angles of a light given relative to the camera (e.g. a raking preset
 * "from the left of the screen"), so that it can stay fixed to the tablet afterwards.
 * @returns {{azimuthDeg: number, polarDeg: number}}
 */
export function cameraLightToWorldAngles(azimuthDeg, polarDeg, camera) {
  return lightAngles(cameraLightToWorld(azimuthDeg, polarDeg, camera));
}

/**
 * Inverse of {@link cameraLightToWorldAngles}: the angles, relative to a camera, of a light
 * direction given in the world frame (what the light widget shows).
 * @param {number[]} l light direction in the world frame (any length > 0)
 * @param {{right: number[], up: number[], dir: number[]}} camera as for cameraLightToWorld
 * @returns {{azimuthDeg: number, polarDeg: number}}
 */
export function worldLightToCameraAngles(l, { right, up, dir }) {
  const d = (a) => a[0] * l[0] + a[1] * l[1] + a[2] * l[2];
  return lightAngles([d(right), -d(up), d(dir)]);
}
