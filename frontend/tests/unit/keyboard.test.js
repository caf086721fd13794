import { describe, expect, it } from 'vitest';
import { actionForKey, SHORTCUTS } from '../../src/viewer/keyboard.js';

describe('keyboard shortcuts', () => {
  it('map each key to one action only', () => {
    const seen = new Map();
    for (const s of SHORTCUTS) {
      for (const k of s.keys) {
        expect(seen.has(k), `key ${k} is bound twice`).toBe(false);
        seen.set(k, s.action);
      }
    }
  });
  it('dispatch light, mode and view keys, with Shift for fine steps', () => {
    expect(actionForKey({ key: 'ArrowLeft', shiftKey: true })).toEqual({ action: 'light-azimuth', key: 'ArrowLeft', fine: true });
    expect(actionForKey({ key: '3' }).action).toBe('raking');
    expect(actionForKey({ key: 'N', shiftKey: true }).action).toBe('mode:normals');
    expect(actionForKey({ key: 'n' }).action).toBe('mode:natural');
    expect(actionForKey({ key: 'r' }).action).toBe('view:reverse');
  });
  it('leave typing in form fields and browser shortcuts alone', () => {
    expect(actionForKey({ key: 'n', target: { tagName: 'INPUT' } })).toBeNull();
    expect(actionForKey({ key: 's', ctrlKey: true })).toBeNull();
    expect(actionForKey({ key: 'F5' })).toBeNull();
  });
});
