/**
 * RTIViewer's enhancements and OpenLIME's lens as viewer state (the GLSL is in
 * shaderExtras.js). Pure functions: the state, its checks, and the uniforms it sets.
 *
 * - Unsharp masking of the normals, k_n: n' = normalize(n + k_n(n − blur_r(n))) — every lit
 *   mode sees the sharpened normals (RTIViewer's "normal unsharp masking");
 * - unsharp masking of the luminance, k_L: L' = L + k_L(L − blur_r(L)) on the diffuse
 *   luminance of the natural-colour and clay modes (RTIViewer's "luminance unsharp masking";
 *   Palma et al. 2010);
 * - r: the blur radius in texels of the normal map (both masks);
 * - the lens: another shading mode inside a circle of the canvas (OpenLIME, Ponchio et al.
 *   2022), centre and radius in CSS pixels of the canvas.
 */

/** Modes the lens can show: every shading mode (permalink.js' SHADING_MODES; listed here, as
 * permalink.js imports this module). The viewer binds the lens mode's maps beside the main
 * mode's and loads them on first use, as it does for the main mode. */
export const LENS_MODES = Object.freeze([
  'natural',
  'clay',
  'curvature',
  'accessibility',
  'relief',
  'depth',
  'normals',
  'quality',
  'trust',
]);

export const UNSHARP_MAX = 8;
export const RADIUS_RANGE_PX = Object.freeze([1, 64]);

/** Enhancements off, no lens. */
export function defaultEnhance() {
  return { normalUnsharp: 0, lumaUnsharp: 0, radiusPx: 8, lens: null };
}

/**
 * Check an enhancement state; returns it normalised (numbers clamped to their ranges) or
 * throws a RangeError naming the field.
 * @param {{normalUnsharp: number, lumaUnsharp: number, radiusPx: number,
 *   lens: null | {mode: string, x: number, y: number, radius: number}}} e
 */
export function checkEnhance(e) {
  const out = { ...defaultEnhance(), ...e };
  for (const key of ['normalUnsharp', 'lumaUnsharp', 'radiusPx']) {
    if (!Number.isFinite(out[key])) throw new RangeError(`${key} must be a number, got ${out[key]}`);
  }
  out.normalUnsharp = Math.min(Math.max(out.normalUnsharp, 0), UNSHARP_MAX);
  out.lumaUnsharp = Math.min(Math.max(out.lumaUnsharp, 0), UNSHARP_MAX);
  out.radiusPx = Math.min(Math.max(out.radiusPx, RADIUS_RANGE_PX[0]), RADIUS_RANGE_PX[1]);
  if (out.lens) {
    const { mode, x, y, radius } = out.lens;
    if (!LENS_MODES.includes(mode)) throw new RangeError(`lens mode must be one of ${LENS_MODES.join(', ')}, got ${mode}`);
    if (![x, y, radius].every(Number.isFinite) || radius <= 0) {
      throw new RangeError('lens x, y and radius must be numbers, radius > 0');
    }
    out.lens = { mode, x, y, radius };
  }
  return out;
}

/**
 * What a screenshot's description says of the enhancements ('' when off), so a saved image
 * tells how it was made: "normals unsharp-masked (k = 1.5, r = 8 px); lens: trust".
 * @param {object} e see {@link checkEnhance}
 */
export function describeEnhance(e) {
  const parts = [];
  const r = `r = ${e.radiusPx} px`;
  if (e.normalUnsharp > 0) parts.push(`normals unsharp-masked (k = ${e.normalUnsharp}, ${r})`);
  if (e.lumaUnsharp > 0) parts.push(`luminance unsharp-masked (k = ${e.lumaUnsharp}, ${r})`);
  if (e.lens) parts.push(`lens: ${e.lens.mode}`);
  return parts.join('; ');
}

/**
 * The lens in the shader's terms: gl_FragCoord is in device pixels from the bottom-left
 * corner, the page's positions in CSS pixels from the top-left.
 * @param {{x: number, y: number, radius: number}} lens CSS pixels of the canvas
 * @param {{pixelRatio: number, canvasHeight: number}} canvas CSS height, device pixel ratio
 * @returns {{centre: [number, number], radius: number}} device pixels
 */
export function lensToDevice(lens, { pixelRatio, canvasHeight }) {
  return {
    centre: [lens.x * pixelRatio, (canvasHeight - lens.y) * pixelRatio],
    radius: lens.radius * pixelRatio,
  };
}

/**
 * Set the extras' uniforms (shaderExtras.js) from an enhancement state.
 * @param {Record<string, {value: any}>} u the material's uniforms
 * @param {object} enhance see {@link checkEnhance}
 * @param {{pixelRatio: number, canvasHeight: number}} canvas
 * @param {Record<string, number>} modeIndex shading mode → the shader's mode number
 */
export function applyEnhance(u, enhance, canvas, modeIndex) {
  const e = checkEnhance(enhance);
  u.uNormalUnsharp.value = e.normalUnsharp;
  u.uLumaUnsharp.value = e.lumaUnsharp;
  u.uUnsharpRadius.value = e.radiusPx;
  if (e.lens) {
    const d = lensToDevice(e.lens, canvas);
    u.uLensMode.value = modeIndex[e.lens.mode];
    u.uLensCentre.value.set(d.centre[0], d.centre[1]);
    u.uLensRadius.value = d.radius;
  } else {
    u.uLensMode.value = -1;
    u.uLensRadius.value = 0;
  }
  return e;
}
