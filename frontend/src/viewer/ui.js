/**
 * The viewer's controls on the tablet page: light widget and sliders, shading, views,
 * measuring, screenshot, permalink and keyboard shortcuts. Binds DOM elements (by id, see
 * tablet.html) to a viewer; owns no state of its own beyond what the viewer reports.
 */
import { profileChart } from './chart.js';
import { actionForKey, SHORTCUTS } from './keyboard.js';
import { clampPolar, compassLabel, RAKING_PRESETS, wrapAzimuth } from './light.js';
import { createLightWidget } from './lightWidget.js';
import { createPicker, distanceMm, pixelSizeFromMesh } from './measure.js';
import { annotateScreenshot, shotMmPerPixel } from './shot.js';
import { encodeViewState } from './permalink.js';
import { niceStep, profileToCsv, sampleProfile } from './profile.js';
import { parseNpy } from './npy.js';
import { fetchBytes } from './assets.js';
import { unavailableViewReason } from './views.js';
import { fmtUm, formatDistance, profileUncertainty } from './trust.js';
import { describeEnhance } from './enhance.js';
import { unavailableModeReason } from './modes.js';
import { pointsOnOneFace, transformPoint } from './faceGrids.js';

const $ = (id) => document.getElementById(id);

/**
 * @param {ReturnType<import('./viewer.js').createViewer>} viewer
 * @param {{getHeightUrl: () => string | null, getPixelSizeUm: () => number | null,
 *   baseName: () => string}} context
 */
export function bindViewerUi(viewer, context) {
  const canvas = $('viewer');
  const widget = createLightWidget($('light-widget'), {
    // The disc is the hemisphere facing the camera: its angles are relative to the view.
    onInput: (angles) => viewer.setLightFromView(angles),
  });

  // --- light ------------------------------------------------------------------------------
  const raking = $('raking');
  RAKING_PRESETS.forEach((p, i) => {
    const b = document.createElement('button');
    b.type = 'button';
    b.textContent = String(i + 1);
    b.title = `Raking light from the ${p.label} of the view (key ${i + 1})`;
    b.setAttribute('aria-label', b.title);
    b.addEventListener('click', () => viewer.setLightFromView({ azimuthDeg: p.azimuthDeg, polarDeg: p.polarDeg }));
    raking.append(b);
  });
  $('light-follow').addEventListener('change', (e) => viewer.setLight({ follow: e.target.checked }));
  for (const id of ['intensity', 'ambient', 'gloss']) {
    $(id).addEventListener('input', (e) => viewer.setLight({ [id]: Number(e.target.value) }));
  }

  // --- shading ----------------------------------------------------------------------------
  $('mode').addEventListener('change', (e) => viewer.setShading({ mode: e.target.value }));
  $('exaggeration').addEventListener('input', (e) => viewer.setShading({ exaggeration: Number(e.target.value) }));
  $('curvature-scale').addEventListener('change', (e) =>
    viewer.setShading({ curvatureScale: Number(e.target.value) }),
  );
  $('quality-map').addEventListener('change', (e) => viewer.setShading({ quality: e.target.value }));

  // --- views ------------------------------------------------------------------------------
  for (const b of document.querySelectorAll('[data-view]')) {
    b.addEventListener('click', () => viewer.setView(b.dataset.view));
  }
  $('reset').addEventListener('click', () => viewer.resetView());
  $('projection').addEventListener('click', toggleProjection);
  function toggleProjection() {
    viewer.setProjection(viewer.projection === 'orthographic' ? 'perspective' : 'orthographic');
  }

  /** Why a mode cannot be chosen on the model in view (modes.js), or null. */
  function modeUnavailable(mode) {
    const m = viewer.model;
    return m ? unavailableModeReason(mode, m.assets, { streamed: Boolean(m.tiles) }) : null;
  }

  // --- measuring --------------------------------------------------------------------------
  let tool = null; // 'distance' | 'profile' | null
  let lastProfile = null;
  let lastMeasure = null; // {tool, points, lengthMm}: what a permalink restores

  const picker = createPicker(viewer, canvas, {
    onPoint: (points) => {
      if (points.length === 1) setReadout(tool === 'profile' ? 'Click the end of the profile line.' : 'Click the second point.');
    },
    onDone: (points) => showMeasure(tool, points),
  });
  function setTool(next) {
    tool = tool === next ? null : next;
    $('measure').setAttribute('aria-pressed', String(tool === 'distance'));
    $('profile').setAttribute('aria-pressed', String(tool === 'profile'));
    if (tool) {
      picker.start();
      setReadout(tool === 'profile' ? 'Click the start of the profile line.' : 'Click the first point.');
    } else {
      picker.stop();
      setReadout('');
    }
  }
  function setReadout(text) {
    $('readout').textContent = text;
  }
  function showMeasure(kind, points) {
    lastMeasure = { tool: kind, points: points.map((p) => [...p]), lengthMm: distanceMm(points[0], points[1]) };
    delete $('readout').dataset.uncertaintyMm;
    context.measureChanged?.();
    return kind === 'profile' ? showProfile(lastMeasure.points) : showDistance(lastMeasure.points);
  }
  /**
   * Picked points put on the full-resolution heights of a streamed model (tiles.js
   * `onSurface`: a face's, or on a whole tablet each point's own face's, in its scan frame),
   * whatever level was drawn when picked; others as they are.
   */
  async function onFullSurface(points) {
    const tiled = viewer.model?.tiles;
    if (tiled?.heights) return tiled.heights.onSurface(points);
    if (tiled?.kind !== 'tablet') return points;
    const faces = viewer.model.assets.faces;
    return Promise.all(
      points.map(async (p) => {
        const face = faces[viewer.faceOfPoint(p)];
        const rows = face?.heights();
        if (!rows || !face.toFace) return p;
        const [q] = await rows.onSurface([transformPoint(face.toFace, p)]);
        return transformPoint(face.toModel, q);
      }),
    );
  }
  async function showDistance(points) {
    const measure = lastMeasure; // a newer measurement replaces this one's readout
    if (viewer.model?.tiles) points = await onFullSurface(points).catch(() => points);
    if (lastMeasure !== measure) return;
    const d = distanceMm(points[0], points[1]);
    setReadout(`Distance: ${d.toFixed(2)} mm`);
    $('readout').dataset.distanceMm = String(d);
    // The ± from the model's height uncertainty (trust.js), when it has one.
    const pm = await context.uncertainty?.distance(points).catch(() => null);
    // (not `points`: a streamed model's were moved onto the full-resolution surface)
    if (pm != null && lastMeasure === measure) {
      setReadout(`Distance: ${formatDistance(d, pm)}`);
      $('readout').dataset.uncertaintyMm = String(pm);
    }
  }
  let heightGrid = null; // {url, grid}
  async function loadHeightGrid(face = null) {
    // A whole tablet: the face's own heights (faces/<label>/height.npy) and pixel size.
    const url = face ? context.assetUrl?.(face.assets.height) : context.getHeightUrl();
    if (!url) {
      throw new Error(
        face
          ? `the face ${face.name} has no height.npy in this whole tablet, so no profile can be drawn`
          : 'this model has no height.npy, so no profile can be drawn',
      );
    }
    if (heightGrid?.url === url) return heightGrid.grid;
    setReadout('Loading height.npy…');
    const { shape, data } = parseNpy(await fetchBytes(url));
    let pixelSizeUm = face ? context.facePixelSizeUm?.(face.name) : context.getPixelSizeUm();
    if (!pixelSizeUm && face) throw new Error(`the pixel size of the face ${face.name} is unknown`);
    if (!pixelSizeUm) {
      const g = viewer.model.mesh.geometry;
      pixelSizeUm = pixelSizeFromMesh(g.attributes.position.array, g.attributes.uv.array, shape[1]);
    }
    const grid = { heightUm: data, rows: shape[0], cols: shape[1], pixelSizeUm };
    heightGrid = { url, grid };
    return grid;
  }
  async function showProfile(points) {
    try {
      const streamed = viewer.model?.tiles?.heights; // only the rows the line touches
      if (streamed) {
        setReadout('Reading heights…');
        const part = await streamed.reader.gridForSegment(points[0], points[1], streamed.pixelSizeUm);
        lastProfile = sampleProfile(part.grid, part.start, part.end);
        heightGrid = { url: null, grid: { pixelSizeUm: streamed.pixelSizeUm } };
      } else if (viewer.model?.assets.faces?.length) {
        // A whole tablet: the line on one face, cut from that face's own full-resolution
        // heights in its scan frame (faceGrids.js), as on the face model.
        // A streamed tablet's face: only the rows the line touches, by Range reads.
        const on = pointsOnOneFace(points, (p) => viewer.faceOfPoint(p), viewer.model.assets.faces);
        const face = viewer.model.assets.faces[on.face];
        const rows = face.heights?.();
        if (rows) {
          setReadout('Reading heights…');
          const part = await rows.reader.gridForSegment(on.points[0], on.points[1], rows.pixelSizeUm);
          lastProfile = sampleProfile(part.grid, part.start, part.end);
          heightGrid = { url: null, grid: { pixelSizeUm: rows.pixelSizeUm } };
        } else {
          lastProfile = sampleProfile(await loadHeightGrid(face), on.points[0], on.points[1]);
        }
        lastProfile.face = face.name;
      } else {
        lastProfile = sampleProfile(await loadHeightGrid(), points[0], points[1]);
      }
      // σ_h along the line (trust.js): a band on the chart, ± in the readout and the CSV.
      const sigmaUm = await context.uncertainty?.profile(lastProfile, points).catch(() => null);
      if (sigmaUm) lastProfile.sigmaUm = sigmaUm;
      const chart = $('profile-chart');
      chart.replaceChildren(profileChart(lastProfile));
      $('profile-panel').hidden = false;
      const u = sigmaUm ? profileUncertainty(lastProfile.heightUm, sigmaUm) : null;
      const pm = u ? `, heights ± ${fmtUm(u.medianUm)} (median; up to ${fmtUm(u.maxUm)})` : '';
      const on = lastProfile.face ? ` on ${lastProfile.face}` : '';
      setReadout(`Profile${on}: ${lastProfile.lengthMm.toFixed(2)} mm, ${lastProfile.heightUm.length} samples${pm}`);
    } catch (err) {
      setReadout(`Profile: ${err.message}`);
    }
  }
  $('measure').addEventListener('click', () => setTool('distance'));
  $('profile').addEventListener('click', () => setTool('profile'));
  $('profile-close').addEventListener('click', () => {
    $('profile-panel').hidden = true;
  });
  $('profile-csv').addEventListener('click', () => {
    if (!lastProfile) return;
    const about = {
      ...(context.describe?.() ?? {}),
      start: lastMeasure?.points[0],
      end: lastMeasure?.points[1],
      pixelSizeUm: heightGrid?.grid.pixelSizeUm,
      permalink: permalinkUrl(),
    };
    download(new Blob([profileToCsv(lastProfile, about)], { type: 'text/csv' }), `${context.baseName()}-profile.csv`);
  });

  // --- share ------------------------------------------------------------------------------
  async function screenshot() {
    const width = Math.round(Number($('shot-w').value));
    const height = Math.round(Number($('shot-h').value));
    try {
      const shot = await viewer.screenshot({ width, height });
      const mmPerPx = shotMmPerPixel({
        mmPerScreenPx: viewer.mmPerPixel(),
        canvasW: canvas.clientWidth || 1,
        canvasH: canvas.clientHeight || 1,
        shotW: width,
        shotH: height,
      });
      const about = context.describe?.() ?? {};
      const title = about.tablet
        ? `${about.tablet}${about.pNumber ? ` (${about.pNumber})` : ''}, model ${about.modelId} version ${about.modelVersion}`
        : null;
      const { blob } = await annotateScreenshot(shot, {
        mmPerPx,
        text: {
          Title: title,
          Description:
            `${viewer.shading.mode} shading, light azimuth ${Math.round(viewer.light.azimuthDeg)}°, polar ${Math.round(viewer.light.polarDeg)}°` +
            (describeEnhance(viewer.enhance) ? `; ${describeEnhance(viewer.enhance)}` : ''),
          Copyright: about.licence,
          Author: about.attribution,
          Source: permalinkUrl(),
          'Creation Time': new Date().toISOString(),
          Software: 'Digital Hammurabi viewer',
        },
      });
      download(blob, `${context.baseName()}-${viewer.shading.mode}.png`);
    } catch (err) {
      showNotice(`Screenshot failed: ${err.message}`);
    }
  }
  function permalinkUrl() {
    const url = new URL(window.location.href);
    url.hash = encodeViewState({ ...viewer.getState(), measure: lastMeasure });
    return url.toString();
  }
  function permalink() {
    const url = new URL(permalinkUrl());
    $('permalink-text').value = url.toString();
    $('permalink-text').select();
    navigator.clipboard?.writeText(url.toString()).catch(() => {});
    return url.toString();
  }
  $('screenshot').addEventListener('click', screenshot);
  $('permalink').addEventListener('click', permalink);

  // --- keyboard ---------------------------------------------------------------------------
  const table = $('help-table');
  for (const s of SHORTCUTS) {
    const tr = document.createElement('tr');
    const th = document.createElement('th');
    th.textContent = s.label;
    const td = document.createElement('td');
    td.textContent = s.help;
    tr.append(th, td);
    table.append(tr);
  }
  $('help-button').addEventListener('click', () => $('help').showModal());

  function onKey(event) {
    const hit = actionForKey(event);
    if (!hit || !viewer.model) return;
    const step = hit.fine ? 1 : 5;
    const l = viewer.light;
    const [verb, arg] = hit.action.split(':');
    switch (verb) {
      case 'light-azimuth':
        viewer.setLight({ azimuthDeg: wrapAzimuth(l.azimuthDeg + (hit.key === 'ArrowRight' ? step : -step)) });
        break;
      case 'light-polar':
        viewer.setLight({ polarDeg: clampPolar(l.polarDeg + (hit.key === 'ArrowDown' ? step : -step)) });
        break;
      case 'raking': {
        const p = RAKING_PRESETS[Number(hit.key) - 1];
        viewer.setLightFromView({ azimuthDeg: p.azimuthDeg, polarDeg: p.polarDeg });
        break;
      }
      case 'overhead':
        // From the camera, and following it: the light stays where the eye is as the tablet turns.
        viewer.setLight({ follow: true, azimuthDeg: 0, polarDeg: 0 });
        break;
      case 'brighter':
        viewer.setLight({ intensity: Math.min(2, l.intensity + 0.1) });
        break;
      case 'dimmer':
        viewer.setLight({ intensity: Math.max(0, l.intensity - 0.1) });
        break;
      case 'gloss':
        viewer.setLight({ gloss: l.gloss > 0 ? 0 : 0.5 });
        break;
      case 'mode':
        if (modeUnavailable(arg)) {
          setReadout(modeUnavailable(arg)); // the select's option is disabled for that reason
        } else if (arg === 'curvature' && viewer.shading.mode === 'curvature') {
          const n = $('curvature-scale').options.length || 1;
          viewer.setShading({ curvatureScale: (viewer.shading.curvatureScale + 1) % n });
        } else {
          viewer.setShading({ mode: arg });
        }
        break;
      case 'view':
        if (!viewer.views.includes(arg)) return; // a face model: the button says why
        viewer.setView(arg);
        break;
      case 'reset':
        viewer.resetView();
        break;
      case 'projection':
        toggleProjection();
        break;
      case 'zoom-in':
        viewer.zoomBy(1.25);
        break;
      case 'zoom-out':
        viewer.zoomBy(0.8);
        break;
      case 'turn-right':
        viewer.orbitBy(15);
        break;
      case 'turn-left':
        viewer.orbitBy(-15);
        break;
      case 'measure':
        setTool('distance');
        break;
      case 'profile':
        setTool('profile');
        break;
      case 'cancel':
        context.onAction?.('cancel');
        if (tool) setTool(tool);
        $('profile-panel').hidden = true;
        break;
      case 'screenshot':
        screenshot();
        break;
      case 'permalink':
        permalink();
        break;
      case 'help':
        $('help').showModal();
        break;
      default:
        // The Read panel's tools (scholar.js): best light, section, lens.
        if (!context.onAction?.(verb, arg)) return;
    }
    event.preventDefault();
  }
  window.addEventListener('keydown', onKey);

  // --- reflect the viewer's state ---------------------------------------------------------
  let scheduled = false;
  function sync() {
    scheduled = false;
    const l = viewer.light;
    widget.draw(viewer.lightInView());
    const behind = l.polarDeg > 90 ? ', from behind' : '';
    $('light-readout').textContent =
      `azimuth ${l.azimuthDeg.toFixed(0)}° (from the ${compassLabel(l.azimuthDeg)}), polar ${l.polarDeg.toFixed(0)}°` +
      `${behind}, ${l.follow ? 'relative to the camera' : 'fixed to the tablet'}`;
    $('light-follow').checked = Boolean(l.follow);
    const views = viewer.views;
    for (const b of document.querySelectorAll('[data-view]')) {
      const ok = !viewer.model || views.includes(b.dataset.view);
      b.disabled = !ok;
      b.title = ok ? '' : unavailableViewReason(b.dataset.view, context.face?.() ?? null);
    }
    $('intensity').value = String(l.intensity);
    $('ambient').value = String(l.ambient);
    $('gloss').value = String(l.gloss);
    const s = viewer.shading;
    // Modes the model has nothing for are disabled, their reason in the option's title.
    for (const select of [$('mode'), $('lens-mode')]) {
      for (const option of select.options) {
        const why = modeUnavailable(option.value);
        option.disabled = Boolean(why);
        option.title = why ?? '';
      }
    }
    $('mode').value = s.mode;
    $('exaggeration').value = String(s.exaggeration);
    $('curvature-scale-row').hidden = s.mode !== 'curvature';
    $('quality-row').hidden = s.mode !== 'quality';
    fillSelect($('curvature-scale'), (viewer.model?.assets.curvature || []).map((c, i) => [String(i), c.label]), String(s.curvatureScale));
    fillSelect($('quality-map'), (viewer.model?.assets.quality || []).map((q) => [q.name, q.name]), s.quality ?? '');
    $('projection').setAttribute('aria-pressed', String(viewer.projection === 'perspective'));
    $('projection').textContent = viewer.projection === 'perspective' ? 'Orthographic' : 'Perspective';
    updateLegend(s);
    // The link's problems stay up while the map notices come and go with the mode.
    showNotice([linkNotice, viewer.missingMessage()].filter(Boolean).join(' ') || null);
    updateScaleBar();
    canvas.dataset.mode = s.mode;
    canvas.dataset.azimuth = l.azimuthDeg.toFixed(3);
    canvas.dataset.polar = l.polarDeg.toFixed(3);
    canvas.dataset.follow = String(Boolean(l.follow));
  }
  /** Colour ramps say what their colours mean: the quality map's range, curvature's sign. */
  function updateLegend(s) {
    const legend = $('legend');
    const assets = viewer.model?.assets;
    let spec = null;
    if (s.mode === 'curvature' && assets?.curvature?.length) {
      const layer = assets.curvature[Math.min(s.curvatureScale, assets.curvature.length - 1)];
      spec = { cls: 'diverging', lo: 'concave', hi: 'convex', what: `mean curvature (${layer.label})` };
    } else if (s.mode === 'quality' && assets?.quality?.length) {
      const q = assets.quality.find((m) => m.name === s.quality) ?? assets.quality[0];
      const fmt = (v) => Number(v.toPrecision(3)).toString();
      spec = { cls: 'sequential', lo: fmt(q.range[0]), hi: fmt(q.range[1]), what: `${q.name} (2nd–98th percentile)` };
    } else if (s.mode === 'depth' && viewer.model) {
      const [lo, hi] = [-viewer.model.box.max[2], -viewer.model.box.min[2]];
      spec = { cls: 'sequential', lo: `${lo.toFixed(2)} mm`, hi: `${hi.toFixed(2)} mm`, what: 'height toward the camera' };
    }
    legend.hidden = !spec;
    if (!spec) return;
    legend.querySelector('.ramp').className = `ramp ${spec.cls}`;
    const [lo, hi] = legend.querySelectorAll('.ends span');
    lo.textContent = spec.lo;
    hi.textContent = spec.hi;
    legend.querySelector('.what').textContent = spec.what;
  }
  let linkNotice = null; // what the page's permalink asked for and could not have
  function showNotice(text) {
    $('notice').hidden = !text;
    $('notice').textContent = text ?? '';
  }
  function updateScaleBar() {
    const mmPerPx = viewer.mmPerPixel();
    if (!(mmPerPx > 0) || !viewer.model) {
      $('scalebar').hidden = true;
      return;
    }
    const mm = niceStep(mmPerPx * 120);
    $('scalebar').hidden = false;
    $('scalebar').querySelector('.bar').style.width = `${mm / mmPerPx}px`;
    $('scalebar').querySelector('span').textContent = mm >= 1 ? `${mm} mm` : `${Math.round(mm * 1000)} µm`;
  }

  return {
    /** Call from the viewer's onChange. */
    changed() {
      if (scheduled) return;
      scheduled = true;
      queueMicrotask(sync);
    },
    stopTools() {
      if (tool) setTool(tool);
      heightGrid = null;
      lastMeasure = null;
      $('profile-panel').hidden = true;
    },
    permalink,
    permalinkUrl,
    /** The measurement on screen ({tool, points, lengthMm}) or null. */
    measurement: () => lastMeasure,
    /** Show a measurement a permalink carried: marks, readout and (for a profile) the chart. */
    async restoreMeasure(measure) {
      if (!measure) return;
      viewer.setMarks(measure.points);
      // A streamed tablet's faces have their frames once their tiles are in (tiles.js).
      if (viewer.model?.tiles?.kind === 'tablet') await viewer.whenTilesSettled();
      return showMeasure(measure.tool, measure.points);
    },
    /** A lasting notice about the opened link (null: none), shown before any map notice. */
    setLinkNotice(text) {
      linkNotice = text || null;
      sync();
    },
    dispose() {
      window.removeEventListener('keydown', onKey);
      picker.dispose();
      widget.dispose();
    },
  };
}

function fillSelect(select, entries, value) {
  const key = entries.map((e) => e.join('=')).join('|');
  if (select.dataset.key !== key) {
    select.replaceChildren(
      ...entries.map(([v, label]) => {
        const o = document.createElement('option');
        o.value = v;
        o.textContent = label;
        return o;
      }),
    );
    select.dataset.key = key;
  }
  if (entries.some(([v]) => v === value)) select.value = value;
}

function download(blob, filename) {
  const a = document.createElement('a');
  a.href = URL.createObjectURL(blob);
  a.download = filename;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(a.href), 10000);
}

