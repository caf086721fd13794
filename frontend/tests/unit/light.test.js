import { describe, expect, it } from 'vitest';
import {
  anglesToDisc,
  compassLabel,
  discToAngles,
  lightAngles,
  lightDirection,
  RAKING_PRESETS,
} from '../../src/viewer/light.js';

const close = (a, b, eps = 1e-12) => a.forEach((v, i) => expect(v).toBeCloseTo(b[i], 12));

describe('lightDirection follows SCAN_BUNDLE.md', () => {
  it('φ = 0° lights from +y, the bottom edge of the image', () => {
    close(lightDirection(0, 90), [0, 1, 0]);
  });
  it('φ = 90° lights from +x, the right edge', () => {
    close(lightDirection(90, 90), [1, 0, 0]);
  });
  it('θ = 0° is straight from the camera (−z, the camera looks along +z)', () => {
    close(lightDirection(123, 0), [0, 0, -1]);
  });
  it('matches l = (sin θ sin φ, sin θ cos φ, −cos θ) for any angle and is a unit vector', () => {
    for (let k = 0; k < 50; k++) {
      const phi = -400 + 17.3 * k;
      const theta = (k * 1.7) % 90;
      const l = lightDirection(phi, theta);
      const p = (phi * Math.PI) / 180;
      const t = (theta * Math.PI) / 180;
      close(l, [Math.sin(t) * Math.sin(p), Math.sin(t) * Math.cos(p), -Math.cos(t)]);
      expect(Math.hypot(...l)).toBeCloseTo(1, 12);
    }
  });
  it('a face tilted toward the right edge (n_x > 0, n_z < 0) is lit by φ = 90° and dark by φ = 270°', () => {
    const n = [Math.sin(0.3), 0, -Math.cos(0.3)];
    const dot = (l) => l[0] * n[0] + l[1] * n[1] + l[2] * n[2];
    expect(dot(lightDirection(90, 75))).toBeGreaterThan(dot(lightDirection(270, 75)));
  });
  it('rejects polar angles outside [0, 90] and non-finite azimuths', () => {
    expect(() => lightDirection(0, 91)).toThrow(/polarDeg/);
    expect(() => lightDirection(Number.NaN, 10)).toThrow(/azimuthDeg/);
  });
});

describe('angles round-trip', () => {
  it('lightAngles inverts lightDirection', () => {
    for (const [a, p] of [[0, 30], [45, 60], [90, 89], [200, 10], [359, 45]]) {
      const back = lightAngles(lightDirection(a, p));
      expect(back.azimuthDeg).toBeCloseTo(a, 9);
      expect(back.polarDeg).toBeCloseTo(p, 9);
    }
  });
  it('the widget disc shows the light where it projects on the image (y down)', () => {
    const [dx, dy] = anglesToDisc(0, 90);
    expect(dx).toBeCloseTo(0, 12);
    expect(dy).toBeCloseTo(1, 12); // bottom of the disc = bottom edge of the image
    for (const [a, p] of [[0, 30], [90, 45], [225, 70]]) {
      const back = discToAngles(...anglesToDisc(a, p));
      expect(back.azimuthDeg).toBeCloseTo(a, 9);
      expect(back.polarDeg).toBeCloseTo(p, 9);
    }
  });
  it('a drag outside the disc is clamped to a grazing light', () => {
    expect(discToAngles(3, 0).polarDeg).toBe(89);
    expect(discToAngles(3, 0).azimuthDeg).toBeCloseTo(90, 9);
  });
});

describe('raking presets', () => {
  it('come from eight azimuths 45° apart, named by image edge', () => {
    expect(RAKING_PRESETS.map((p) => p.azimuthDeg)).toEqual([0, 45, 90, 135, 180, 225, 270, 315]);
    expect(compassLabel(90)).toBe('right');
    expect(compassLabel(180)).toBe('top');
    expect(compassLabel(-90)).toBe('left');
  });
});
