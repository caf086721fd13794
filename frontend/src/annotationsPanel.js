/**
 * The "Signs" panel of the tablet page: the transliteration (when the record has one) with
 * clickable signs, the tablet's annotations (searchable, each naming its model version), and
 * for signed-in users a form to draw a region on the model and tie it to a sign.
 *
 * Regions of the model version on screen are drawn over it; clicking a sign (or an
 * annotation) highlights its regions. Builds its own DOM inside `container`.
 */
import * as api from './api.js';
import './annotations.css';
import { el, showError } from './dom.js';
import { annotationsOfSign, canAnnotate, canEdit, createRegionOverlay, normaliseReference, regionBody } from './viewer/annotations.js';
import { faceUvOfPoint } from './viewer/faceGrids.js';

const SEARCH_DELAY_MS = 250;
const DRAG_PX = 4; // a press that moves more is an orbit, not a click on the surface

/**
 * @param {ReturnType<import('./viewer/viewer.js').createViewer>} viewer
 * @param {{container: HTMLElement, canvas: HTMLCanvasElement, stopTools: () => void}} context
 */
export function bindAnnotations(viewer, { container, canvas, stopTools }) {
  const overlay = createRegionOverlay(viewer.addOverlay);
  let tablet = null;
  let model = null; // the API's model record on screen
  let me = null;
  let items = []; // the tablet's annotations (JSON-LD, with our plain fields)
  let highlighted = null; // a reference ("o 2 3") or null
  let draft = []; // picks {point, uv, part} of the region being drawn
  let drawing = false;
  let editing = null; // the annotation being edited, or null for a new one
  let searchTimer = null;

  // --- DOM ----------------------------------------------------------------------------------
  const translit = el('div', { id: 'transliteration', class: 'transliteration', hidden: true });
  const search = el('input', {
    id: 'annotation-search',
    type: 'search',
    placeholder: 'Search: o 2, lugal, a comment…',
    'aria-label': 'Search the annotations',
  });
  const count = el('p', { id: 'annotation-count', class: 'muted', role: 'status' });
  const list = el('ul', { id: 'annotation-list', class: 'annotation-list' });
  const login = el('p', { id: 'annotation-login', class: 'muted', hidden: true }, 'Sign in (Staff page) to annotate signs.');
  const newButton = el('button', { type: 'button', id: 'annotation-new', hidden: true }, 'Annotate a sign');
  const reference = el('input', { name: 'reference', id: 'annotation-reference', placeholder: 'o 2 3', required: true, autocomplete: 'off' });
  const reading = el('input', { name: 'reading', id: 'annotation-reading', maxlength: 200, autocomplete: 'off' });
  const comment = el('textarea', { name: 'comment', id: 'annotation-comment', rows: 2, maxlength: 10000 });
  const drawButton = el('button', { type: 'button', id: 'annotation-draw', 'aria-pressed': 'false' }, 'Draw region');
  const undoButton = el('button', { type: 'button', id: 'annotation-undo' }, 'Undo point');
  const status = el('p', { id: 'annotation-status', class: 'muted', role: 'status' });
  const error = el('p', { id: 'annotation-error', class: 'error', role: 'alert', hidden: true });
  const save = el('button', { type: 'submit', id: 'annotation-save' }, 'Save');
  const cancel = el('button', { type: 'button', id: 'annotation-cancel' }, 'Cancel');
  const form = el(
    'form',
    { id: 'annotation-form', class: 'annotation-form', hidden: true },
    el('label', {}, 'Reference ', reference),
    el('small', { class: 'muted' }, 'surface line sign: o obverse, r reverse, le/re/te/be edges'),
    el('label', {}, 'Reading ', reading),
    el('label', {}, 'Comment ', comment),
    el('div', { class: 'buttons' }, drawButton, undoButton),
    status,
    error,
    el('div', { class: 'buttons' }, save, cancel),
  );
  container.replaceChildren(el('h2', {}, 'Signs'), translit, search, count, list, login, newButton, form);

  // --- data ---------------------------------------------------------------------------------
  async function setTablet(next) {
    tablet = next;
    me = await api.sessionUser().catch(() => null);
    login.hidden = canAnnotate(me);
    newButton.hidden = !canAnnotate(me) || !model;
    translit.hidden = true;
    if (tablet.atf) {
      try {
        renderTransliteration(await api.getTransliteration(tablet.id));
      } catch (err) {
        showError(error, `The transliteration could not be read: ${err.message}`);
      }
    }
    await refresh();
  }

  function setModel(next) {
    model = next;
    // A region drawn on the previous version does not belong to this one.
    if (!form.hidden) closeForm();
    stopDrawing();
    newButton.hidden = !canAnnotate(me) || !model;
    redraw();
    renderList();
  }

  async function refresh() {
    if (!tablet) return;
    const page = await api.tabletAnnotations(tablet.id, search.value.trim() || undefined);
    items = page.items ?? [];
    renderList();
    markAnnotatedSigns();
    redraw();
  }

  // --- transliteration -----------------------------------------------------------------------
  function renderTransliteration(parsed) {
    translit.replaceChildren();
    for (const surface of parsed.surfaces) {
      translit.append(el('h3', {}, surface.name));
      const lines = el('ol', { class: 'atf-lines' });
      for (const line of surface.lines) {
        const li = el('li', {}, el('span', { class: 'atf-number' }, `${line.number}.`));
        for (const sign of line.signs) {
          const b = el('button', { type: 'button', class: 'sign', 'data-ref': sign.reference, title: sign.reference }, sign.text);
          b.addEventListener('click', () => selectSign(sign.reference));
          li.append(' ', b);
        }
        lines.append(li);
      }
      translit.append(lines);
    }
    translit.hidden = !parsed.surfaces.length;
    markAnnotatedSigns();
  }

  function markAnnotatedSigns() {
    const refs = new Set(items.map((a) => a.reference?.text));
    for (const b of translit.querySelectorAll('button.sign')) {
      b.classList.toggle('annotated', refs.has(b.dataset.ref));
      b.setAttribute('aria-pressed', String(b.dataset.ref === highlighted));
    }
  }

  /** Highlight a sign's regions (again: off); while annotating, it becomes the reference. */
  function selectSign(ref) {
    highlighted = highlighted === ref ? null : ref;
    if (!form.hidden && highlighted) reference.value = ref;
    markAnnotatedSigns();
    renderList();
    redraw();
  }

  // --- list ---------------------------------------------------------------------------------
  function renderList() {
    list.replaceChildren();
    const q = search.value.trim();
    count.textContent = `${items.length} annotation${items.length === 1 ? '' : 's'}${q ? ` matching “${q}”` : ''}`;
    for (const a of items) {
      const here = model && a.modelId === model.id;
      const li = el(
        'li',
        {
          'data-annotation': a.annotationId,
          'data-ref': a.reference.text,
          class: [here ? 'here' : 'elsewhere', a.reference.text === highlighted ? 'highlighted' : ''].join(' ').trim(),
        },
        el('button', { type: 'button', class: 'ref', title: 'Highlight on the model' }, a.reference.text),
        a.reading ? el('span', { class: 'reading' }, ` ${a.reading}`) : null,
        el('span', { class: 'muted' }, ` — ${a.face === 'tablet' ? 'whole tablet' : a.face}, version ${a.modelVersion}${here ? '' : ' (not shown)'}`),
        a.comment ? el('div', { class: 'comment' }, a.comment) : null,
      );
      li.querySelector('.ref').addEventListener('click', () => selectSign(a.reference.text));
      if (canEdit(me, a, tablet)) {
        const edit = el('button', { type: 'button', class: 'edit' }, 'Edit');
        const del = el('button', { type: 'button', class: 'delete' }, 'Delete');
        edit.addEventListener('click', () => openForm(a));
        del.addEventListener('click', () => remove(a));
        li.append(el('span', { class: 'buttons' }, edit, del));
      }
      list.append(li);
    }
  }

  function redraw() {
    const regions = items
      .filter((a) => model && a.modelId === model.id)
      .map((a) => ({ points: a.polygonMm, highlighted: a.reference.text === highlighted }));
    overlay.set(regions, draft.map((p) => p.point), (viewer.model?.radius ?? 30) * 0.01);
    viewer.invalidate(); // the viewer renders on demand
  }

  search.addEventListener('input', () => {
    clearTimeout(searchTimer);
    searchTimer = setTimeout(() => refresh().catch((err) => showError(error, err.message)), SEARCH_DELAY_MS);
  });

  // --- drawing on the model --------------------------------------------------------------------
  let downAt = null;
  canvas.addEventListener('pointerdown', (e) => {
    if (drawing && e.button === 0) downAt = [e.clientX, e.clientY];
  });
  canvas.addEventListener('pointerup', (e) => {
    if (!drawing || !downAt) return;
    const moved = Math.hypot(e.clientX - downAt[0], e.clientY - downAt[1]);
    downAt = null;
    if (moved > DRAG_PX) return;
    const hit = viewer.pick(e.clientX, e.clientY);
    if (!hit) return;
    draft.push({ point: hit.point, uv: faceUv(hit), part: hit.part ?? null });
    drawStatus();
    redraw();
  });

  /** A hit's uv on its face's whole image grid: a streamed tablet's hit carries its tile's
   * uv, so its point is taken onto the face's grid (faceGrids.js); model.glb's is that already. */
  function faceUv(hit) {
    const tiled = viewer.model?.tiles;
    if (tiled?.kind !== 'tablet') return hit.uv;
    const face = viewer.model.assets.faces.find((f) => f.name === hit.part);
    const grid = tiled.faceGrid(hit.part);
    if (!face?.toFace || !grid) return null;
    return faceUvOfPoint(face.toFace, hit.point, Number(grid.pixel_size_um), grid.width_px, grid.height_px);
  }

  function startDrawing() {
    stopTools(); // one tool takes the clicks at a time
    drawing = true;
    draft = [];
    drawButton.setAttribute('aria-pressed', 'true');
    canvas.classList.add('picking');
    drawStatus();
    redraw();
  }

  function stopDrawing() {
    drawing = false;
    drawButton.setAttribute('aria-pressed', 'false');
    canvas.classList.remove('picking');
  }

  function drawStatus() {
    const n = draft.length;
    status.textContent = drawing
      ? `${n} point${n === 1 ? '' : 's'}: click around the sign on the model${n >= 3 ? ', then Save' : ' (at least 3)'}.`
      : '';
  }

  drawButton.addEventListener('click', () => (drawing ? stopDrawing() : startDrawing()));
  undoButton.addEventListener('click', () => {
    draft.pop();
    drawStatus();
    redraw();
  });
  // The measuring tools take the clicks: drawing stops.
  for (const id of ['measure', 'profile']) document.getElementById(id)?.addEventListener('click', stopDrawing);

  // --- the form --------------------------------------------------------------------------------
  function openForm(annotation = null) {
    editing = annotation;
    form.hidden = false;
    newButton.hidden = true;
    showError(error, null);
    reference.value = annotation?.reference.text ?? highlighted ?? '';
    reading.value = annotation?.reading ?? '';
    comment.value = annotation?.comment ?? '';
    save.textContent = annotation ? 'Save changes' : 'Save';
    if (annotation) {
      draft = [];
      status.textContent = 'Draw a new region to replace the old one, or keep it.';
      redraw();
    } else {
      startDrawing();
    }
    reference.focus();
  }

  function closeForm() {
    stopDrawing();
    draft = [];
    editing = null;
    form.hidden = true;
    newButton.hidden = !canAnnotate(me) || !model;
    status.textContent = '';
    redraw();
  }

  newButton.addEventListener('click', () => openForm(null));
  cancel.addEventListener('click', closeForm);

  form.addEventListener('submit', async (e) => {
    e.preventDefault();
    showError(error, null);
    const ref = normaliseReference(reference.value);
    if (!ref) {
      showError(error, `“${reference.value}” is not a reference like “o 2 3” (surface, line, sign).`);
      return;
    }
    const whole = Boolean(viewer.model?.parts);
    const gridOf = (part) => {
      const grid = viewer.model.tiles?.faceGrid?.(part); // a streamed tablet's face
      if (grid) return { width: grid.width_px, height: grid.height_px };
      const i = viewer.model.parts.names.indexOf(part);
      const img = viewer.model.assets.faces?.[i]?.normals?.image;
      return img ? { width: img.width, height: img.height } : null;
    };
    const text = { reference: ref, reading: reading.value.trim() || null, comment: comment.value.trim() || null };
    if (!editing && draft.length < 3) {
      showError(error, 'Draw the region first: click at least 3 points around the sign on the model.');
      return;
    }
    const region = draft.length >= 3 ? regionBody(draft, { whole, gridOf }) : {};
    try {
      if (editing) await api.updateAnnotation(editing.annotationId, { ...text, ...region });
      else await api.createAnnotation(model.id, { ...text, ...region });
    } catch (err) {
      showError(error, err.detail ?? err.message);
      return;
    }
    highlighted = ref;
    closeForm();
    await refresh();
  });

  async function remove(annotation) {
    if (!window.confirm(`Delete the annotation of ${annotation.reference.text}?`)) return;
    try {
      await api.deleteAnnotation(annotation.annotationId);
    } catch (err) {
      showError(error, err.detail ?? err.message);
      return;
    }
    await refresh();
  }

  return {
    setTablet,
    setModel,
    refresh,
    selectSign,
    stopDrawing,
    /** For tests and the console: what the panel holds. */
    get state() {
      return { items, highlighted, draft: draft.map((p) => ({ ...p })), drawing, modelId: model?.id ?? null };
    },
    regionsOf: (ref) => annotationsOfSign(items, ref),
  };
}
