/**
 * The library search as URL state: `index.html?q=…&period=…&page=2` ↔ the API's query
 * parameters (GET /api/v1/tablets). Pure functions, so a search is a link.
 */

export const FACETS = Object.freeze([
  ['period', 'Period'],
  ['provenience', 'Provenience'],
  ['genre', 'Genre'],
  ['collection', 'Collection'],
  ['language', 'Language'],
  ['has_3d', '3-D model'],
]);

export const SORTS = Object.freeze([
  ['', 'Relevance'],
  ['designation', 'Designation'],
  ['-created_at', 'Newest'],
  ['period', 'Period'],
]);

export const PAGE_SIZE = 24;

/**
 * @param {string} search location.search
 * @returns {{q: string, filters: Record<string, string>, sort: string, page: number}}
 */
export function parseSearch(search) {
  const p = new URLSearchParams(search);
  const filters = {};
  for (const [key] of FACETS) {
    const v = p.get(key);
    if (v !== null && v !== '') filters[key] = key === 'has_3d' ? String(v === 'true' || v === '1') : v;
  }
  const page = Number.parseInt(p.get('page') ?? '1', 10);
  return {
    q: p.get('q') ?? '',
    filters,
    sort: SORTS.some(([v]) => v === p.get('sort')) ? p.get('sort') : '',
    page: Number.isFinite(page) && page >= 1 ? page : 1,
  };
}

/** The state as a query string (for the page URL), without empty fields. */
export function formatSearch(state) {
  const p = new URLSearchParams();
  if (state.q) p.set('q', state.q);
  for (const [key] of FACETS) if (state.filters[key] !== undefined) p.set(key, state.filters[key]);
  if (state.sort) p.set('sort', state.sort);
  if (state.page > 1) p.set('page', String(state.page));
  const text = p.toString();
  return text ? `?${text}` : '';
}

/** The API's query parameters for a state. */
export function apiParams(state) {
  return {
    q: state.q || undefined,
    ...state.filters,
    sort: state.sort || undefined,
    page: state.page,
    page_size: PAGE_SIZE,
  };
}

/** A new state with a facet value toggled (and back to page 1). */
export function toggleFacet(state, key, value) {
  const filters = { ...state.filters };
  const v = String(value);
  if (filters[key] !== undefined && sameFacetValue(filters[key], v)) delete filters[key];
  else filters[key] = v;
  return { ...state, filters, page: 1 };
}

/** Whether facet value `a` is `b` (values are grouped regardless of case by the API). */
export function sameFacetValue(a, b) {
  return String(a).toLowerCase() === String(b).toLowerCase();
}

/**
 * The search's active parts as removable chips, in reading order: the text, then each filter
 * in the order of FACETS. `next` is the state without that part.
 * @returns {{key: string, title: string, label: string, next: object}[]}
 */
export function activeChips(state) {
  const chips = [];
  if (state.q) chips.push({ key: 'q', title: 'Text', label: `“${state.q}”`, next: { ...state, q: '', page: 1 } });
  for (const [key, title] of FACETS) {
    const v = state.filters[key];
    if (v === undefined) continue;
    const filters = { ...state.filters };
    delete filters[key];
    const label = key === 'has_3d' ? (v === 'true' ? 'with 3-D model' : 'without 3-D model') : v;
    chips.push({ key, title, label, next: { ...state, filters, page: 1 } });
  }
  return chips;
}

/** The state with no text and no filter (sort kept). */
export function clearSearch(state) {
  return { ...state, q: '', filters: {}, page: 1 };
}

/** Page numbers to offer around the current page ("…" as null), for `total` results. */
export function pageList(page, total, pageSize = PAGE_SIZE) {
  const last = Math.max(1, Math.ceil(total / pageSize));
  const wanted = new Set([1, last, page - 1, page, page + 1].filter((n) => n >= 1 && n <= last));
  const sorted = [...wanted].sort((a, b) => a - b);
  const out = [];
  for (let i = 0; i < sorted.length; i++) {
    if (i && sorted[i] - sorted[i - 1] > 1) out.push(null);
    out.push(sorted[i]);
  }
  return out;
}
