import { describe, expect, it } from 'vitest';
import {
  anglesToDisc,
  cameraLightToWorld,
  cameraLightToWorldAngles,
  compassLabel,
  worldLightToCameraAngles,
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
  it('reaches the whole sphere: θ = 180° lights from straight behind the view plane', () => {
    close(lightDirection(0, 180), [0, 0, 1]);
    close(lightDirection(90, 135), [Math.SQRT1_2, 0, Math.SQRT1_2]);
  });
  it('rejects polar angles outside [0, 180] and non-finite azimuths', () => {
    expect(() => lightDirection(0, 181)).toThrow(/polarDeg/);
    expect(() => lightDirection(0, -1)).toThrow(/polarDeg/);
    expect(() => lightDirection(Number.NaN, 10)).toThrow(/azimuthDeg/);
  });
});

describe('angles round-trip', () => {
  it('lightAngles inverts lightDirection', () => {
    for (const [a, p] of [[0, 30], [45, 60], [90, 89], [200, 10], [359, 45], [120, 150], [300, 91]]) {
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

describe('light relative to the camera', () => {
  // The reverse view of views.js: looking along −z, screen-up +y, so screen-right is +x.
  const reverse = { right: [1, 0, 0], up: [0, 1, 0], dir: [0, 0, -1] };
  it('on the obverse view it is the scan frame itself', () => {
    const obverse = { right: [1, 0, 0], up: [0, -1, 0], dir: [0, 0, 1] };
    for (const [a, p] of [[0, 75], [135, 40], [270, 120]]) close(cameraLightToWorld(a, p, obverse), lightDirection(a, p));
  });
  it('from the camera on the reverse view is a light from +z, behind the obverse', () => {
    close(cameraLightToWorld(0, 0, reverse), [0, 0, 1]);
    expect(cameraLightToWorldAngles(0, 0, reverse).polarDeg).toBeCloseTo(180, 9);
  });
  it('a raking light from the left of the screen on the reverse comes from −x', () => {
    const l = cameraLightToWorld(270, 90, reverse); // φ = 270°: from the left of the screen
    close(l, [-1, 0, 0]);
    const a = cameraLightToWorldAngles(270, 75, reverse);
    expect(a.polarDeg).toBeGreaterThan(90); // behind the obverse's view plane
    close(lightDirection(a.azimuthDeg, a.polarDeg), cameraLightToWorld(270, 75, reverse));
  });
  it('worldLightToCameraAngles inverts cameraLightToWorld on any view', () => {
    const top = { right: [1, 0, 0], up: [0, 0, 1], dir: [0, 1, 0] }; // views.js' top edge
    for (const cam of [reverse, top]) {
      for (const [a, p] of [[30, 20], [200, 75], [300, 150]]) {
        const back = worldLightToCameraAngles(cameraLightToWorld(a, p, cam), cam);
        expect(back.azimuthDeg).toBeCloseTo(a, 9);
        expect(back.polarDeg).toBeCloseTo(p, 9);
      }
    }
  });
});
