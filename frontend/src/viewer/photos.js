/**
 * The photograph beside the render: the worker keeps every light's photograph of a scan
 * (`photos/index.json`, worker/photos.py); this picks the one taken nearest to the viewer's
 * light, and places it over the canvas, aligned with the model, for a swipe comparison.
 *
 * Pure functions first (no DOM, no three.js); `bindPhotoPanel` at the end is the page glue.
 */

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

/**
 * Bind the photograph panel of the tablet page.
 * @param {object} viewer createViewer's API (lightWorld, project, setLight, getState)
 * @param {object} els {controls, show, swipe, swipeAt, useLight, panel, img, caption, layer, layerImg}
 * @returns {{setModel(model: object|null, href: (url: string) => string): Promise<void>, changed(): void}}
 */
export function bindPhotoPanel(viewer, els) {
  let index = null;
  let base = null; // asset name → URL
  let current = null;
  let sourceSize = null;
  let pixelMm = null;

  function update() {
    if (!index || !els.show.checked) {
      els.panel.hidden = true;
      els.layer.hidden = true;
      return;
    }
    const found = nearestPhoto(index, viewer.lightWorld());
    if (!found) return;
    if (current?.photo.file !== found.photo.file) {
      els.img.src = base[found.photo.file];
      els.layerImg.src = base[found.photo.file];
      els.img.alt = describePhoto(found);
    }
    current = found;
    els.caption.textContent = describePhoto(found);
    els.panel.hidden = false;
    els.layer.hidden = !els.swipe.checked;
    if (els.swipe.checked) place();
  }

  /** Align the swipe layer's photograph with the model: its corners projected to the page. */
  function place() {
    if (!sourceSize || !pixelMm) return;
    const [w, h] = sourceSize;
    const stage = els.layer.getBoundingClientRect();
    const at = (col, row) => {
      const p = viewer.project([col * pixelMm, row * pixelMm, 0]);
      return { x: p.x - stage.left, y: p.y - stage.top };
    };
    const [iw, ih] = index.size_px;
    els.layerImg.style.width = `${iw}px`;
    els.layerImg.style.height = `${ih}px`;
    els.layerImg.style.transform = cornerMatrix(iw, ih, at(-0.5, -0.5), at(w - 0.5, -0.5), at(-0.5, h - 0.5));
    els.layer.style.clipPath = `inset(0 0 0 ${Number(els.swipeAt.value)}%)`;
  }

  els.show.addEventListener('change', update);
  els.swipe.addEventListener('change', () => {
    // The photograph is the camera's straight view of the face: compare it in that view.
    if (els.swipe.checked) viewer.setView('obverse');
    update();
  });
  els.swipeAt.addEventListener('input', () => place());
  els.useLight.addEventListener('click', () => {
    if (!current) return;
    viewer.setLight({ follow: false, azimuthDeg: current.photo.azimuth_deg, polarDeg: current.photo.polar_deg });
  });

  return {
    async setModel(model, href) {
      index = null;
      current = null;
      els.controls.hidden = true;
      update();
      const assets = model?.assets ?? {};
      // Face models only: a whole tablet's faces keep their photographs in their own scans.
      if (!assets['photos/index.json'] || model?.scan_id == null) return;
      const response = await fetch(href(assets['photos/index.json']), { credentials: 'same-origin' });
      if (!response.ok) return;
      const parsed = await response.json();
      if (!Array.isArray(parsed.photos) || !parsed.photos.length) return;
      base = Object.fromEntries(Object.entries(assets).map(([k, v]) => [k, href(v)]));
      index = parsed;
      sourceSize = parsed.source_size_px;
      pixelMm = Number(model?.report?.pixel_size_um) / 1000 || null;
      els.controls.hidden = false;
      update();
    },
    changed: update,
  };
}
