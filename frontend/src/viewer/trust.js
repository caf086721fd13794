/**
 * Trust on screen: what the "trust" shading mode shows and the ± of every measurement. Pure
 * functions on the worker's trust assets (worker/trust.py, worker/trust_assets.py):
 *
 * - `trust.png`: R = source class, G = |fringe − final height|, B = σ_h (each 8-bit on a
 *   linear scale whose top in µm is in `trust.json`), A = 255 on the tablet;
 * - `uncertainty_um.npy`: σ_h in µm (float32, NaN off the tablet).
 *
 * Errors of two heights a, b are taken as fully correlated (the worst case: σ_a + σ_b; the
 * integration paths of neighbouring pixels share most of their steps, so they are far from
 * independent).
 */
import { bilinearHeight } from './profile.js';

/** The trust mode's layers, in the order of the panel's select (and the shader's index). */
export { TRUST_LAYERS } from './permalink.js';

/** Source classes of trust.png's red channel: code → [label, sRGB colour]. */
export const TRUST_CLASSES = Object.freeze({
  1: ['fringes and normals agree', [0.33, 0.63, 0.42]],
  2: ['fringes and normals disagree', [0.89, 0.47, 0.13]],
  3: ['normals only (no fringe height)', [0.36, 0.55, 0.86]],
  4: ['filled by the guard', [0.84, 0.19, 0.56]],
  5: ['changed by a refinement', [0.95, 0.84, 0.25]],
});

/**
 * The legend of a trust layer: categorical swatches (sources) or a ramp in µm.
 * @param {string} layer one of {@link TRUST_LAYERS}
 * @param {{disagreement_scale_um?: number, uncertainty_scale_um?: number,
 *   class_fraction?: Record<string, number>}} meta trust.json
 * @returns {{kind: 'classes', entries: {code: number, label: string, rgb: number[], fraction: number|null}[]}
 *   | {kind: 'ramp', lo: string, hi: string, what: string}}
 */
export function trustLegend(layer, meta = {}) {
  if (layer === 'sources') {
    const entries = Object.entries(TRUST_CLASSES).map(([code, [label, rgb]]) => ({
      code: Number(code),
      label,
      rgb,
      fraction: meta.class_fraction?.[code] ?? null,
    }));
    return { kind: 'classes', entries };
  }
  if (layer === 'uncertainty') {
    return { kind: 'ramp', lo: '0 µm', hi: `≥ ${fmtUm(meta.uncertainty_scale_um ?? 1)}`, what: 'height uncertainty σ_h' };
  }
  if (layer === 'disagreement') {
    return {
      kind: 'ramp',
      lo: '0 µm',
      hi: `≥ ${fmtUm(meta.disagreement_scale_um ?? 1)}`,
      what: '|fringe − final height| (grey: no fringe height)',
    };
  }
  throw new RangeError(`trust layer must be sources, uncertainty or disagreement, got ${layer}`);
}

/** A length in µm with the precision a reader needs (3 significant digits, "µm"). */
export function fmtUm(um) {
  if (!Number.isFinite(um)) return '? µm';
  return `${Number(um.toPrecision(um >= 100 ? 3 : 2))} µm`;
}

/**
 * σ_h (µm) at a model point, bilinear on the image grid (pixel (r, c) at (c·s, r·s) µm);
 * NaN off the tablet.
 * @param {{sigmaUm: Float32Array, cols: number, rows: number, pixelSizeUm: number}} grid
 * @param {number[]} pointMm [x, y, …] in mm
 */
export function sigmaAt(grid, pointMm) {
  const px = 1000 / grid.pixelSizeUm;
  return bilinearHeight(grid.sigmaUm, grid.cols, grid.rows, pointMm[0] * px, pointMm[1] * px);
}

/**
 * The ± of a distance between two picked points (mm): each end's height error moves it along
 * z, changing the distance d by (|Δz|/d)·(σ_a + σ_b); each end's position on the image grid
 * is known to half a pixel, changing d by (|Δxy|/d)·s. The two add (worst case).
 * @param {number[]} a point in mm
 * @param {number[]} b point in mm
 * @param {number} sigmaAUm σ_h at a (µm)
 * @param {number} sigmaBUm σ_h at b (µm)
 * @param {number} pixelSizeUm s
 * @returns {number} ± in mm (NaN when an end has no σ)
 */
export function distanceUncertaintyMm(a, b, sigmaAUm, sigmaBUm, pixelSizeUm) {
  const dxy = Math.hypot(a[0] - b[0], a[1] - b[1]);
  const dz = Math.abs(a[2] - b[2]);
  const d = Math.hypot(dxy, dz);
  if (!(d > 0)) return ((sigmaAUm + sigmaBUm) / 1000) || 0;
  return ((dz / d) * (sigmaAUm + sigmaBUm) + (dxy / d) * pixelSizeUm) / 1000;
}

/**
 * σ_h along a profile: one value per sample, on the same line as the heights.
 * @param {{sigmaUm: Float32Array, cols: number, rows: number, pixelSizeUm: number}} grid
 * @param {number[]} startMm
 * @param {number[]} endMm
 * @param {number} samples the profile's sample count
 * @returns {Float64Array}
 */
export function sigmaAlongLine(grid, startMm, endMm, samples) {
  const out = new Float64Array(samples);
  for (let i = 0; i < samples; i++) {
    const t = samples > 1 ? i / (samples - 1) : 0;
    out[i] = sigmaAt(grid, [startMm[0] + t * (endMm[0] - startMm[0]), startMm[1] + t * (endMm[1] - startMm[1])]);
  }
  return out;
}

/**
 * What a profile's readout says of its uncertainty: the median and the largest σ_h along the
 * line (µm), over the samples that have a height and a σ.
 * @param {ArrayLike<number>} heightUm
 * @param {ArrayLike<number>} sigmaUm
 * @returns {{medianUm: number, maxUm: number} | null}
 */
export function profileUncertainty(heightUm, sigmaUm) {
  const v = [];
  for (let i = 0; i < sigmaUm.length; i++) {
    if (Number.isFinite(heightUm[i]) && Number.isFinite(sigmaUm[i])) v.push(sigmaUm[i]);
  }
  if (!v.length) return null;
  v.sort((x, y) => x - y);
  const mid = v.length >> 1;
  const medianUm = v.length % 2 ? v[mid] : (v[mid - 1] + v[mid]) / 2;
  return { medianUm, maxUm: v[v.length - 1] };
}

/** "12.34 mm ± 8 µm" or "12.34 ± 0.21 mm": the ± in µm while it is under 0.1 mm. */
export function formatDistance(mm, pmMm) {
  if (!Number.isFinite(pmMm)) return `${mm.toFixed(2)} mm`;
  if (pmMm < 0.1) return `${mm.toFixed(2)} mm ± ${fmtUm(pmMm * 1000)}`;
  return `${mm.toFixed(2)} ± ${pmMm.toFixed(2)} mm`;
}
