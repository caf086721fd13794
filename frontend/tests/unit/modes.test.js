import { describe, expect, it } from 'vitest';
import { missingMessage } from '../../src/viewer/modes.js';

const full = () => ({
  names: { curvature: ['curvature.png', 'curvature_coarse.png'], accessibility: 'accessibility.png', quality: ['quality/r.npy'] },
  normals: {},
  albedo: {},
  curvature: null,
  accessibility: null,
  quality: null,
});

describe('missing textures are named in the UI', () => {
  it('says nothing when every map is there and loaded', () => {
    const a = { ...full(), curvature: [{}], accessibility: {}, quality: [{}] };
    for (const mode of ['natural', 'clay', 'curvature', 'accessibility', 'relief', 'depth', 'normals', 'quality']) {
      expect(missingMessage(mode, a)).toBeNull();
    }
  });
  it('names the file a mode lacks', () => {
    const a = full();
    a.names.curvature = [];
    expect(missingMessage('curvature', a)).toBe('This model has no curvature.png: the curvature view is not available.');
    a.names.accessibility = null;
    expect(missingMessage('accessibility', a)).toMatch(/no accessibility\.png/);
    a.names.quality = []; // read as English: it said "This model has no a quality map"
    expect(missingMessage('quality', a)).toBe('This model has no quality map (quality/*.npy): the quality view is not available.');
  });
  it('says when a map is loading or failed to load', () => {
    expect(missingMessage('quality', full())).toMatch(/^Loading quality map/);
    expect(missingMessage('curvature', full(), { curvature: 'HTTP 503' })).toBe('Could not load curvature.png: HTTP 503');
  });
  it('warns that relighting is smoothed without normals.png', () => {
    const a = { ...full(), normals: null };
    expect(missingMessage('clay', a)).toMatch(/No normals\.png: lit by the mesh normals/);
    expect(missingMessage('relief', a)).toMatch(/no normals\.png: the relief view/);
  });
});
