import { describe, expect, it } from 'vitest';
import { apiParams, formatSearch, pageList, parseSearch, toggleFacet } from '../../src/library/searchState.js';

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
});
