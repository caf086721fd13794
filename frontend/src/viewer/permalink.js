/**
 * Permalinks: the viewer state that makes a reading citable — camera, light, shading, the
 * hidden faces of a whole-tablet model and the measurement on screen (a distance or a height
 * profile between two points, in the model's millimetres) — as
 * the URL fragment of a tablet page (`tablet.html?id=12#m=31&az=45&…`). Pure functions.
 *
 * The fragment is never sent to the server, so a permalink cannot break caching, and it keeps
 * working when the page is served from elsewhere.
 */

/** What the trust mode shows (trust.js re-exports it). */
export const TRUST_LAYERS = Object.freeze(['sources', 'uncertainty', 'disagreement']);

import { defaultEnhance, LENS_MODES, RADIUS_RANGE_PX, UNSHARP_MAX } from './enhance.js';

export const SHADING_MODES = Object.freeze([
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

export const PROJECTIONS = Object.freeze(['orthographic', 'perspective']);

/** Defaults of everything a permalink can carry (camera null: frame the model). */
export function defaultViewState() {
  return {
    model: null,
    camera: null,
    // follow: the angles are relative to the camera and the light turns with it (else fixed to
    // the model, angles in its frame).
    light: { azimuthDeg: 315, polarDeg: 45, intensity: 1, ambient: 0.15, gloss: 0, follow: false },
    // trustLayer: what the trust mode shows (trust.js' TRUST_LAYERS)
    shading: { mode: 'natural', curvatureScale: 0, exaggeration: 2, quality: null, trustLayer: 'sources' },
    hidden: [], // names of hidden parts (faces of a whole-tablet model); [] = all shown
    measure: null, // {tool: 'distance' | 'profile', points: [[x, y, z], [x, y, z]]} in mm
    enhance: defaultEnhance(), // unsharp masking and the lens (enhance.js); lens in CSS px
  };
}

export const MAX_HIDDEN_PARTS = 100;
/** Measurement tools a link may carry, by their one-letter code. */
const MEASURE_TOOLS = Object.freeze({ distance: 'd', profile: 'p' });
const MAX_PART_NAME = 200;

/** A part name a link may carry: any text (glTF node names are free) without control characters. */
function isPartName(name) {
  return (
    typeof name === 'string' &&
    name.length <= MAX_PART_NAME &&
    name.trim() !== '' &&
    !/[\u0000-\u001f\u007f]/.test(name)
  );
}

const SIG = 7; // significant digits: 0.1 µm on a 100 mm tablet

function num(v) {
  return String(Number(v.toPrecision(SIG)));
}

function vec(v) {
  return v.map(num).join(',');
}

/**
 * Encode a view state as a URL fragment (without the leading '#').
 * @param {ReturnType<typeof defaultViewState>} state
 * @returns {string}
 */
export function encodeViewState(state) {
  const p = new URLSearchParams();
  if (state.model != null) p.set('m', String(state.model));
  const cam = state.camera;
  if (cam) {
    p.set('cam', cam.projection === 'perspective' ? 'p' : 'o');
    p.set('pos', vec(cam.position));
    p.set('tgt', vec(cam.target));
    p.set('up', vec(cam.up));
    p.set('zoom', num(cam.zoom));
  }
  const l = state.light;
  p.set('az', num(l.azimuthDeg));
  p.set('po', num(l.polarDeg));
  p.set('li', num(l.intensity));
  p.set('am', num(l.ambient));
  p.set('gl', num(l.gloss));
  if (l.follow) p.set('lf', '1');
  const s = state.shading;
  p.set('mode', s.mode);
  if (s.curvatureScale) p.set('cs', String(s.curvatureScale));
  p.set('ex', num(s.exaggeration));
  if (s.quality) p.set('qm', s.quality);
  if (s.trustLayer && s.trustLayer !== 'sources') p.set('tl', s.trustLayer);
  // One `hide` per name, not a comma list: node names may contain commas.
  for (const name of state.hidden ?? []) p.append('hide', name);
  const e = state.enhance;
  if (e) {
    if (e.normalUnsharp) p.set('un', num(e.normalUnsharp));
    if (e.lumaUnsharp) p.set('ul', num(e.lumaUnsharp));
    if (e.radiusPx !== defaultEnhance().radiusPx) p.set('ur', num(e.radiusPx));
    if (e.lens) {
      p.set('lz', e.lens.mode);
      p.set('lx', num(e.lens.x));
      p.set('ly', num(e.lens.y));
      p.set('lr', num(e.lens.radius));
    }
  }
  const m = state.measure;
  if (m && MEASURE_TOOLS[m.tool] && m.points?.length === 2) {
    p.set('mt', MEASURE_TOOLS[m.tool]);
    p.set('ma', vec(m.points[0]));
    p.set('mb', vec(m.points[1]));
  }
  return p.toString();
}

function parseNumber(text, lo, hi) {
  if (text === null || text.trim() === '') return undefined;
  const v = Number(text);
  if (!Number.isFinite(v) || v < lo || v > hi) return undefined;
  return v;
}

function parseVec(text) {
  if (!text) return undefined;
  const parts = text.split(',').map(Number);
  return parts.length === 3 && parts.every(Number.isFinite) ? parts : undefined;
}

/**
 * Decode a URL fragment; anything missing or malformed takes its default and is named in
 * `ignored`, so the page can say which part of a link it could not use.
 * @param {string} fragment with or without the leading '#'
 * @returns {{state: ReturnType<typeof defaultViewState>, ignored: string[]}}
 */
export function decodeViewState(fragment) {
  const p = new URLSearchParams(fragment.startsWith('#') ? fragment.slice(1) : fragment);
  const state = defaultViewState();
  const ignored = [];
  const take = (key, value, assign) => {
    if (!p.has(key)) return;
    if (value === undefined) ignored.push(key);
    else assign(value);
  };

  take('m', parseNumber(p.get('m'), 1, Number.MAX_SAFE_INTEGER), (v) => {
    if (Number.isInteger(v)) state.model = v;
    else ignored.push('m');
  });

  if (p.has('cam') || p.has('pos')) {
    const projection = { o: 'orthographic', p: 'perspective' }[p.get('cam') ?? 'o'];
    const position = parseVec(p.get('pos'));
    const target = parseVec(p.get('tgt'));
    const up = parseVec(p.get('up'));
    const zoom = parseNumber(p.get('zoom') ?? '1', 1e-6, 1e6);
    const upOk = up && Math.hypot(...up) > 1e-9;
    const distinct = position && target && Math.hypot(...position.map((v, i) => v - target[i])) > 0;
    if (projection && position && target && upOk && zoom !== undefined && distinct) {
      state.camera = { projection, position, target, up, zoom };
    } else {
      ignored.push('camera');
    }
  }

  const l = state.light;
  take('az', parseNumber(p.get('az'), -1e6, 1e6), (v) => (l.azimuthDeg = ((v % 360) + 360) % 360));
  take('po', parseNumber(p.get('po'), 0, 180), (v) => (l.polarDeg = v));
  take('li', parseNumber(p.get('li'), 0, 10), (v) => (l.intensity = v));
  take('am', parseNumber(p.get('am'), 0, 1), (v) => (l.ambient = v));
  take('gl', parseNumber(p.get('gl'), 0, 1), (v) => (l.gloss = v));
  take('lf', ['0', '1'].includes(p.get('lf')) ? p.get('lf') === '1' : undefined, (v) => (l.follow = v));

  const s = state.shading;
  take('mode', SHADING_MODES.includes(p.get('mode')) ? p.get('mode') : undefined, (v) => (s.mode = v));
  take('cs', parseNumber(p.get('cs'), 0, 2), (v) => {
    if (Number.isInteger(v)) s.curvatureScale = v;
    else ignored.push('cs');
  });
  take('ex', parseNumber(p.get('ex'), 0, 20), (v) => (s.exaggeration = v));
  // A quality map's asset name, e.g. quality/walls.npy (folders allowed; it only selects among
  // the model's own maps).
  take('qm', /^[\w.-]+(\/[\w.-]+)*$/.test(p.get('qm') ?? '') && p.get('qm').length <= 100 ? p.get('qm') : undefined, (v) => (s.quality = v));
  take('tl', TRUST_LAYERS.includes(p.get('tl')) ? p.get('tl') : undefined, (v) => (s.trustLayer = v));

  // Which names exist is known only once the model is loaded: the viewer ignores unknown ones.
  const hide = p.getAll('hide');
  const valid = hide.filter(isPartName);
  const names = [...new Set(valid)];
  state.hidden = names.slice(0, MAX_HIDDEN_PARTS);
  if (valid.length !== hide.length || names.length > MAX_HIDDEN_PARTS) ignored.push('hide');

  const e = state.enhance;
  take('un', parseNumber(p.get('un'), 0, UNSHARP_MAX), (v) => (e.normalUnsharp = v));
  take('ul', parseNumber(p.get('ul'), 0, UNSHARP_MAX), (v) => (e.lumaUnsharp = v));
  take('ur', parseNumber(p.get('ur'), ...RADIUS_RANGE_PX), (v) => (e.radiusPx = v));
  if (['lz', 'lx', 'ly', 'lr'].some((k) => p.has(k))) {
    // The lens is in CSS pixels of the canvas: a link opened on a smaller screen may put it
    // outside; it is still restored (the reader can drag it back).
    const mode = p.get('lz');
    const [x, y] = ['lx', 'ly'].map((k) => parseNumber(p.get(k), -1e5, 1e5));
    const radius = parseNumber(p.get('lr'), 1, 1e5);
    if (LENS_MODES.includes(mode) && [x, y, radius].every((v) => v !== undefined)) e.lens = { mode, x, y, radius };
    else ignored.push('lens');
  }

  if (p.has('mt') || p.has('ma') || p.has('mb')) {
    const tool = Object.keys(MEASURE_TOOLS).find((k) => MEASURE_TOOLS[k] === p.get('mt'));
    const a = parseVec(p.get('ma'));
    const b = parseVec(p.get('mb'));
    if (tool && a && b && Math.hypot(...a.map((v, i) => v - b[i])) > 0) {
      state.measure = { tool, points: [a, b] };
    } else {
      ignored.push('measurement');
    }
  }
  return { state, ignored };
}
