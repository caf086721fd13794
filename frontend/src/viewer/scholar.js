/**
 * The reader's tools of the tablet page (the "Read" panel): trust on screen (the trust
 * mode's layer and legend, the ± of distances and profiles), unsharp masking and the lens,
 * the right light for a region with its eight raking lights, and sections. Binds DOM
 * elements (tablet.html) to a viewer; the algorithms are the pure modules trust.js,
 * enhance.js, rightLight.js and section.js.
 */
import * as THREE from 'three';
import { fetchBytes } from './assets.js';
import { LENS_MODES } from './enhance.js';
import { createPicker, pixelSizeFromMesh } from './measure.js';
import { parseNpy } from './npy.js';
import { bestLight, rakingSet, shadeCrop } from './rightLight.js';
import { planeToFace, pointsOnOneFace, transformPoint } from './faceGrids.js';
import { boxCorners, chainSegments, gridSectionSegments, planeRowSpan, planeThroughLine, sectionSegments, sectionSvg, toPlane } from './section.js';
import { distanceUncertaintyAxesMm, distanceUncertaintyMm, sigmaAlongLine, sigmaAt, trustLegend } from './trust.js';

const $ = (id) => document.getElementById(id);
/** Largest crop (texels on a side) the right light reads; larger regions are downsampled. */
const MAX_CROP_PX = 192;
const SECTION_COLOUR = 0x00e5ff;
/** What a section was cut from, as the readout and the SVG's note say it. */
const SOURCE_TEXT = Object.freeze({
  heights: 'full-resolution heights',
  mesh: 'decimated mesh',
  'heights and mesh': 'full-resolution heights (the decimated mesh for faces without them)',
});

/** Float32Arrays end to end. */
function concat(parts) {
  const out = new Float32Array(parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) {
    out.set(p, at);
    at += p.length;
  }
  return out;
}

/**
 * @param {ReturnType<import('./viewer.js').createViewer>} viewer
 * @param {{assetUrl: (name: string) => string | null, getPixelSizeUm: () => number | null,
 *   getHeightUrl?: () => string | null, facePixelSizeUm?: (label: string) => number | null,
 *   baseName: () => string, describe?: () => object}} context
 */
export function bindScholarTools(viewer, context) {
  const canvas = $('viewer');

  // --- trust: the layer, its legend, and σ_h for the ± of measurements ---------------------
  $('trust-layer').addEventListener('change', (e) => viewer.setShading({ trustLayer: e.target.value }));

  function drawTrustLegend() {
    const box = $('trust-legend');
    const s = viewer.shading;
    const lensTrust = viewer.enhance.lens?.mode === 'trust';
    const trust = viewer.model?.assets.trust;
    if (!trust || (s.mode !== 'trust' && !lensTrust)) {
      box.hidden = true;
      return;
    }
    const spec = trustLegend(s.trustLayer ?? 'sources', trust.meta ?? {});
    const key = JSON.stringify(spec);
    box.hidden = false;
    if (box.dataset.key === key) return;
    box.dataset.key = key;
    const what = document.createElement('div');
    what.className = 'what';
    if (spec.kind === 'classes') {
      const ul = document.createElement('ul');
      for (const e of spec.entries) {
        const li = document.createElement('li');
        const sw = document.createElement('span');
        sw.className = 'swatch';
        sw.style.background = `rgb(${e.rgb.map((v) => Math.round(v * 255)).join(',')})`;
        const share = e.fraction != null ? ` (${(100 * e.fraction).toFixed(e.fraction < 0.01 ? 2 : 0)} %)` : '';
        li.append(sw, `${e.label}${share}`);
        ul.append(li);
      }
      what.textContent = 'where the heights come from';
      box.replaceChildren(ul, what);
    } else {
      const ramp = document.createElement('div');
      ramp.className = 'ramp sequential';
      const ends = document.createElement('div');
      ends.className = 'ends';
      for (const t of [spec.lo, spec.hi]) {
        const span = document.createElement('span');
        span.textContent = t;
        ends.append(span);
      }
      what.textContent = spec.what;
      box.replaceChildren(ramp, ends, what);
    }
  }

  /**
   * A loader of one full-resolution grid of the model (an .npy asset), cached by URL: the
   * values under `key`, its shape and the pixel size (the model's, else from the mesh).
   */
  function npyGridLoader(getUrl, key) {
    let cached = null; // {url, promise}
    const load = () => {
      const url = getUrl();
      if (!url) return Promise.resolve(null);
      if (cached?.url !== url) {
        cached = {
          url,
          promise: fetchBytes(url).then((buf) => {
            const { shape, data } = parseNpy(buf);
            // The report's, else a streamed face's tiles index, else fitted on the mesh.
            let pixelSizeUm = context.getPixelSizeUm() ?? viewer.model.tiles?.heights?.pixelSizeUm ?? null;
            if (!pixelSizeUm) {
              const g = viewer.model.mesh.geometry;
              pixelSizeUm = pixelSizeFromMesh(g.attributes.position.array, g.attributes.uv.array, shape[1]);
            }
            return { [key]: data, rows: shape[0], cols: shape[1], pixelSizeUm };
          }),
        };
      }
      return cached.promise;
    };
    load.reset = () => {
      cached = null;
    };
    return load;
  }
  const loadSigma = npyGridLoader(() => context.assetUrl('uncertainty_um.npy'), 'sigmaUm');
  // A whole tablet: each face's own σ_h grid (faces/<label>/uncertainty_um.npy) and pixel
  // size (the registration's report, else the face's trust.json).
  const faceGrids = new Map(); // url → Promise<grid>
  function faceGrid(face, name) {
    const url = context.assetUrl(face.assets[name]);
    if (!url) return Promise.resolve(null);
    if (!faceGrids.has(url)) {
      faceGrids.set(
        url,
        Promise.all([fetchBytes(url), facePixelSize(face)]).then(([buf, pixelSizeUm]) => {
          const { shape, data } = parseNpy(buf);
          if (!pixelSizeUm) throw new Error(`the pixel size of the face ${face.name} is unknown`);
          const values = name === 'uncertainty' ? { sigmaUm: data } : { heightUm: data };
          return { ...values, rows: shape[0], cols: shape[1], pixelSizeUm };
        }),
      );
    }
    return faceGrids.get(url);
  }
  async function facePixelSize(face) {
    if (face.pixelSizeUm) return face.pixelSizeUm; // a streamed face's tiles index
    const fromReport = context.facePixelSizeUm?.(face.name);
    if (fromReport) return fromReport;
    const url = context.assetUrl(face.assets.trustMeta);
    if (!url) return null;
    const meta = JSON.parse(new TextDecoder().decode(await fetchBytes(url)));
    return Number(meta.pixel_size_um) || null;
  }
  const faces = () => viewer.model?.assets.faces ?? [];
  const uncertainty = {
    /** ± (mm) of the distance between two points, or null without an uncertainty map. */
    async distance(points) {
      if (faces().length) return wholeTabletDistance(points);
      const g = await loadSigma();
      if (!g) return null;
      const [a, b] = points;
      const pm = distanceUncertaintyMm(a, b, sigmaAt(g, a), sigmaAt(g, b), g.pixelSizeUm);
      return Number.isFinite(pm) ? pm : null;
    },
    /** σ_h (µm) at each sample of a profile, or null. */
    async profile(profile, points) {
      if (faces().length) {
        // The profile's own face (ui.js reads its heights the same way).
        const on = pointsOnOneFace(points, (p) => viewer.faceOfPoint(p), faces());
        const g = await faceGrid(faces()[on.face], 'uncertainty');
        return g ? sigmaAlongLine(g, on.points[0], on.points[1], profile.heightUm.length) : null;
      }
      const g = await loadSigma();
      return g ? sigmaAlongLine(g, points[0], points[1], profile.heightUm.length) : null;
    },
  };
  /** ± of a distance on a whole tablet: each end's σ_h on its own face, along that face's
   * viewing axis (trust.js' distanceUncertaintyAxesMm). */
  async function wholeTabletDistance(points) {
    const ends = await Promise.all(
      points.map(async (p) => {
        const i = viewer.faceOfPoint(p);
        const face = faces()[i];
        // (a streamed face's frame is known once one of its tiles has loaded)
        const g = face?.toModel ? await faceGrid(face, 'uncertainty') : null;
        if (!g) return null;
        // The face's viewing axis (scan-frame z) in the model frame: column 2 of its transform.
        const m = face.toModel;
        return { sigmaUm: sigmaAt(g, transformPoint(face.toFace, p)), axis: [m[8], m[9], m[10]], pixelSizeUm: g.pixelSizeUm };
      }),
    );
    if (ends.some((e) => !e)) return null;
    const pm = distanceUncertaintyAxesMm(points[0], points[1], ends);
    return Number.isFinite(pm) ? pm : null;
  }

  // --- unsharp masking and the lens ---------------------------------------------------------
  const sliders = { 'unsharp-normals': 'normalUnsharp', 'unsharp-luma': 'lumaUnsharp', 'unsharp-radius': 'radiusPx' };
  for (const [id, key] of Object.entries(sliders)) {
    $(id).addEventListener('input', (e) => viewer.setEnhance({ [key]: Number(e.target.value) }));
  }
  const ring = $('lens-ring');
  function setLens(on) {
    if (!on) return viewer.setEnhance({ lens: null });
    const w = canvas.clientWidth || 1;
    const h = canvas.clientHeight || 1;
    const old = viewer.enhance.lens;
    viewer.setEnhance({
      lens: { mode: $('lens-mode').value, x: old?.x ?? w / 2, y: old?.y ?? h / 2, radius: old?.radius ?? Math.min(w, h) / 5 },
    });
  }
  $('lens-on').addEventListener('change', (e) => setLens(e.target.checked));
  $('lens-mode').addEventListener('change', () => $('lens-on').checked && setLens(true));
  let drag = null;
  ring.addEventListener('pointerdown', (e) => {
    const lens = viewer.enhance.lens;
    if (!lens) return;
    drag = { id: e.pointerId, dx: e.clientX - lens.x, dy: e.clientY - lens.y };
    ring.setPointerCapture(e.pointerId);
    e.preventDefault();
  });
  ring.addEventListener('pointermove', (e) => {
    if (!drag || e.pointerId !== drag.id) return;
    const lens = viewer.enhance.lens;
    viewer.setEnhance({ lens: { ...lens, x: e.clientX - drag.dx, y: e.clientY - drag.dy } });
  });
  const endDrag = () => {
    drag = null;
  };
  ring.addEventListener('pointerup', endDrag);
  ring.addEventListener('pointercancel', endDrag);
  ring.addEventListener(
    'wheel',
    (e) => {
      const lens = viewer.enhance.lens;
      if (!lens) return;
      e.preventDefault();
      const radius = Math.min(Math.max(lens.radius * (e.deltaY > 0 ? 0.9 : 1.1), 12), 2000);
      viewer.setEnhance({ lens: { ...lens, radius } });
    },
    { passive: false },
  );
  function placeRing() {
    const lens = viewer.enhance.lens;
    ring.hidden = !lens || !viewer.model;
    if (ring.hidden) return;
    // Lens x, y are relative to the canvas' top-left; the ring sits in the same stage.
    Object.assign(ring.style, {
      left: `${canvas.offsetLeft + lens.x - lens.radius}px`,
      top: `${canvas.offsetTop + lens.y - lens.radius}px`,
      width: `${2 * lens.radius}px`,
      height: `${2 * lens.radius}px`,
    });
    ring.dataset.mode = lens.mode;
  }

  // --- tools that pick on the model: best light (one click), section (two) ------------------
  let tool = null; // 'light' | 'section' | null
  let downAt = null;
  const onDown = (e) => {
    if (tool === 'light' && e.button === 0) downAt = [e.clientX, e.clientY];
  };
  const onUp = (e) => {
    if (tool !== 'light' || !downAt) return;
    const moved = Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]);
    downAt = null;
    if (moved <= 4) pickRegion(e.clientX, e.clientY);
  };
  canvas.addEventListener('pointerdown', onDown);
  canvas.addEventListener('pointerup', onUp);
  const sectionPicker = createPicker(viewer, canvas, { onDone: (points) => cutSection(points) });

  function setTool(next) {
    tool = tool === next ? null : next;
    // A streamed model's section cuts its full-resolution heights by Range reads (a face's
    // rows, or each face's of a whole tablet); one without them (no height.f32) is refused.
    const streamed = viewer.model?.tiles;
    const refused = tool === 'section' && streamed && !streamed.heights && streamed.kind !== 'tablet' ? tool : null;
    if (refused) tool = null;
    $('best-light').setAttribute('aria-pressed', String(tool === 'light'));
    $('section').setAttribute('aria-pressed', String(tool === 'section'));
    canvas.classList.toggle('picking', Boolean(tool));
    if (tool === 'section') sectionPicker.start();
    else sectionPicker.stop();
    corner = null;
    if (tool === 'light') {
      say($('region-shape').value === 'rectangle' ? 'Click two opposite corners of the region to light.' : 'Click the middle of the region to light.');
    }
    else if (tool === 'section') say('Click the two ends of the section line.');
    if (tool) canvas.classList.add('picking');
    if (refused) say(`Section: this streamed model has no full-resolution heights (tiles/height.f32) to cut.`);
  }
  function say(text) {
    $('readout').textContent = text;
  }
  $('best-light').addEventListener('click', () => setTool('light'));
  $('section').addEventListener('click', () => setTool('section'));

  /**
   * The normal map (and albedo) of what was hit, its rotation to the model frame (row-major),
   * and `same(other)`: whether another hit is on the same map. A streamed model: the hit
   * tile's own maps (its uv span them; at full zoom they are the full-resolution normals); a
   * whole tablet: the hit face's (hit.part is its name); else the model's.
   */
  function mapsOfHit(hit) {
    const a = viewer.model.assets;
    const tileMaterial = viewer.model.tiles?.has(hit.object?.material) ? hit.object.material : null;
    if (tileMaterial) {
      const u = tileMaterial.uniforms;
      return {
        normals: u.uHasNormalMap.value ? u.uNormalMap.value.image : null,
        albedo: u.uHasAlbedo.value ? u.uAlbedoMap.value.image : null,
        rotation: u.uObjectToWorld.value.clone().transpose().elements,
        same: (other) => other?.object === hit.object,
        texelUm: (context.getPixelSizeUm() ?? viewer.model.tiles.heights?.pixelSizeUm ?? a.faces?.find((f) => f.name === hit.part)?.pixelSizeUm ?? NaN) *
          (tileMaterial.userData.tile?.pixel_step ?? NaN),
      };
    }
    const f = a.faces?.length && hit.part != null ? a.faces.find((face) => face.name === hit.part) : null;
    const same = (other) => (other?.part ?? null) === (hit.part ?? null);
    if (f) {
      const texelUm = context.facePixelSizeUm?.(f.name) ?? context.getPixelSizeUm();
      return { normals: f.normals?.image, albedo: f.albedo?.image ?? null, rotation: f.rotation.clone().transpose().elements, same, texelUm };
    }
    return { normals: a.normals?.image, albedo: a.albedo?.image ?? null, rotation: null, same, texelUm: context.getPixelSizeUm() };
  }

  function crop(image, sx, sy, sw, sh, ow, oh) {
    const c = new OffscreenCanvas(ow, oh);
    const ctx = c.getContext('2d', { willReadFrequently: true });
    ctx.imageSmoothingEnabled = true;
    ctx.drawImage(image, sx, sy, sw, sh, 0, 0, ow, oh);
    return ctx.getImageData(0, 0, ow, oh).data;
  }

  let corner = null; // a rectangle's first corner: {hit, maps}
  function pickRegion(clientX, clientY) {
    const hit = viewer.pick(clientX, clientY);
    if (!hit?.uv) return say('Best light: click on the tablet.');
    const maps = mapsOfHit(hit);
    if (!maps.normals) return say('Best light: this model (or face) has no normals.png to compute it from.');
    const W = maps.normals.width;
    const H = maps.normals.height;
    if ($('region-shape').value === 'rectangle') {
      if (!corner || !corner.maps.same(hit)) {
        corner = { hit, maps };
        viewer.setMarks([hit.point]);
        return say('Best light: click the opposite corner of the rectangle.');
      }
      const a = corner.hit;
      corner = null;
      const [u0, u1] = [Math.min(a.uv[0], hit.uv[0]) * W, Math.max(a.uv[0], hit.uv[0]) * W];
      const [v0, v1] = [Math.min(a.uv[1], hit.uv[1]) * H, Math.max(a.uv[1], hit.uv[1]) * H];
      const sw = Math.max(u1 - u0, 3);
      const sh = Math.max(v1 - v0, 3);
      const k = Math.min(1, MAX_CROP_PX / Math.max(sw, sh));
      return lightRegion({ maps, sx: u0, sy: v0, sw, sh, ow: Math.max(3, Math.round(sw * k)), oh: Math.max(3, Math.round(sh * k)), circle: false, marks: [a.point, hit.point] });
    }
    // Texels per mm at the point: from a second pick a few pixels away (any model, any face).
    const probe = viewer.pick(clientX + 6, clientY) ?? viewer.pick(clientX - 6, clientY);
    let texPerMm = null;
    if (probe?.uv && maps.same(probe)) {
      const dmm = Math.hypot(...probe.point.map((v, k) => v - hit.point[k]));
      const dtex = Math.hypot((probe.uv[0] - hit.uv[0]) * W, (probe.uv[1] - hit.uv[1]) * H);
      if (dmm > 0 && dtex > 0) texPerMm = dtex / dmm;
    }
    if (!texPerMm) texPerMm = maps.texelUm > 0 ? 1000 / maps.texelUm : null;
    if (!texPerMm) return say('Best light: cannot tell the scale here; click nearer the middle of a face.');
    const radiusMm = Math.min(Math.max(Number($('region-mm').value) || 3, 0.2), 50);
    const rTex = Math.max(3, radiusMm * texPerMm);
    const size = Math.ceil(2 * rTex);
    const out = Math.min(size, MAX_CROP_PX);
    const sx = hit.uv[0] * W - rTex;
    const sy = hit.uv[1] * H - rTex;
    return lightRegion({ maps, sx, sy, sw: size, sh: size, ow: out, oh: out, circle: true, marks: [hit.point] });
  }

  let stripLights = [];
  /** The best light for a crop of the normal map, its strip of eight, and apply the best. */
  function lightRegion({ maps, sx, sy, sw, sh, ow, oh, circle, marks }) {
    const nrm = crop(maps.normals, sx, sy, sw, sh, ow, oh);
    if (circle) {
      // Outside the circle: no normal (alpha 0), so it is neither searched nor shaded.
      for (let y = 0; y < oh; y++) {
        for (let x = 0; x < ow; x++) {
          if (Math.hypot(x + 0.5 - ow / 2, y + 0.5 - oh / 2) > ow / 2) nrm[4 * (y * ow + x) + 3] = 0;
        }
      }
    }
    const normals = modelNormals(nrm, maps.rotation);
    if (normals.length < 9) return say('Best light: too few normals there.');
    const best = bestLight(normals);
    const albedo = maps.albedo ? crop(maps.albedo, sx, sy, sw, sh, ow, oh) : null;
    stripLights = rakingSet(best.basis, best.elevationDeg, best.localAzimuthDeg);
    const cells = stripLights.map((l, i) => {
      const fig = document.createElement('figure');
      if (i === 0) fig.className = 'best';
      const c = document.createElement('canvas');
      c.width = ow;
      c.height = oh;
      c.dataset.azimuth = l.azimuthDeg.toFixed(3);
      c.dataset.polar = l.polarDeg.toFixed(3);
      c.title = `Apply: azimuth ${l.azimuthDeg.toFixed(0)}°, elevation ${l.elevationDeg}° over the region`;
      const px = shadeCrop(nrm, albedo, l.direction, { rotation: maps.rotation });
      c.getContext('2d').putImageData(new ImageData(px, ow, oh), 0, 0);
      c.addEventListener('click', () => applyLight(l));
      const cap = document.createElement('figcaption');
      cap.textContent = `${Math.round(l.azimuthDeg) % 360}°${i === 0 ? ' ★' : ''}`;
      fig.append(c, cap);
      return fig;
    });
    $('light-strip-cells').replaceChildren(...cells);
    $('light-strip-best').textContent =
      `most contrast: azimuth ${best.azimuthDeg.toFixed(0)}°, polar ${best.polarDeg.toFixed(0)}° ` +
      `(${best.elevationDeg}° over the region)`;
    const strip = $('light-strip');
    strip.hidden = false;
    strip.dataset.azimuth = best.azimuthDeg.toFixed(3);
    strip.dataset.polar = best.polarDeg.toFixed(3);
    strip.dataset.contrast = String(best.contrast);
    strip.dataset.normals = String(normals.length / 3);
    viewer.setMarks(marks);
    applyLight(stripLights[0]);
    say(`Best light: azimuth ${best.azimuthDeg.toFixed(0)}°, polar ${best.polarDeg.toFixed(0)}° (click a raking light to change).`);
  }

  function applyLight(l) {
    // The search's angles are in the model's frame: the light is fixed to the tablet.
    viewer.setLight({ follow: false, azimuthDeg: l.azimuthDeg, polarDeg: l.polarDeg });
  }
  $('light-strip-close').addEventListener('click', () => {
    $('light-strip').hidden = true;
  });

  // --- sections ------------------------------------------------------------------------
  let section = null; // {remove, object, svg}
  function clearSection() {
    if (!section) return;
    section.remove();
    section.object.geometry.dispose();
    section.object.material.dispose();
    section = null;
  }
  /** A face model's full-resolution heights (height.npy), cached by URL. */
  const loadModelHeights = npyGridLoader(() => context.getHeightUrl?.(), 'heightUm');

  /**
   * The plane's cut of the finest surface at hand (section.js): a face model's height.npy, a
   * streamed face's rows between the two ends (heightRows.js Range reads, as profiles do), a
   * whole tablet's faces/<label>/height.npy for each shown face (the mesh for a face without
   * one), else the decimated mesh. {segments, source: 'heights' | 'mesh' | 'heights and mesh',
   * pixels: cut grid cells' pixel count}.
   */
  async function cutFinest(plane, points) {
    const model = viewer.model;
    const streamed = model.tiles?.heights;
    if (model.tiles?.kind === 'tablet') return cutStreamedTablet(plane);
    if (streamed) {
      const s = streamed.pixelSizeUm;
      const part = await streamed.reader.gridForSegment(points[0], points[1], s);
      const row0 = Math.round(((points[0][1] - part.start[1]) * 1000) / s);
      return { segments: gridSectionSegments(part.grid, plane, { row0 }), source: 'heights', rows: part.grid.rows };
    }
    const g = model.mesh.geometry;
    const mats = Array.isArray(model.mesh.material) ? model.mesh.material : null;
    const fs = faces();
    if (fs.length && mats && g.groups.length) {
      // A whole tablet: only its shown faces are cut, each on its own grid.
      const shown = g.groups.map((gr, i) => [gr, i]).filter(([gr]) => mats[gr.materialIndex]?.visible !== false);
      const parts = [];
      const meshRanges = [];
      for (const [gr, i] of shown) {
        const face = fs[i];
        const grid = face?.assets.height ? await faceGrid(face, 'height') : null;
        if (grid) parts.push(gridSectionSegments(grid, planeToFace(plane, face.toModel, face.toFace), { toModel: face.toModel }));
        else meshRanges.push(gr);
      }
      if (meshRanges.length) parts.push(sectionSegments(g.attributes.position.array, g.index?.array ?? null, plane, meshRanges));
      const segments = concat(parts);
      const source = meshRanges.length === shown.length ? 'mesh' : meshRanges.length ? 'heights and mesh' : 'heights';
      return { segments, source };
    }
    const grid = await loadModelHeights();
    if (grid) return { segments: gridSectionSegments(grid, plane), source: 'heights' };
    const ranges = mats && g.groups.length ? g.groups.filter((gr) => mats[gr.materialIndex]?.visible !== false) : null;
    return { segments: sectionSegments(g.attributes.position.array, g.index?.array ?? null, plane, ranges), source: 'mesh' };
  }

  /**
   * A streamed whole tablet's cut: each shown face's full-resolution heights (its height.f32),
   * only the rows where the plane can meet the tablet (section.js planeRowSpan: the plane
   * through the tablet's box, taken into the face's scan frame), cut in that frame and the
   * outline taken back into the tablet's, as model.glb's faces are cut from their height.npy.
   */
  async function cutStreamedTablet(plane) {
    const model = viewer.model;
    const parts = [];
    let rowsRead = 0;
    for (const face of faces()) {
      const rows = face.heights?.();
      if (!rows || !face.toFace || (model.parts && !model.parts.isVisible(face.name))) continue;
      const p = planeToFace(plane, face.toModel, face.toFace);
      const corners = boxCorners(model.box).map((c) => transformPoint(face.toFace, c));
      const span = planeRowSpan(p, corners, rows.pixelSizeUm, rows.reader.rows);
      if (!span) continue;
      const [r0, r1] = span;
      const heightUm = await rows.reader.readRows(r0, r1);
      const grid = { heightUm, rows: r1 - r0, cols: rows.reader.cols, pixelSizeUm: rows.pixelSizeUm };
      parts.push(gridSectionSegments(grid, p, { row0: r0, toModel: face.toModel }));
      rowsRead += r1 - r0;
    }
    if (!rowsRead) throw new Error('no shown face of this streamed tablet has full-resolution heights loaded here yet');
    return { segments: concat(parts), source: 'heights', rows: rowsRead };
  }

  let cutting = 0; // the latest cut (an older one finishing late is dropped)
  async function cutSection(points) {
    clearSection();
    const dir = viewer.getCamera().getWorldDirection(new THREE.Vector3()).toArray();
    let plane;
    try {
      plane = planeThroughLine(points[0], points[1], dir);
    } catch (err) {
      return say(`Section: ${err.message}.`);
    }
    const ticket = ++cutting;
    let cut;
    try {
      say('Section: cutting…');
      cut = await cutFinest(plane, points);
    } catch (err) {
      return say(`Section: ${err.message}`);
    }
    if (ticket !== cutting || !viewer.model) return;
    const segs = cut.segments;
    if (!segs.length) return say('Section: the plane does not cut the model.');
    const geometry = new THREE.BufferGeometry();
    geometry.setAttribute('position', new THREE.BufferAttribute(segs, 3));
    const object = new THREE.LineSegments(
      geometry,
      new THREE.LineBasicMaterial({ color: SECTION_COLOUR, depthTest: false, transparent: true }),
    );
    object.renderOrder = 12;
    const lines = toPlane(chainSegments(segs), plane);
    const about = context.describe?.() ?? {};
    const svg = sectionSvg(lines, {
      title: `Section of ${about.tablet ?? 'the tablet'}${about.modelId != null ? `, model ${about.modelId} version ${about.modelVersion}` : ''}`,
      note: `Plane through (${points[0].map((v) => v.toFixed(3)).join(', ')}) and (${points[1].map((v) => v.toFixed(3)).join(', ')}) mm, holding the viewing direction; cut from the ${SOURCE_TEXT[cut.source]}; horizontal: along the line, vertical: depth as seen; 1 unit = 1 mm.${about.licence ? ` Licence: ${about.licence}.` : ''}`,
    });
    section = { remove: viewer.addOverlay(object), object, svg };
    const doc = new DOMParser().parseFromString(svg, 'image/svg+xml').documentElement;
    $('section-chart').replaceChildren(document.importNode(doc, true));
    const [w, d] = extent(lines);
    $('section-readout').textContent = `${lines.length} outline${lines.length === 1 ? '' : 's'}, ${w.toFixed(2)} × ${d.toFixed(2)} mm, from the ${SOURCE_TEXT[cut.source]}`;
    $('section-panel').hidden = false;
    $('section-panel').dataset.source = cut.source;
    $('section-panel').dataset.widthMm = String(w);
    $('section-panel').dataset.depthMm = String(d);
    say(`Section: ${w.toFixed(2)} mm along the line, ${d.toFixed(2)} mm deep.`);
  }
  $('section-svg').addEventListener('click', () => {
    if (!section) return;
    const a = document.createElement('a');
    a.href = URL.createObjectURL(new Blob([section.svg], { type: 'image/svg+xml' }));
    a.download = `${context.baseName()}-section.svg`;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 10000);
  });
  $('section-close').addEventListener('click', () => {
    $('section-panel').hidden = true;
    clearSection();
  });

  // --- reflect the viewer's state -----------------------------------------------------------
  let scheduled = false;
  function sync() {
    scheduled = false;
    const s = viewer.shading;
    $('trust-row').hidden = s.mode !== 'trust';
    $('trust-layer').value = s.trustLayer ?? 'sources';
    const e = viewer.enhance;
    $('unsharp-normals').value = String(e.normalUnsharp);
    $('unsharp-luma').value = String(e.lumaUnsharp);
    $('unsharp-radius').value = String(e.radiusPx);
    $('lens-on').checked = Boolean(e.lens);
    if (e.lens) $('lens-mode').value = e.lens.mode;
    canvas.dataset.lens = e.lens ? e.lens.mode : '';
    drawTrustLegend();
    placeRing();
  }

  return {
    uncertainty,
    /** Call from the viewer's onChange. */
    changed() {
      if (scheduled) return;
      scheduled = true;
      queueMicrotask(sync);
    },
    /** Keyboard actions of keyboard.js this panel owns; true when handled. */
    onAction(verb) {
      if (!viewer.model) return false;
      if (verb === 'best-light') setTool('light');
      else if (verb === 'section') setTool('section');
      else if (verb === 'lens') setLens(!viewer.enhance.lens);
      else if (verb === 'cancel') {
        if (tool) setTool(tool);
        $('light-strip').hidden = true;
        return false; // the page's own tools close too
      } else return false;
      return true;
    },
    /** A new model: tools off, panels closed, caches dropped. */
    stop() {
      if (tool) setTool(tool);
      clearSection();
      $('section-panel').hidden = true;
      $('light-strip').hidden = true;
      loadSigma.reset();
      loadModelHeights.reset();
      faceGrids.clear();
    },
    /** For tests: the lens modes offered. */
    lensModes: LENS_MODES,
    dispose() {
      canvas.removeEventListener('pointerdown', onDown);
      canvas.removeEventListener('pointerup', onUp);
      sectionPicker.dispose();
      clearSection();
    },
  };
}

/** Normals of an RGBA crop of normals.png (3N, alpha > 0), turned into the model frame. */
function modelNormals(rgba, rotation) {
  const out = [];
  for (let i = 0; i < rgba.length; i += 4) {
    if (rgba[i + 3] === 0) continue;
    let n = [(rgba[i] / 255) * 2 - 1, (rgba[i + 1] / 255) * 2 - 1, (rgba[i + 2] / 255) * 2 - 1];
    const len = Math.hypot(...n);
    if (len < 0.5) continue; // off the tablet (black) or a blend with it
    n = n.map((v) => v / len);
    if (rotation) n = [0, 1, 2].map((r) => rotation[3 * r] * n[0] + rotation[3 * r + 1] * n[1] + rotation[3 * r + 2] * n[2]);
    out.push(...n);
  }
  return Float32Array.from(out);
}

function extent(lines) {
  let [x0, y0, x1, y1] = [Infinity, Infinity, -Infinity, -Infinity];
  for (const [x, y] of lines.flat()) {
    x0 = Math.min(x0, x);
    x1 = Math.max(x1, x);
    y0 = Math.min(y0, y);
    y1 = Math.max(y1, y);
  }
  return [x1 - x0, y1 - y0];
}
