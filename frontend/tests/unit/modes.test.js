import { describe, expect, it } from 'vitest';
import { lensMissingMessage, missingMessage, unavailableModeReason } from '../../src/viewer/modes.js';

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

describe('trust on a whole tablet, the lens, and modes a model cannot offer', () => {
  const face = (name, trust) => ({ name, assets: { normals: 'n', curvature: ['c'], accessibility: 'a', trust: trust ? 't' : null }, normals: {}, albedo: {} });
  it('names the faces of a whole tablet without a trust map', () => {
    const a = { ...full(), names: { ...full().names, trust: null }, trust: {}, faces: [face('obverse', true), face('reverse', false)] };
    expect(missingMessage('trust', a)).toBe('No trust.png (made by the worker from the quality maps) for reverse: drawn in half-lit clay there.');
    a.faces[1] = face('reverse', true);
    expect(missingMessage('trust', a)).toBeNull();
  });
  it('says what the lens lacks, once, and nothing when it shows the main mode', () => {
    const a = full();
    a.names.accessibility = null;
    a.normals = null;
    expect(lensMissingMessage('accessibility', 'clay', a)).toBe('In the lens: This model has no accessibility.png: the accessibility view is not available.');
    expect(lensMissingMessage('accessibility', 'accessibility', a)).toBeNull();
    expect(lensMissingMessage(null, 'clay', a)).toBeNull();
  });
  it('disables trust, with the reason, only where the model has none', () => {
    expect(unavailableModeReason('trust', { names: { trust: null }, faces: [] }, { streamed: true })).toMatch(/streamed model has no trust map/);
    expect(unavailableModeReason('trust', { names: { trust: null }, faces: [] })).toMatch(/no trust map \(trust\.png\)/);
    expect(unavailableModeReason('trust', { names: { trust: 'trust.png' }, faces: [] })).toBeNull();
    expect(unavailableModeReason('trust', { names: {}, faces: [face('obverse', false), face('reverse', true)] })).toBeNull();
    expect(unavailableModeReason('curvature', { names: { curvature: [] }, faces: [] })).toBeNull();
  });
});
