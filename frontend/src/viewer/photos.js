/**
 * The photograph beside the render: the worker keeps every light's photograph of a scan
 * (`photos/index.json`, worker/photos.py); this picks the one taken nearest to the viewer's
 * light, and places it over the canvas, aligned with the model, for a swipe comparison. A
 * whole tablet keeps each face's photographs (`faces/<label>/photos/`): the face in view is
 * shown, under the light turned into that face's scan frame (photoFaces.js).
 *
 * Pure functions first (no DOM, no three.js); `bindPhotoPanel` at the end is the page glue.
 */

import { lightAngles, lightDirection } from './light.js';
import { faceFrames, faceInView, faceOfPart, scanToTabletDir, scanToTabletPoint, tabletToScanDir } from './photoFaces.js';

const DEG = 180 / Math.PI;

/**
 * The photograph whose light is nearest to `light` (unit vector, scan frame), and the angle
 * between the two in degrees; null when there is none.
 * @param {{photos: Array<{light: number[]}>}} index the parsed photos/index.json
 * @param {number[]} light
 */
export function nearestPhoto(index, light) {
  const photos = index?.photos ?? [];
  let best = null;
  let bestDot = -Infinity;
  const n = Math.hypot(...light) || 1;
  for (const p of photos) {
    const l = p.light;
    if (!Array.isArray(l) || l.length !== 3) continue;
    const dot = (l[0] * light[0] + l[1] * light[1] + l[2] * light[2]) / ((Math.hypot(...l) || 1) * n);
    if (dot > bestDot) {
      bestDot = dot;
      best = p;
    }
  }
  if (!best) return null;
  return { photo: best, angleDeg: Math.acos(Math.min(1, Math.max(-1, bestDot))) * DEG };
}

/**
 * CSS `matrix(a, b, c, d, e, f)` (transform-origin 0 0) that maps an image of `width` ×
 * `height` CSS pixels onto the page points `p0` (its top-left corner), `p1` (top-right) and
 * `p2` (bottom-left): an affine map, exact for an orthographic view.
 */
export function cornerMatrix(width, height, p0, p1, p2) {
  const a = (p1.x - p0.x) / width;
  const b = (p1.y - p0.y) / width;
  const c = (p2.x - p0.x) / height;
  const d = (p2.y - p0.y) / height;
  return `matrix(${[a, b, c, d, p0.x, p0.y].map((v) => +v.toFixed(4)).join(', ')})`;
}

/** The photograph's caption: which light it was taken under and how far from the current one. */
export function describePhoto({ photo, angleDeg }) {
  const what = photo.kind === 'color' ? 'Colour photograph' : 'Photograph';
  const az = Math.round(photo.azimuth_deg);
  const polar = Math.round(photo.polar_deg);
  const off = angleDeg < 0.5 ? 'the same light as the render' : `${Math.round(angleDeg)}° from the render's light`;
  return `${what} taken under the light at azimuth ${az}°, polar ${polar}° (${off}).`;
}

/** Caption of a whole tablet's photograph: the face first. */
export function describeFacePhoto(found, faceLabel) {
  return faceLabel ? `Face ${faceLabel}: ${describePhoto(found)}` : describePhoto(found);
}

const IDENTITY = { rotation: [[1, 0, 0], [0, 1, 0], [0, 0, 1]], translationMm: [0, 0, 0] };

async function fetchJson(url) {
  const response = await fetch(url, { credentials: 'same-origin' });
  if (!response.ok) return null;
  return response.json();
}

/** A parsed photos/index.json that lists at least one photograph, else null. */
function usableIndex(parsed) {
  return parsed && Array.isArray(parsed.photos) && parsed.photos.length ? parsed : null;
}

/**
 * The photograph sources of a model: a face model's own stack (one source, scan frame = world),
 * or each face of a whole tablet that kept its photographs (photoFaces.js' frames).
 */
async function photoSources(model, href) {
  const assets = model?.assets ?? {};
  const url = (name) => (assets[name] ? href(assets[name]) : null);
  if (model?.scan_id != null) {
    const index = url('photos/index.json') && usableIndex(await fetchJson(url('photos/index.json')));
    const pixelMm = Number(model?.report?.pixel_size_um) / 1000 || null;
    return index ? [{ ...IDENTITY, label: null, face: null, prefix: '', pixelMm, index }] : [];
  }
  if (!url('transforms.json')) return [];
  const frames = faceFrames(await fetchJson(url('transforms.json')), model?.report ?? {});
  const withPhotos = frames.filter((f) => assets[`${f.prefix}photos/index.json`]);
  const indexes = await Promise.all(withPhotos.map((f) => fetchJson(url(`${f.prefix}photos/index.json`)).catch(() => null)));
  return withPhotos.map((f, i) => ({ ...f, index: usableIndex(indexes[i]) })).filter((f) => f.index);
}

/**
 * Bind the photograph panel of the tablet page.
 * @param {object} viewer createViewer's API (lightWorld, project, setLight, getState, pick)
 * @param {object} els {canvas, controls, show, swipe, swipeAt, useLight, panel, img, caption, layer, layerImg}
 * @returns {{setModel(model: object|null, href: (url: string) => string): Promise<void>, changed(): void}}
 */
export function bindPhotoPanel(viewer, els) {
  let sources = []; // {index, rotation, translationMm, prefix, label, face, pixelMm}
  let base = null; // asset name → URL
  let current = null; // {photo, angleDeg, source}
  let generation = 0;

  /** The face in view: the one under the screen centre, else the one facing the camera. */
  function sourceInView() {
    if (sources.length === 1) return sources[0];
    const rect = els.canvas?.getBoundingClientRect();
    const hit = rect ? viewer.pick(rect.left + rect.width / 2, rect.top + rect.height / 2) : null;
    const under = faceOfPart(sources, hit?.part);
    if (under) return under;
    const { position, target } = viewer.getState().camera;
    const dir = target.map((t, i) => t - position[i]);
    return faceInView(sources, dir)?.face ?? sources[0];
  }

  function update() {
    if (!sources.length || !els.show.checked) {
      els.panel.hidden = true;
      els.layer.hidden = true;
      return;
    }
    const source = sourceInView();
    // The photographs' lights are in their face's scan frame: the light turned into it.
    const found = nearestPhoto(source.index, tabletToScanDir(source, viewer.lightWorld()));
    if (!found) return;
    const name = source.prefix + found.photo.file;
    const caption = describeFacePhoto(found, source.label);
    if (current?.name !== name) {
      els.img.src = base[name];
      els.layerImg.src = base[name];
    }
    els.img.alt = caption;
    current = { ...found, source, name };
    els.caption.textContent = caption;
    els.panel.dataset.face = source.label ?? '';
    els.panel.hidden = false;
    els.layer.hidden = !els.swipe.checked;
    if (els.swipe.checked) place();
  }

  /** Align the swipe layer's photograph with its face: the image corners projected to the page. */
  function place() {
    const source = current?.source;
    if (!source?.pixelMm || !Array.isArray(source.index.source_size_px)) return;
    const [w, h] = source.index.source_size_px;
    const stage = els.layer.getBoundingClientRect();
    const at = (col, row) => {
      const p = viewer.project(scanToTabletPoint(source, [col * source.pixelMm, row * source.pixelMm, 0]));
      return { x: p.x - stage.left, y: p.y - stage.top };
    };
    const [iw, ih] = source.index.size_px;
    els.layerImg.style.width = `${iw}px`;
    els.layerImg.style.height = `${ih}px`;
    els.layerImg.style.transform = cornerMatrix(iw, ih, at(-0.5, -0.5), at(w - 0.5, -0.5), at(-0.5, h - 0.5));
    els.layer.style.clipPath = `inset(0 0 0 ${Number(els.swipeAt.value)}%)`;
  }

  els.show.addEventListener('change', update);
  els.swipe.addEventListener('change', () => {
    // The photograph is the camera's straight view of its face: compare it in that view
    // (a face model's only view; on a whole tablet the canonical view of the face in view).
    if (els.swipe.checked) {
      const face = sources.length ? sourceInView().face : null;
      const views = viewer.views ?? [];
      viewer.setView(face && views.includes(face) ? face : 'obverse');
    }
    update();
  });
  els.swipeAt.addEventListener('input', () => place());
  els.useLight.addEventListener('click', () => {
    if (!current) return;
    const { photo, source } = current;
    if (!source.label) {
      viewer.setLight({ follow: false, azimuthDeg: photo.azimuth_deg, polarDeg: photo.polar_deg });
      return;
    }
    // The photograph's light, from its face's scan frame into the tablet frame.
    const world = scanToTabletDir(source, lightDirection(photo.azimuth_deg, photo.polar_deg));
    viewer.setLight({ follow: false, ...lightAngles(world) });
  });

  return {
    async setModel(model, href) {
      const mine = ++generation;
      sources = [];
      current = null;
      els.controls.hidden = true;
      update();
      const found = await photoSources(model, href);
      if (mine !== generation || !found.length) return; // another model was opened meanwhile
      base = Object.fromEntries(Object.entries(model.assets ?? {}).map(([k, v]) => [k, href(v)]));
      sources = found;
      els.controls.hidden = false;
      update();
    },
    changed: update,
  };
}
