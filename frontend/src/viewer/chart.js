/**
 * A height profile as an SVG line chart: height in µm against distance in mm (the paper's
 * Fig. 8). Gaps where the profile leaves the surface (NaN) break the line.
 */
import { finiteRange, niceTicks } from './profile.js';

const SVG = 'http://www.w3.org/2000/svg';

function el(name, attrs = {}, text) {
  const node = document.createElementNS(SVG, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text !== undefined) node.textContent = text;
  return node;
}

/**
 * The band h ± σ_h where both are finite, as SVG path data: one closed polygon per run of
 * samples (a gap breaks the band as it breaks the line). Pure; sx, sy map data to the chart.
 * @param {{distanceMm: ArrayLike<number>, heightUm: ArrayLike<number>, sigmaUm: ArrayLike<number>}} profile
 * @param {(x: number) => number} sx
 * @param {(y: number) => number} sy
 * @returns {string}
 */
export function bandPath(profile, sx, sy) {
  const { distanceMm: x, heightUm: h, sigmaUm: s } = profile;
  let d = '';
  let run = [];
  const flush = () => {
    if (run.length >= 2) {
      const up = run.map((i) => `${sx(x[i]).toFixed(1)},${sy(h[i] + s[i]).toFixed(1)}`);
      const down = run.map((i) => `${sx(x[i]).toFixed(1)},${sy(h[i] - s[i]).toFixed(1)}`).reverse();
      d += `M${up.join('L')}L${down.join('L')}Z`;
    }
    run = [];
  };
  for (let i = 0; i < x.length; i++) {
    if (Number.isFinite(h[i]) && Number.isFinite(s[i])) run.push(i);
    else flush();
  }
  flush();
  return d;
}

/**
 * @param {{distanceMm: ArrayLike<number>, heightUm: ArrayLike<number>, sigmaUm?: ArrayLike<number>}} profile
 *   with `sigmaUm` (σ_h per sample, trust.js) a band h ± σ_h is drawn under the line
 * @param {{width?: number, height?: number}} [size]
 * @returns {SVGSVGElement}
 */
export function profileChart(profile, { width = 520, height = 220 } = {}) {
  const m = { left: 56, right: 12, top: 12, bottom: 36 };
  const svg = el('svg', { viewBox: `0 0 ${width} ${height}`, class: 'profile-chart', role: 'img' });
  const xr = [0, profile.distanceMm[profile.distanceMm.length - 1] || 1];
  const yr = finiteRange(profile.heightUm) ?? [0, 1];
  if (profile.sigmaUm) {
    const hi = finiteRange(Array.from(profile.heightUm, (h, i) => h + profile.sigmaUm[i]));
    const lo = finiteRange(Array.from(profile.heightUm, (h, i) => h - profile.sigmaUm[i]));
    if (hi && lo) [yr[0], yr[1]] = [Math.min(yr[0], lo[0]), Math.max(yr[1], hi[1])];
  }
  if (yr[1] - yr[0] < 1) {
    yr[0] -= 0.5;
    yr[1] += 0.5;
  }
  const pw = width - m.left - m.right;
  const ph = height - m.top - m.bottom;
  const sx = (x) => m.left + ((x - xr[0]) / (xr[1] - xr[0])) * pw;
  const sy = (y) => m.top + (1 - (y - yr[0]) / (yr[1] - yr[0])) * ph;
  svg.append(el('title', {}, 'Height profile: height in micrometres against distance in millimetres'));
  const axes = el('g', { class: 'axes' });
  for (const t of niceTicks(xr[0], xr[1], 6)) {
    axes.append(el('line', { x1: sx(t), x2: sx(t), y1: m.top, y2: m.top + ph, class: 'grid' }));
    axes.append(el('text', { x: sx(t), y: height - m.bottom + 14, 'text-anchor': 'middle' }, String(t)));
  }
  for (const t of niceTicks(yr[0], yr[1], 5)) {
    axes.append(el('line', { x1: m.left, x2: m.left + pw, y1: sy(t), y2: sy(t), class: 'grid' }));
    axes.append(el('text', { x: m.left - 6, y: sy(t) + 4, 'text-anchor': 'end' }, String(t)));
  }
  axes.append(el('text', { x: m.left + pw / 2, y: height - 4, 'text-anchor': 'middle' }, 'distance (mm)'));
  axes.append(
    el('text', { x: 12, y: m.top + ph / 2, 'text-anchor': 'middle', transform: `rotate(-90 12 ${m.top + ph / 2})` }, 'height (µm)'),
  );
  svg.append(axes);
  if (profile.sigmaUm) {
    const band = el('path', { d: bandPath(profile, sx, sy), class: 'band' });
    band.append(el('title', {}, 'height ± σ_h (height uncertainty from the trust map)'));
    svg.append(band);
  }
  let d = '';
  let pen = false;
  for (let i = 0; i < profile.distanceMm.length; i++) {
    const h = profile.heightUm[i];
    if (!Number.isFinite(h)) {
      pen = false;
      continue;
    }
    d += `${pen ? 'L' : 'M'}${sx(profile.distanceMm[i]).toFixed(1)},${sy(h).toFixed(1)}`;
    pen = true;
  }
  svg.append(el('path', { d, class: 'line' }));
  return svg;
}
