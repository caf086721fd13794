/**
 * The library page: search box, facets with counts, result grid with thumbnails, paging.
 * The URL holds the search (see searchState.js), so every search is a link and Back works.
 */
import * as api from '../api.js';
import { el, showError } from '../dom.js';
import {
  activeChips,
  apiParams,
  clearSearch,
  FACETS,
  formatSearch,
  pageList,
  parseSearch,
  sameFacetValue,
  SORTS,
  toggleFacet,
} from './searchState.js';

const $ = (id) => document.getElementById(id);
let state = parseSearch(window.location.search);
let controller = null;

for (const [value, label] of SORTS) $('sort').append(el('option', { value }, label));

function go(next, { push = true, clicked = null } = {}) {
  state = next;
  if (push) history.pushState(null, '', `${window.location.pathname}${formatSearch(state)}`);
  run(clicked);
}

function facetLabel(key, value) {
  if (key === 'has_3d') return value === true || value === 'true' ? 'with 3-D model' : 'without 3-D model';
  return value === null || value === '' ? '(unknown)' : String(value);
}

function renderFacets(facets, clicked) {
  const box = $('facets');
  box.replaceChildren();
  for (const [key, title] of FACETS) {
    let values = (facets?.[key] ?? []).filter(({ value }) => value !== null);
    const active = state.filters[key];
    if (!values.length && active === undefined) continue;
    if (active !== undefined) {
      // The chosen value heads its group, so it stays in sight after the click.
      const chosen = values.find(({ value }) => sameFacetValue(value, active)) ?? { value: active, count: 0 };
      values = [chosen, ...values.filter((v) => v !== chosen)];
    }
    const list = el('ul', {});
    for (const { value, count } of values) {
      const on = active !== undefined && sameFacetValue(active, value);
      const button = el(
        'button',
        { type: 'button', class: on ? 'facet on' : 'facet', 'aria-pressed': String(on), 'data-facet': key, 'data-value': String(value) },
        el('span', { class: 'facet-value' }, facetLabel(key, value)),
        el('span', { class: 'count' }, count),
      );
      button.addEventListener('click', () => go(toggleFacet(state, key, value), { clicked: key }));
      list.append(el('li', {}, button));
    }
    const group = el('section', { class: 'facet-group', 'data-group': key }, el('h2', {}, title), list);
    box.append(group);
    if (clicked === key) group.scrollIntoView({ block: 'nearest' });
  }
}

function renderChips() {
  const box = $('chips');
  const chips = activeChips(state);
  box.replaceChildren();
  box.hidden = !chips.length;
  for (const chip of chips) {
    const button = el(
      'button',
      { type: 'button', class: 'chip', 'data-chip': chip.key, title: `Remove this filter (${chip.title})` },
      el('span', { class: 'chip-title' }, `${chip.title}:`),
      ' ',
      el('span', { class: 'chip-label' }, chip.label),
      el('span', { class: 'chip-x', 'aria-hidden': 'true' }, ' ×'),
    );
    button.setAttribute('aria-label', `Remove ${chip.title}: ${chip.label}`);
    button.addEventListener('click', () => go(chip.next));
    box.append(button);
  }
  if (chips.length > 1) {
    const clear = el('button', { type: 'button', class: 'chip clear', 'data-chip': 'all' }, 'Clear all');
    clear.addEventListener('click', () => go(clearSearch(state)));
    box.append(clear);
  }
}

function thumbnailImg(url) {
  return el('img', { src: api.assetHref(url), alt: '', loading: 'lazy', width: 160, height: 160 });
}

// Until the search API returns a thumbnail with each tablet, a tablet with a 3-D model that
// scrolls into view asks for its scans once and shows the newest model's thumbnail.png.
const lazyThumbs = new IntersectionObserver((entries) => {
  for (const entry of entries) {
    if (!entry.isIntersecting) continue;
    lazyThumbs.unobserve(entry.target);
    const holder = entry.target;
    api
      .tabletScans(holder.dataset.tablet)
      .then((scans) => {
        const models = scans.flatMap((s) => s.models ?? []).filter((m) => m.assets?.['thumbnail.png']);
        const newest = models.sort((a, b) => String(b.created_at).localeCompare(String(a.created_at)))[0];
        if (newest && holder.isConnected) holder.replaceWith(thumbnailImg(newest.assets['thumbnail.png']));
      })
      .catch(() => {}); // the placeholder stays: a thumbnail is not worth an error message
  }
});

function thumbnailOf(item) {
  const url = item.thumbnail_url ?? item.thumbnail ?? null;
  if (url) return thumbnailImg(url);
  const holder = el('div', { class: 'placeholder', 'aria-hidden': 'true', 'data-tablet': item.id }, item.has_3d ? '3-D' : '—');
  if (item.has_3d) lazyThumbs.observe(holder);
  return holder;
}

function renderResults(page) {
  const list = $('results');
  list.replaceChildren();
  for (const item of page.items) {
    const meta = [item.period, item.provenience, item.genre].filter(Boolean).join(' · ');
    const card = el(
      'li',
      { class: 'card' },
      el(
        'a',
        { href: `./tablet.html?id=${encodeURIComponent(item.id)}` },
        thumbnailOf(item),
        el('strong', { class: 'designation' }, item.designation),
        item.museum_no ? el('span', { class: 'museum' }, item.museum_no) : null,
        el('span', { class: 'meta' }, meta),
        item.has_3d ? el('span', { class: 'badge' }, '3-D') : null,
      ),
    );
    list.append(card);
  }
  const from = page.total ? (page.page - 1) * page.page_size + 1 : 0;
  const to = Math.min(page.total, page.page * page.page_size);
  $('summary').textContent = page.total
    ? `${page.total.toLocaleString('en')} tablet${page.total === 1 ? '' : 's'} — showing ${from}–${to}`
    : 'No tablet matches this search.';
  const pager = $('pager');
  pager.replaceChildren();
  for (const n of pageList(page.page, page.total, page.page_size)) {
    if (n === null) {
      pager.append(el('span', { class: 'gap' }, '…'));
      continue;
    }
    const b = el('button', { type: 'button', 'aria-current': n === page.page ? 'page' : null }, n);
    b.addEventListener('click', () => go({ ...state, page: n }));
    pager.append(b);
  }
  const params = apiParams(state);
  delete params.page;
  delete params.page_size;
  $('export-csv').href = api.searchUrl(params, 'csv');
  $('export-jsonl').href = api.searchUrl(params, 'jsonl');
}

async function run(clicked = null) {
  $('q').value = state.q;
  $('sort').value = state.sort;
  controller?.abort();
  controller = new AbortController();
  document.body.classList.add('busy');
  try {
    const page = await api.searchTablets(apiParams(state), { signal: controller.signal });
    showError($('search-error'), '');
    renderChips();
    renderFacets(page.facets, clicked);
    renderResults(page);
    document.body.dataset.total = String(page.total);
  } catch (err) {
    if (err.name === 'AbortError') return;
    showError($('search-error'), `Search failed: ${err.message}`);
  } finally {
    document.body.classList.remove('busy');
  }
}

$('search-form').addEventListener('submit', (e) => {
  e.preventDefault();
  go({ ...state, q: $('q').value.trim(), sort: $('sort').value, page: 1 });
});
$('sort').addEventListener('change', () => go({ ...state, sort: $('sort').value, page: 1 }));
window.addEventListener('popstate', () => go(parseSearch(window.location.search), { push: false }));
run();
