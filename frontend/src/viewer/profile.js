/**
 * Height profiles along a line, like the Digital Hammurabi paper's Fig. 8 (height in µm vs
 * distance in mm). Pure functions on the model's height grid.
 *
 * The grid is the scan's image grid: pixel (row r, column c) is the object-plane point
 * (x, y) = (c·s, r·s) µm with s the pixel size (SCAN_BUNDLE.md), so a point (x_mm, y_mm)
 * lies at fractional column c = 1000·x_mm/s and row r = 1000·y_mm/s.
 */

/**
 * Bilinear height at a fractional pixel position; NaN if any of the four neighbours is NaN
 * or the point is outside the grid (no extrapolation, no guessing across holes).
 * @param {Float32Array|Float64Array} heightUm (rows × cols) C-order, µm
 * @param {number} cols width of the grid
 * @param {number} rows height of the grid
 * @param {number} c fractional column
 * @param {number} r fractional row
 */
export function bilinearHeight(heightUm, cols, rows, c, r) {
  if (!(c >= 0 && r >= 0 && c <= cols - 1 && r <= rows - 1)) return Number.NaN;
  const c0 = Math.min(Math.floor(c), cols - 2 < 0 ? 0 : cols - 2);
  const r0 = Math.min(Math.floor(r), rows - 2 < 0 ? 0 : rows - 2);
  const c1 = Math.min(c0 + 1, cols - 1);
  const r1 = Math.min(r0 + 1, rows - 1);
  const fc = c - c0;
  const fr = r - r0;
  const h00 = heightUm[r0 * cols + c0];
  const h01 = heightUm[r0 * cols + c1];
  const h10 = heightUm[r1 * cols + c0];
  const h11 = heightUm[r1 * cols + c1];
  return (h00 * (1 - fc) + h01 * fc) * (1 - fr) + (h10 * (1 - fc) + h11 * fc) * fr;
}

/**
 * Sample the height along the segment from `startMm` to `endMm` (object-plane x, y in mm).
 * @param {{heightUm: Float32Array, cols: number, rows: number, pixelSizeUm: number}} grid
 * @param {[number, number]} startMm
 * @param {[number, number]} endMm
 * @param {object} [options]
 * @param {number} [options.samples] number of samples; default one per pixel along the line (≥ 2)
 * @returns {{distanceMm: Float64Array, heightUm: Float64Array, lengthMm: number}}
 *   heightUm[i] is NaN where the line leaves the reconstructed surface
 */
export function sampleProfile(grid, startMm, endMm, { samples } = {}) {
  const { heightUm, cols, rows, pixelSizeUm } = grid;
  if (!(pixelSizeUm > 0)) throw new RangeError(`pixelSizeUm must be > 0, got ${pixelSizeUm}`);
  if (!(cols >= 1 && rows >= 1) || heightUm.length !== cols * rows) {
    throw new RangeError(`heightUm has ${heightUm.length} values, expected cols·rows = ${cols * rows}`);
  }
  const dx = endMm[0] - startMm[0];
  const dy = endMm[1] - startMm[1];
  const lengthMm = Math.hypot(dx, dy);
  const n = samples ?? Math.max(2, Math.ceil((lengthMm * 1000) / pixelSizeUm) + 1);
  if (!Number.isInteger(n) || n < 2) throw new RangeError(`samples must be an integer ≥ 2, got ${samples}`);
  const distanceMm = new Float64Array(n);
  const out = new Float64Array(n);
  const pxPerMm = 1000 / pixelSizeUm;
  for (let i = 0; i < n; i++) {
    const t = i / (n - 1);
    const x = startMm[0] + t * dx;
    const y = startMm[1] + t * dy;
    distanceMm[i] = t * lengthMm;
    out[i] = bilinearHeight(heightUm, cols, rows, x * pxPerMm, y * pxPerMm);
  }
  return { distanceMm, heightUm: out, lengthMm };
}

/**
 * Profile as CSV text: `#` comment lines saying what was measured (tablet, model id and
 * version, units, end points in mm, licence, permalink), then "distance_mm,height_um" rows
 * with NaN written as an empty field. Spreadsheets and `numpy.loadtxt(comments='#')` skip
 * the comments; a reader of the file alone still knows what it is.
 * @param {{distanceMm: ArrayLike<number>, heightUm: ArrayLike<number>}} profile
 * @param {{tablet?: string, pNumber?: string|null, modelId?: number, modelVersion?: number,
 *   start?: number[], end?: number[], licence?: string|null, attribution?: string|null,
 *   permalink?: string, pixelSizeUm?: number|null}} [about]
 */
export function profileToCsv(profile, about = {}) {
  const clean = (v) => String(v).replace(/[\r\n]+/g, ' ');
  const point = (p) => p.map((v) => v.toFixed(4)).join(', ');
  const header = [
    ['tablet', about.tablet && `${about.tablet}${about.pNumber ? ` (${about.pNumber})` : ''}`],
    ['model', about.modelId != null && `id ${about.modelId}, version ${about.modelVersion ?? '?'}`],
    ['units', 'distance_mm: millimetres along the line; height_um: micrometres toward the camera'],
    ['start_mm', about.start && point(about.start)],
    ['end_mm', about.end && point(about.end)],
    ['pixel_size_um', about.pixelSizeUm],
    ['licence', about.licence],
    ['attribution', about.attribution],
    ['permalink', about.permalink],
  ]
    .filter(([, v]) => v != null && v !== false && v !== '')
    .map(([k, v]) => `# ${k}: ${clean(v)}`);
  // With σ_h along the line (trust.js), a third column: the height's uncertainty in µm.
  const sig = profile.sigmaUm;
  const lines = [...header, sig ? 'distance_mm,height_um,sigma_um' : 'distance_mm,height_um'];
  const f2 = (v) => (Number.isFinite(v) ? v.toFixed(2) : '');
  for (let i = 0; i < profile.distanceMm.length; i++) {
    const row = `${profile.distanceMm[i].toFixed(4)},${f2(profile.heightUm[i])}`;
    lines.push(sig ? `${row},${f2(sig[i])}` : row);
  }
  return `${lines.join('\n')}\n`;
}

/** Finite min and max of an array, or null if there is no finite value. */
export function finiteRange(values) {
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of values) {
    if (Number.isFinite(v)) {
      if (v < lo) lo = v;
      if (v > hi) hi = v;
    }
  }
  return lo <= hi ? [lo, hi] : null;
}

/**
 * "Nice" tick values covering [lo, hi] (1, 2, 5 × 10^k steps), for chart axes and the
 * scale bar.
 */
export function niceTicks(lo, hi, targetCount = 5) {
  if (!(hi > lo)) return [lo];
  const step = niceStep((hi - lo) / Math.max(1, targetCount));
  const first = Math.ceil(lo / step - 1e-9) * step;
  const ticks = [];
  for (let v = first; v <= hi + step * 1e-9; v += step) ticks.push(Number(v.toPrecision(12)));
  return ticks;
}

/** The largest of 1, 2, 5 × 10^k that is ≤ `value` (value > 0). */
export function niceStep(value) {
  if (!(value > 0)) throw new RangeError(`value must be > 0, got ${value}`);
  const exp = Math.floor(Math.log10(value));
  const base = 10 ** exp;
  const m = value / base;
  const f = m >= 5 ? 5 : m >= 2 ? 2 : 1;
  return f * base;
}
