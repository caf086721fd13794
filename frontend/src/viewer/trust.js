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
 * The ± of a distance whose ends lie on faces seen along different axes (a whole tablet):
 * each end's height error moves it along its own face's viewing axis z_k, changing the
 * distance by |ê·z_k|·σ_k (ê the unit vector a → b); its position on that face's grid, known
 * to half a pixel, by √(1 − (ê·z_k)²)·s_k/2. The ends add (worst case). With both axes the
 * model's z and one pixel size this is {@link distanceUncertaintyMm}.
 * @param {number[]} a point in mm
 * @param {number[]} b point in mm
 * @param {{sigmaUm: number, axis: number[], pixelSizeUm: number}[]} ends σ_h, the face's
 *   unit viewing axis in the model frame, and its pixel size, at a and at b
 * @returns {number} ± in mm (NaN when an end has no σ)
 */
export function distanceUncertaintyAxesMm(a, b, ends) {
  const d = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
  const len = Math.hypot(...d);
  let um = 0;
  for (const { sigmaUm, axis, pixelSizeUm } of ends) {
    if (!(len > 0)) {
      um += sigmaUm;
      continue;
    }
    const n = Math.hypot(...axis) || 1;
    const c = Math.min(1, Math.abs((d[0] * axis[0] + d[1] * axis[1] + d[2] * axis[2]) / (len * n)));
    um += c * sigmaUm + Math.sqrt(1 - c * c) * (pixelSizeUm / 2);
  }
  return um / 1000;
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

/**
 * One trust.json for a whole tablet from its faces' own (worker/register/run.py writes each
 * face's on the same legend tops): the share of each source class over the whole tablet (each
 * face's shares weighted by its tablet pixels, `pixels`; equally when a face does not say) and
 * the largest legend tops (the same on every face made by the registration).
 * @param {object[]} metas the faces' trust.json
 * @returns {object} a trust.json as trustLegend reads it
 */
export function mergeTrustMeta(metas) {
  if (!metas.length) return {};
  const weights = metas.map((m) => (Number(m.pixels) > 0 ? Number(m.pixels) : 1));
  const total = weights.reduce((a, b) => a + b, 0);
  const classFraction = {};
  for (const code of Object.keys(TRUST_CLASSES)) {
    let share = 0;
    let known = false;
    metas.forEach((m, i) => {
      const f = m.class_fraction?.[code];
      if (Number.isFinite(f)) {
        share += f * weights[i];
        known = true;
      }
    });
    if (known) classFraction[code] = share / total;
  }
  const top = (key) => {
    const v = metas.map((m) => Number(m[key])).filter((x) => x > 0);
    return v.length ? Math.max(...v) : undefined;
  };
  return {
    class_fraction: classFraction,
    disagreement_scale_um: top('disagreement_scale_um'),
    uncertainty_scale_um: top('uncertainty_scale_um'),
    faces: metas.length,
  };
}
