import { describe, expect, it } from 'vitest';
import { distanceMm, pixelSizeFromMesh } from '../../src/viewer/measure.js';

describe('measuring', () => {
  it('measures Euclidean distances in mm', () => {
    expect(distanceMm([0, 0, 0], [3, 4, 12])).toBe(13);
  });
  it('recovers the pixel size from the image-grid texture coordinates of the mesh', () => {
    // 640 × 480 grid at 42.5 µm, vertices every 16 px: x = c·s/1000, u = (c + 0.5)/W
    const W = 640;
    const s = 42.5;
    const positions = [];
    const uvs = [];
    for (let r = 0; r < 480; r += 16) {
      for (let c = 0; c < W; c += 16) {
        positions.push((c * s) / 1000, (r * s) / 1000, -0.3);
        uvs.push((c + 0.5) / W, (r + 0.5) / 480);
      }
    }
    expect(pixelSizeFromMesh(positions, uvs, W)).toBeCloseTo(s, 9);
  });
  it('refuses a mesh without extent', () => {
    expect(() => pixelSizeFromMesh([0, 0, 0, 0, 1, 0], [0.5, 0.1, 0.5, 0.9], 10)).toThrow(/width/);
  });
});
