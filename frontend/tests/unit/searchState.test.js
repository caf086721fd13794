import { describe, expect, it } from 'vitest';
import {
  activeChips,
  apiParams,
  clearSearch,
  formatSearch,
  pageList,
  parseSearch,
  sameFacetValue,
  toggleFacet,
} from '../../src/library/searchState.js';

describe('library search state', () => {
  it('round-trips through the page URL', () => {
    const state = { q: 'Hammurabi code', filters: { period: 'Old Babylonian', has_3d: 'true' }, sort: 'designation', page: 3 };
    expect(parseSearch(formatSearch(state))).toEqual(state);
    expect(formatSearch({ q: '', filters: {}, sort: '', page: 1 })).toBe('');
  });
  it('asks the API for one page of results with the filters', () => {
    const params = apiParams(parseSearch('?q=ur&genre=Letter&page=2'));
    expect(params).toEqual({ q: 'ur', genre: 'Letter', sort: undefined, page: 2, page_size: 24 });
  });
  it('toggles facet values and goes back to the first page', () => {
    const s = parseSearch('?period=Ur%20III&page=4');
    expect(toggleFacet(s, 'period', 'Ur III').filters).toEqual({});
    const t = toggleFacet(s, 'genre', 'Legal');
    expect(t.filters).toEqual({ period: 'Ur III', genre: 'Legal' });
    expect(t.page).toBe(1);
  });
  it('ignores nonsense pages and sorts', () => {
    expect(parseSearch('?page=-3&sort=drop').page).toBe(1);
    expect(parseSearch('?page=-3&sort=drop').sort).toBe('');
  });
  it('lists pages around the current one with gaps', () => {
    expect(pageList(5, 24 * 10)).toEqual([1, null, 4, 5, 6, null, 10]);
    expect(pageList(1, 0)).toEqual([1]);
  });
  it('shows the text and each filter as a chip that removes just itself', () => {
    const s = parseSearch('?q=ur%20iii&genre=mathematical&period=Ur%20III&has_3d=true&sort=period&page=3');
    const chips = activeChips(s);
    expect(chips.map((c) => [c.key, c.label])).toEqual([
      ['q', '“ur iii”'],
      ['period', 'Ur III'],
      ['genre', 'mathematical'],
      ['has_3d', 'with 3-D model'],
    ]);
    const withoutPeriod = chips[1].next;
    expect(withoutPeriod.filters).toEqual({ genre: 'mathematical', has_3d: 'true' });
    expect(withoutPeriod.q).toBe('ur iii');
    expect(withoutPeriod.page).toBe(1);
    expect(chips[0].next.q).toBe('');
    expect(activeChips(parseSearch(''))).toEqual([]);
    const cleared = clearSearch(s);
    expect([cleared.q, cleared.filters, cleared.sort, cleared.page]).toEqual(['', {}, 'period', 1]);
  });
  it('treats facet values that differ in case as one (the API groups them)', () => {
    expect(sameFacetValue('Mathematical', 'mathematical')).toBe(true);
    expect(sameFacetValue('Ur III', 'Ur II')).toBe(false);
    const s = parseSearch('?genre=Mathematical');
    expect(toggleFacet(s, 'genre', 'mathematical').filters).toEqual({});
  });
});
