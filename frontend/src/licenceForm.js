/**
 * The model's licence and attribution on the tablet page (issue 18): everyone reads the ones
 * that apply (`effective_licence`, `effective_attribution` of GET /models/{id}); staff of the
 * institution that holds the tablet, and admins, set the model's own with
 * PATCH /models/{id} (docs/api.md, "Licences and attribution"). The API decides; the form is
 * only hidden from those it would refuse.
 */
import * as api from './api.js';
import { el, showError } from './dom.js';

/** Licences offered in the form's list (any Creative Commons or RightsStatements.org URI is accepted). */
export const SUGGESTED_LICENCES = Object.freeze([
  'https://creativecommons.org/licenses/by/4.0/',
  'https://creativecommons.org/licenses/by-sa/4.0/',
  'https://creativecommons.org/licenses/by-nc/4.0/',
  'https://creativecommons.org/publicdomain/zero/1.0/',
  'http://rightsstatements.org/vocab/InC/1.0/',
]);

/** May `me` set the licence of a model of `tablet`? Admins, and staff of its institution. */
export function canSetLicence(me, tablet) {
  if (!me || !tablet) return false;
  if (me.role === 'admin') return true;
  return me.role === 'staff' && me.institution_id != null && me.institution_id === tablet.institution_id;
}

/**
 * The PATCH body from the form's fields: a blank field clears the model's own value (null:
 * the tablet's or institution's applies again); text is trimmed.
 * @returns {{licence: string|null, attribution: string|null}}
 */
export function licenceBody(licence, attribution) {
  const clean = (v) => (String(v ?? '').trim() ? String(v).trim() : null);
  return { licence: clean(licence), attribution: clean(attribution) };
}

/** An API error as one sentence for the form: the server's message and the field it names. */
export function describeLicenceError(err) {
  if (err?.status === 401) return 'Sign in (Staff page) to set the licence.';
  if (err?.status === 403) return `Not allowed: ${err.detail ?? err.message}`;
  const problems = (err?.problems ?? []).map((p) => `${p.where}: ${p.message}`);
  if (problems.length) return `The licence was not saved: ${problems.join('; ')}`;
  return `The licence was not saved: ${err?.message ?? err}`;
}

/**
 * @param {{container: HTMLElement, onSaved: (model: object) => void}} options
 *   onSaved receives the model record the API returned (with the new effective values)
 * @returns {{setContext(me: object|null, tablet: object): void, setModel(model: object|null): void}}
 */
export function bindLicenceForm({ container, onSaved }) {
  const shown = el('p', { id: 'licence-shown' });
  const licence = el('input', { id: 'licence-uri', type: 'url', list: 'licence-suggestions', size: 30, placeholder: 'blank: the tablet’s' });
  const attribution = el('input', { id: 'licence-attribution', type: 'text', size: 30, placeholder: 'blank: the tablet’s' });
  const list = el('datalist', { id: 'licence-suggestions' }, ...SUGGESTED_LICENCES.map((u) => el('option', { value: u })));
  const save = el('button', { type: 'submit', id: 'licence-save' }, 'Save licence');
  const status = el('p', { id: 'licence-status', class: 'muted', role: 'status' });
  const error = el('p', { id: 'licence-error', class: 'error', role: 'alert', hidden: true });
  const form = el(
    'form',
    { id: 'licence-form', hidden: true },
    el('label', {}, 'Licence (URI) ', licence),
    list,
    el('label', {}, 'Attribution ', attribution),
    el('div', { class: 'buttons' }, save),
    status,
    error,
  );
  container.replaceChildren(el('h2', {}, 'Licence'), shown, form);
  container.hidden = true;
  let me = null;
  let tablet = null;
  let model = null;

  function render() {
    container.hidden = !model;
    if (!model) return;
    const text = model.effective_licence ?? 'none stated';
    const credit = model.effective_attribution ? ` · ${model.effective_attribution}` : '';
    const own = model.licence || model.attribution ? ' (this model’s own)' : '';
    shown.textContent = `${text}${credit}${own}`;
    form.hidden = !canSetLicence(me, tablet);
  }

  form.addEventListener('submit', async (event) => {
    event.preventDefault();
    if (!model) return;
    showError(error, null);
    status.textContent = 'Saving…';
    save.disabled = true;
    try {
      const saved = await api.updateModel(model.id, licenceBody(licence.value, attribution.value));
      model = { ...model, ...saved };
      status.textContent = 'Saved.';
      render();
      onSaved(saved);
    } catch (err) {
      status.textContent = '';
      showError(error, describeLicenceError(err));
    } finally {
      save.disabled = false;
    }
  });

  return {
    setContext(nextMe, nextTablet) {
      me = nextMe;
      tablet = nextTablet;
      container.dataset.context = me ? me.role : 'anonymous'; // who the form was decided for
      render();
    },
    setModel(next) {
      model = next;
      licence.value = next?.licence ?? '';
      attribution.value = next?.attribution ?? '';
      status.textContent = '';
      showError(error, null);
      render();
    },
  };
}
