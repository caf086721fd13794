/**
 * The tablet page (`tablet.html?id=N#<permalink>`): catalogue data, scans with their job
 * state, model versions, downloads, links, and the relighting viewer.
 */
import * as api from './api.js';
import { el, formatDate, showError } from './dom.js';
import { bindViewerUi } from './viewer/ui.js';
import { bindScholarTools } from './viewer/scholar.js';
import { bindCite } from './viewer/citeUi.js';
import { bindPhotoPanel } from './viewer/photos.js';
import { bindAnnotations } from './annotationsPanel.js';
import { bindLicenceForm } from './licenceForm.js';
import { decodeViewState, encodeViewState } from './viewer/permalink.js';
import { tileOptionsFromSearch } from './viewer/tilesIndex.js';
import { createViewer } from './viewer/viewer.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(window.location.search);
const tabletId = params.get('id');

const CATALOGUE_FIELDS = [
  ['designation', 'Designation'],
  ['p_number', 'CDLI number'],
  ['museum_no', 'Museum number'],
  ['collection', 'Collection'],
  ['period', 'Period'],
  ['provenience', 'Provenience'],
  ['genre', 'Genre'],
  ['subgenre', 'Subgenre'],
  ['language', 'Language'],
  ['material', 'Material'],
  ['object_type', 'Object type'],
  ['excavation_no', 'Excavation number'],
  ['primary_publication', 'Publication'],
  ['institution', 'Institution'],
];

const JOB_POLL_MS = 2000;

let tablet = null;
let currentModel = null; // the API's model record
let loadController = null;
let hashTimer = null;
let restoring = decodeViewState(window.location.hash);

const tileSettings = tileOptionsFromSearch(location.search); // ?tile_budget_mb=…&tile_error_px=…
let ui = null; // bound below; the viewer reports changes while it is being created
let photos = null;
let scholar = null;
const viewer = createViewer($('viewer'), {
  onChange: () => {
    ui?.changed();
    photos?.changed();
    scholar?.changed();
    if (currentModel) scheduleHash();
  },
});
/** A model asset's URL by name, or null. */
const assetUrl = (name) => (name && currentModel?.assets?.[name] ? api.assetHref(currentModel.assets[name]) : null);
/** A whole tablet's face's pixel size (µm), from the registration's report (faces.<label>). */
const facePixelSizeUm = (label) => Number(currentModel?.report?.faces?.[label]?.pixel_size_um) || null;
scholar = bindScholarTools(viewer, {
  assetUrl,
  facePixelSizeUm,
  getPixelSizeUm: () => Number(currentModel?.report?.pixel_size_um) || null,
  getHeightUrl: () => assetUrl('height.npy'),
  baseName: () => (tablet?.designation ?? `tablet-${tabletId}`).replace(/[^\w.-]+/g, '_'),
  describe: describeShown,
});
ui = bindViewerUi(viewer, {
  uncertainty: scholar.uncertainty,
  onAction: scholar.onAction,
  getHeightUrl: () => assetUrl('height.npy'),
  assetUrl,
  facePixelSizeUm,
  getPixelSizeUm: () => Number(currentModel?.report?.pixel_size_um) || null,
  baseName: () => (tablet?.designation ?? `tablet-${tabletId}`).replace(/[^\w.-]+/g, '_'),
  face: () => currentModel?.report?.scan?.face ?? null,
  describe: describeShown,
  measureChanged: () => currentModel && scheduleHash(),
});
photos = bindPhotoPanel(viewer, {
  canvas: $('viewer'),
  controls: $('photo-controls'),
  show: $('photo-show'),
  swipe: $('photo-swipe'),
  swipeAt: $('photo-swipe-at'),
  useLight: $('photo-use-light'),
  panel: $('photo-panel'),
  img: $('photo-img'),
  caption: $('photo-caption'),
  layer: $('photo-layer'),
  layerImg: $('photo-layer-img'),
});
bindCite({
  getAbout: () => {
    if (!currentModel) return null;
    const state = viewer.getState();
    return {
      ...describeShown(),
      institution: tablet?.institution ?? null,
      view: { mode: state.shading.mode, light: state.light, measure: ui.measurement() },
      permalink: ui.permalinkUrl(),
    };
  },
});

const licence = bindLicenceForm({
  container: $('licence'),
  // Citations and exports read the model on screen: they carry the new licence at once.
  onSaved: (saved) => {
    if (currentModel?.id === saved.id) currentModel = { ...currentModel, ...saved };
  },
});

// Drawing a region takes the clicks: the measuring tools and the Read panel's (section, best
// light) stop, or a click would count for two tools.
const annotations = bindAnnotations(viewer, {
  container: $('annotations'),
  canvas: $('viewer'),
  stopTools: () => {
    ui.stopTools();
    scholar.onAction('cancel');
  },
});

/** The tablet and model on screen, for citations and exported files. */
function describeShown() {
  return {
    tablet: tablet?.designation ?? `tablet ${tabletId}`,
    pNumber: tablet?.p_number ?? null,
    modelId: currentModel?.id,
    modelVersion: currentModel?.version,
    licence: currentModel?.effective_licence ?? tablet?.effective_licence ?? null,
    attribution: currentModel?.effective_attribution ?? tablet?.effective_attribution ?? null,
  };
}
// For the console and for tests: the page's viewer.
window.hammurabi = { viewer, ui, annotations, scholar };

function scheduleHash() {
  clearTimeout(hashTimer);
  hashTimer = setTimeout(() => {
    const state = viewer.getState();
    state.model = currentModel.id;
    state.measure = ui.measurement();
    history.replaceState(null, '', `#${encodeViewState(state)}`);
  }, 250);
}

function renderCatalogue(t) {
  document.title = `${t.designation} — Digital Hammurabi`;
  $('title').textContent = t.designation;
  const dl = $('catalogue');
  dl.replaceChildren();
  for (const [key, label] of CATALOGUE_FIELDS) {
    const v = t[key];
    if (v === null || v === undefined || v === '' || key === 'designation') continue;
    dl.append(el('dt', {}, label), el('dd', {}, String(v)));
  }
  const dims = ['height_mm', 'width_mm', 'thickness_mm'].map((k) => t[k]);
  if (dims.some((d) => d)) {
    dl.append(el('dt', {}, 'Size'), el('dd', {}, `${dims.map((d) => (d ? d.toFixed(1) : '?')).join(' × ')} mm`));
  }
  $('links').replaceChildren(
    el('li', {}, el('a', { href: api.tabletUrl(t.id) }, 'Catalogue record (JSON API)')),
    el('li', {}, el('a', { href: api.iiifManifestUrl(t.id) }, 'IIIF manifest')),
  );
}

function modelsOf(scan) {
  return (scan.models ?? []).map((m) => (typeof m === 'object' ? m : { id: m }));
}

function jobText(job) {
  if (!job) return 'no job';
  const pct = job.progress != null ? ` ${Math.round(job.progress * 100)} %` : '';
  if (job.state === 'failed') return `failed: ${job.error ?? 'unknown error'}`;
  if (job.state === 'running') return `running${pct}${job.stage ? ` (${job.stage})` : ''}`;
  return job.state;
}

let tabletModels = []; // tablet-level models (scan_id null): the whole tablet

function renderScans(scans) {
  const list = $('scans');
  list.replaceChildren();
  const select = $('model-select');
  select.replaceChildren();
  for (const scan of scans) {
    const job = scan.latest_job;
    const li = el(
      'li',
      { 'data-scan': scan.id },
      el('strong', {}, scan.face),
      ` scanned ${formatDate(scan.created_at)} — `,
      el('span', { class: `job job-${job?.state ?? 'none'}` }, jobText(job)),
    );
    list.append(li);
    for (const m of modelsOf(scan)) {
      const label = `${scan.face}, version ${m.version ?? m.id}${m.created_at ? ` (${formatDate(m.created_at)})` : ''}`;
      select.append(el('option', { value: m.id }, label));
    }
  }
  for (const m of tabletModels) {
    const label = `Whole tablet, version ${m.version ?? m.id}${m.created_at ? ` (${formatDate(m.created_at)})` : ''}`;
    select.append(el('option', { value: m.id }, label));
  }
  if (!select.options.length) select.append(el('option', { value: '' }, 'none yet'));
  return scans.some((s) => ['queued', 'running'].includes(s.latest_job?.state));
}

function renderDownloads(model) {
  const list = $('downloads');
  list.replaceChildren();
  if (!model) return;
  const wanted = [
    ['mesh.ply', 'Mesh, full resolution (PLY)'],
    ['model.glb', 'Model for the web (GLB)'],
    ['height.npy', 'Height map, µm (NumPy)'],
    ['albedo.png', 'Albedo (PNG)'],
    ['normals.png', 'Normal map (PNG)'],
    ['report.json', 'Reconstruction report (JSON)'],
  ];
  for (const [name, label] of wanted) {
    const url = model.assets?.[name];
    if (url) list.append(el('li', {}, el('a', { href: api.assetHref(url), download: '' }, label)));
  }
  list.append(el('li', {}, el('a', { href: `${api.API_PREFIX}/models/${model.id}` }, 'Model record (JSON API)')));
}

/** The whole-tablet model's face checkboxes and fatcross plate links (else nothing). */
function renderFaces(model) {
  let section = $('faces');
  if (!section) {
    section = el('section', { id: 'faces' });
    $('downloads').closest('section').before(section);
  }
  section.replaceChildren();
  const names = viewer.partNames();
  // The publication plates (and their PDF) first; the single views after them.
  const plates = Object.keys(model?.assets ?? {})
    .filter((n) => /^fatcross\/.+\.(png|pdf)$/.test(n))
    .sort((a, b) => Number(!/_fatcross/.test(a)) - Number(!/_fatcross/.test(b)) || a.localeCompare(b));
  section.hidden = !names.length && !plates.length;
  if (section.hidden) return;
  section.append(el('h2', {}, 'Faces'));
  const list = el('ul', { class: 'faces' });
  const hidden = new Set(viewer.getState().hidden);
  for (const name of names) {
    const box = el('input', { type: 'checkbox', 'data-face': name });
    box.checked = !hidden.has(name);
    box.addEventListener('change', () => viewer.setPartVisible(name, box.checked));
    list.append(el('li', {}, el('label', {}, box, ` ${name}`)));
  }
  section.append(list);
  if (plates.length) {
    section.append(el('p', {}, el('strong', {}, 'Fatcross plates')));
    const links = el('ul', { class: 'plates' });
    for (const n of plates) {
      links.append(el('li', {}, el('a', { href: api.assetHref(model.assets[n]) }, n.slice('fatcross/'.length))));
    }
    section.append(links);
  }
}

async function showModel(modelId) {
  loadController?.abort();
  loadController = new AbortController();
  const { signal } = loadController;
  ui.stopTools();
  scholar.stop();
  $('progress').hidden = false;
  $('progress-fill').style.width = '0%';
  $('progress-label').textContent = 'Loading the model…';
  try {
    const model = (await takeEarly('model', modelId)) ?? (await api.getModel(modelId));
    if (signal.aborted) return;
    const assets = Object.fromEntries(Object.entries(model.assets ?? {}).map(([k, v]) => [k, api.assetHref(v)]));
    await viewer.load({
      assets,
      signal,
      tiles: tileSettings.options, // streamed models: GPU budget, error target
      onProgress: (fraction, label) => {
        $('progress-fill').style.width = `${Math.round(fraction * 100)}%`;
        $('progress-label').textContent = `Loading the model: ${label}`;
      },
    });
    if (signal.aborted) return;
    currentModel = model;
    // The photographs are an extra: the page works without them.
    photos.setModel(model, api.assetHref).catch((err) => console.warn('photographs not shown:', err));
    // Simulated data must never pass for a measurement of the catalogued tablet.
    $('simulated-badge').hidden = !model.simulated;
    $('model-select').value = String(model.id);
    renderDownloads(model);
    const restore = restoring;
    restoring = null;
    // The viewer's state names the model, so that its permalink button links this version.
    viewer.setState({ model: model.id });
    const tileIgnored = model.assets?.['tiles/index.json'] ? tileSettings.ignored : [];
    if (restore && (restore.state.model === null || restore.state.model === model.id)) {
      const { unknownParts } = viewer.setState({ ...restore.state, model: model.id });
      const ignored = restore.ignored.concat(
        unknownParts.map((n) => `face ${JSON.stringify(n)} (not in this model)`),
        tileIgnored,
      );
      if (ignored.length) ui.setLinkNotice(`Parts of the link could not be used: ${ignored.join(', ')}.`);
      if (restore.state.measure) ui.restoreMeasure(restore.state.measure);
    } else if (tileIgnored.length) {
      ui.setLinkNotice(`Parts of the link could not be used: ${tileIgnored.join(', ')}.`);
    }
    renderFaces(model);
    annotations.setModel(model);
    licence.setModel(model);
    scheduleHash();
    $('viewer').dataset.loaded = String(model.id);
  } catch (err) {
    if (err.name === 'AbortError') return;
    showError($('tablet-error'), `The model could not be shown: ${err.message}`);
  } finally {
    if (!signal.aborted) $('progress').hidden = true;
  }
}

async function refreshScans({ pickModel }) {
  // The catalogue's numeric id: the page may have been opened by P-number (?id=P451806),
  // which the tablet route resolves but the model list (?tablet_id=) does not.
  const id = tablet?.id ?? tabletId;
  const [scans, wholeTablet] = await Promise.all([
    takeEarly('scans', id).then((r) => r ?? api.tabletScans(id)),
    // The whole tablet is an extra; the page works without it.
    takeEarly('models', id).then((r) => r ?? api.tabletModels(id).catch(() => [])),
  ]);
  tabletModels = Array.isArray(wholeTablet) ? wholeTablet : [];
  const list = Array.isArray(scans) ? scans : (scans.items ?? []);
  const busy = renderScans(list);
  const faceModels = list.flatMap(modelsOf);
  const all = faceModels.concat(tabletModels);
  $('empty').hidden = all.length > 0 || busy;
  if (pickModel && all.length) {
    const wanted = restoring?.state.model;
    // By default the whole tablet (the object as a reader holds it), else the latest face model.
    const pool = tabletModels.length ? tabletModels : all;
    const latest = pool.reduce((a, b) => ((b.version ?? b.id) > (a.version ?? a.id) ? b : a));
    const target = all.find((m) => m.id === wanted) ?? latest;
    const missingLinked = wanted != null && target.id !== wanted;
    await showModel(target.id);
    if (missingLinked) ui.setLinkNotice(`Model ${wanted} of the link is not among this tablet's models: showing the latest.`);
  } else if (currentModel) {
    $('model-select').value = String(currentModel.id);
  }
  if (busy) {
    setTimeout(() => refreshScans({ pickModel: !currentModel }).catch(reportError), JOB_POLL_MS);
  }
}

function reportError(err) {
  showError($('tablet-error'), err.status === 404 ? `No tablet with id ${tabletId}.` : err.message);
}

$('model-select').addEventListener('change', (e) => {
  ui.setLinkNotice(null); // another version than the link's: its notice no longer applies
  if (e.target.value) showModel(Number(e.target.value));
});
window.addEventListener('beforeunload', () => viewer.dispose());

/**
 * Requests the page will make, started together at once instead of one after the other
 * (issue 19: first render ≤ 1 s): the tablet's scans and models when the page's id is the
 * numeric one (the lists need it; a P-number is resolved by the tablet route first), and the
 * model a permalink names. Each is used once, by the step that would have asked for it, and
 * only for the id it was asked for; a failed one is asked for again there (its error shown).
 */
const early = new Map(); // kind → {id, promise of the response or null}

function startEarly(kind, id, request) {
  early.set(kind, { id, promise: request().catch(() => null) });
}

/** The early response of `kind` for `id`, or null (none, another id, failed, used already). */
async function takeEarly(kind, id) {
  const e = early.get(kind);
  if (!e || String(e.id) !== String(id)) return null;
  early.delete(kind);
  return e.promise;
}

async function main() {
  if (!tabletId) {
    showError($('tablet-error'), 'No tablet given: open this page as tablet.html?id=N from the library.');
    return;
  }
  if (/^\d+$/.test(tabletId)) {
    startEarly('scans', tabletId, () => api.tabletScans(tabletId));
    startEarly('models', tabletId, () => api.tabletModels(tabletId));
  }
  const linked = restoring?.state.model;
  if (Number.isInteger(linked)) startEarly('model', linked, () => api.getModel(linked));
  try {
    tablet = await api.getTablet(tabletId);
    renderCatalogue(tablet);
    annotations.setTablet(tablet).catch(reportError);
    api
      .sessionUser()
      .catch(() => null)
      .then((me) => licence.setContext(me, tablet));
    await refreshScans({ pickModel: true });
  } catch (err) {
    reportError(err);
  }
}

main();
