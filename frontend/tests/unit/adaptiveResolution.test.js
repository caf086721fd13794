import { describe, expect, it } from 'vitest';
import { createAdaptiveResolution, MIN_SCALE, nextResolutionScale, quantizeScale, TARGET_FRAME_MS } from '../../src/viewer/adaptiveResolution.js';

describe('nextResolutionScale', () => {
  it('keeps the frame-time target: the pixel count follows target / measured', () => {
    // 20 % too slow at scale 0.8: the scale that meets the target is 0.8 / sqrt(1.2).
    expect(nextResolutionScale(0.8, 1.2 * TARGET_FRAME_MS)).toBeCloseTo(0.8 / Math.sqrt(1.2), 10);
    // fast frames grow the scale again, by at most 1.25 a frame, never past full resolution
    expect(nextResolutionScale(0.5, TARGET_FRAME_MS / 4)).toBeCloseTo(0.625, 10);
    expect(nextResolutionScale(0.9, 1)).toBe(1);
  });

  it('halves at most per frame and stays above the floor', () => {
    expect(nextResolutionScale(1, 2000)).toBe(0.5);
    expect(nextResolutionScale(0.3, 2000)).toBe(MIN_SCALE);
    expect(nextResolutionScale(0.3, 2000, { minScale: 0.1 })).toBeCloseTo(0.15, 10);
  });

  it('ignores a frame time it cannot use and rejects a bad scale', () => {
    expect(nextResolutionScale(0.6, 0)).toBe(0.6);
    expect(nextResolutionScale(0.6, Number.NaN)).toBe(0.6);
    expect(() => nextResolutionScale(0, 10)).toThrow(RangeError);
  });
});

/** A clock of timers run by hand. */
function manualTimers() {
  const timers = new Map();
  let id = 0;
  return {
    setTimer: (f, ms) => {
      timers.set(++id, { f, ms });
      return id;
    },
    clearTimer: (t) => timers.delete(t),
    fire() {
      const all = [...timers.values()];
      timers.clear();
      for (const t of all) t.f();
    },
    get pending() {
      return timers.size;
    },
  };
}

describe('quantizeScale', () => {
  it('rounds down to steps of sqrt(2), at least the minimum, so the drawing buffer keeps a size', () => {
    expect(quantizeScale(1)).toBe(1);
    expect(quantizeScale(0.99)).toBeCloseTo(Math.SQRT1_2, 12);
    expect(quantizeScale(Math.SQRT1_2)).toBeCloseTo(Math.SQRT1_2, 12);
    expect(quantizeScale(0.6)).toBe(0.5);
    expect(quantizeScale(0.5)).toBe(0.5);
    expect(quantizeScale(0.4)).toBeCloseTo(0.5 * Math.SQRT1_2, 12);
    expect(quantizeScale(0.1)).toBe(MIN_SCALE);
    expect(quantizeScale(0.1, 0.05)).toBeCloseTo(2 ** -3.5, 12);
    expect(() => quantizeScale(0)).toThrow(RangeError);
  });

  it('is what a moving frame is drawn at, while the learned scale stays off the ladder', () => {
    const a = createAdaptiveResolution({ onSettle: () => {}, ...manualTimers() });
    a.moved();
    a.frame(0);
    a.moved();
    // a 45 ms frame: learned sqrt(33.3 / 45) = 0.86, drawn at the step below, 1/sqrt(2)
    expect(a.frame(45)).toBeCloseTo(Math.SQRT1_2, 12);
    expect(a.scale).toBeCloseTo(Math.sqrt(TARGET_FRAME_MS / 45), 12);
  });
});

describe('createAdaptiveResolution', () => {
  it('draws at full resolution when still, lower while slow frames move, full again once settled', () => {
    const clock = manualTimers();
    let settled = 0;
    const a = createAdaptiveResolution({ onSettle: () => settled++, ...clock });
    expect(a.frame(0)).toBe(1); // still: full
    // moving, 1 s a frame (a software renderer under load)
    let t = 0;
    const scales = [];
    for (let i = 0; i < 4; i++) {
      a.moved();
      scales.push(a.frame(t));
      t += 1000;
    }
    expect(scales[0]).toBe(1); // nothing measured yet
    expect(scales[1]).toBe(0.5);
    expect(scales[3]).toBe(MIN_SCALE);
    expect(a.moving).toBe(true);
    expect(clock.pending).toBe(1); // one settle timer, re-armed by each move
    clock.fire();
    expect(settled).toBe(1);
    expect(a.moving).toBe(false);
    expect(a.frame(t)).toBe(1);
    // the next interaction starts at the learned scale
    a.moved();
    expect(a.frame(t + 5000)).toBe(MIN_SCALE);
  });

  it('waits longer than a slow frame before settling, and measures across it', () => {
    const clock = manualTimers();
    let settled = 0;
    const a = createAdaptiveResolution({ onSettle: () => settled++, ...clock });
    a.moved();
    a.frame(0);
    clock.fire(); // the first settle (200 ms) passed while the frame was being drawn
    expect(settled).toBe(1);
    a.moved(); // the next move lands with that full-resolution frame's request
    expect(a.frame(3000)).toBe(0.5); // measured: 3 s a frame
    a.moved();
    expect(clock.pending).toBe(1);
    expect(a.frame(6000)).toBe(MIN_SCALE);
  });

  it('does not count a pause between two moves as frame cost', () => {
    const clock = manualTimers();
    const a = createAdaptiveResolution({ onSettle: () => {}, ...clock });
    a.moved();
    a.frame(0);
    a.frame(16); // a frame without a move (e.g. a tile arrived): the run of moving frames ends
    a.moved();
    expect(a.frame(3000)).toBe(1);
  });

  it('can be turned off: every frame at full resolution', () => {
    const clock = manualTimers();
    let settled = 0;
    const a = createAdaptiveResolution({ onSettle: () => settled++, ...clock });
    a.moved();
    a.frame(0);
    a.moved();
    a.frame(1000);
    a.setEnabled(false);
    expect(settled).toBe(1);
    a.moved();
    expect(a.frame(2000)).toBe(1);
  });
});
