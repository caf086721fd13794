import { describe, expect, it } from 'vitest';
import { lightDirection } from '../../src/viewer/light.js';
import { cornerMatrix, describePhoto, nearestPhoto } from '../../src/viewer/photos.js';

const photo = (az, polar, kind = 'photometric') => ({
  file: `photos/${kind}-${az}.jpg`,
  kind,
  azimuth_deg: az,
  polar_deg: polar,
  light: lightDirection(az, polar),
});
const index = { photos: [0, 45, 90, 135, 180, 225, 270, 315].map((a) => photo(a, 45)) };

describe('nearestPhoto', () => {
  it('picks the photograph whose light is closest, with the angle between them', () => {
    const found = nearestPhoto(index, lightDirection(100, 45));
    expect(found.photo.azimuth_deg).toBe(90);
    expect(found.angleDeg).toBeGreaterThan(5);
    expect(found.angleDeg).toBeLessThan(10);
    expect(nearestPhoto(index, lightDirection(315, 45)).angleDeg).toBeLessThan(1e-3);
  });

  it('wraps azimuth around 360° and ignores entries without a light', () => {
    const found = nearestPhoto({ photos: [...index.photos, { file: 'x', light: null }] }, lightDirection(355, 45));
    expect(found.photo.azimuth_deg).toBe(0);
  });

  it('returns null with no photographs', () => {
    expect(nearestPhoto({ photos: [] }, [0, 0, -1])).toBeNull();
    expect(nearestPhoto(null, [0, 0, -1])).toBeNull();
  });
});

describe('cornerMatrix', () => {
  it('maps the image corners onto the projected ones', () => {
    const m = cornerMatrix(200, 100, { x: 10, y: 20 }, { x: 410, y: 20 }, { x: 10, y: 220 });
    expect(m).toBe('matrix(2, 0, 0, 2, 10, 20)');
    // A quarter turn: the image's x axis runs down the page.
    expect(cornerMatrix(100, 100, { x: 0, y: 0 }, { x: 0, y: 100 }, { x: -100, y: 0 })).toBe('matrix(0, 1, -1, 0, 0, 0)');
  });
});

describe('describePhoto', () => {
  it('says which light and how far from the render', () => {
    expect(describePhoto({ photo: photo(90, 45, 'color'), angleDeg: 12.3 })).toBe(
      "Colour photograph taken under the light at azimuth 90°, polar 45° (12° from the render's light).",
    );
    expect(describePhoto({ photo: photo(0, 45), angleDeg: 0 })).toMatch(/the same light as the render/);
  });
});
