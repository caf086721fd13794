import { describe, expect, it } from 'vitest';
import { applyHiddenParts, createPartToggles, hiddenParts } from '../../src/viewer/parts.js';

describe('createPartToggles', () => {
  it('shows every part at first', () => {
    const t = createPartToggles(['obverse', 'reverse']);
    expect(t.visibleNames()).toEqual(['obverse', 'reverse']);
    expect([0, 1].map(t.groupMaterialIndex)).toEqual([0, 0]);
  });

  it('hides and shows a part, reporting only real changes', () => {
    const t = createPartToggles(['obverse', 'reverse', 'top']);
    expect(t.set('reverse', false)).toBe(true);
    expect(t.set('reverse', false)).toBe(false);
    expect(t.isVisible('reverse')).toBe(false);
    expect(t.visibleNames()).toEqual(['obverse', 'top']);
    expect([0, 1, 2].map(t.groupMaterialIndex)).toEqual([0, 1, 0]);
    expect(t.set('reverse', true)).toBe(true);
    expect(t.visibleNames()).toEqual(['obverse', 'reverse', 'top']);
  });

  it('names blank and repeated parts uniquely', () => {
    const t = createPartToggles(['obverse', '', 'obverse', null]);
    expect(t.names).toEqual(['obverse', 'part 2', 'obverse (2)', 'part 4']);
    t.set('obverse (2)', false);
    expect(t.isVisible('obverse')).toBe(true);
    expect(t.groupMaterialIndex(2)).toBe(1);
  });

  it('rejects unknown parts and bad input', () => {
    const t = createPartToggles(['obverse']);
    expect(() => t.set('left', false)).toThrow(/no part named "left"/);
    expect(() => createPartToggles('obverse')).toThrow(TypeError);
  });
});

describe('applyHiddenParts (the hidden faces of a permalink)', () => {
  it('hides exactly the named parts and shows the others', () => {
    const t = createPartToggles(['obverse', 'reverse', 'top']);
    t.set('obverse', false);
    expect(applyHiddenParts(t, ['top', 'reverse'])).toEqual({ changed: true, unknown: [] });
    expect(t.visibleNames()).toEqual(['obverse']);
    expect(hiddenParts(t)).toEqual(['reverse', 'top']); // part order, not the link's
    expect(applyHiddenParts(t, ['reverse', 'top'])).toEqual({ changed: false, unknown: [] });
    expect(applyHiddenParts(t, [])).toEqual({ changed: true, unknown: [] });
    expect(hiddenParts(t)).toEqual([]);
  });

  it('returns unknown names instead of throwing, and applies the known ones', () => {
    const t = createPartToggles(['obverse', 'reverse']);
    expect(applyHiddenParts(t, ['left', 'reverse', 'part 9'])).toEqual({ changed: true, unknown: ['left', 'part 9'] });
    expect(t.visibleNames()).toEqual(['obverse']);
  });

  it('copes with a model without parts and with junk', () => {
    expect(applyHiddenParts(null, ['reverse'])).toEqual({ changed: false, unknown: ['reverse'] });
    expect(hiddenParts(null)).toEqual([]);
    const t = createPartToggles(['obverse', 'reverse']);
    expect(applyHiddenParts(t, 'reverse')).toEqual({ changed: false, unknown: [] });
    expect(applyHiddenParts(t, [42, null, 'reverse'])).toEqual({ changed: true, unknown: [] });
    expect(hiddenParts(t)).toEqual(['reverse']);
  });
});
