import { describe, expect, it } from 'vitest';
import * as THREE from 'three';
import { classifyFaceAssets, loadFaceQualityMaps, pooledRobustRange, robustRange } from '../../src/viewer/assets.js';
import { applyPartShading, chooseQualityMap, createPartMaterial, createRelightMaterial } from '../../src/viewer/material.js';
import { missingMessage } from '../../src/viewer/modes.js';
import { tiledAssets, tileTextureBytes } from '../../src/viewer/tiles.js';

/** A float32 .npy (version 1.0) of a rows × cols map. */
function npy(values, rows, cols) {
  let header = `{'descr': '<f4', 'fortran_order': False, 'shape': (${rows}, ${cols}), }`;
  while ((10 + header.length + 1) % 64) header += ' ';
  header += '\n';
  const out = new Uint8Array(10 + header.length + 4 * values.length);
  out.set([0x93, ...'NUMPY'].map((c) => (typeof c === 'string' ? c.charCodeAt(0) : c)), 0);
  out.set([1, 0, header.length & 255, header.length >> 8], 6);
  out.set([...header].map((c) => c.charCodeAt(0)), 10);
  out.set(new Uint8Array(Float32Array.from(values).buffer), 10 + header.length);
  return out.buffer;
}

describe("a whole tablet's quality maps", () => {
  const assets = {
    'faces/obverse/quality/walls.npy': '/m/faces/obverse/quality/walls.npy',
    'faces/obverse/quality/guard.npy': '/m/faces/obverse/quality/guard.npy',
    'faces/obverse/quality/deeper/x.npy': '/m/x.npy', // not a map of the face's folder
    'faces/left_edge/quality/walls.npy': '/m/faces/left_edge/quality/walls.npy',
    'faces/obverse/height.npy': '/m/faces/obverse/height.npy',
  };

  it("lists each face's maps under the face model's names", () => {
    expect(classifyFaceAssets(assets, 'obverse').quality).toEqual(['quality/guard.npy', 'quality/walls.npy']);
    expect(classifyFaceAssets(assets, 'left edge').quality).toEqual(['quality/walls.npy']);
    expect(classifyFaceAssets(assets, 'reverse').quality).toEqual([]);
    expect(classifyFaceAssets(assets, 'obverse').prefix).toBe('faces/obverse/');
  });

  it("pools the faces' values into one legend, each face weighing by its pixels", () => {
    const a = Float32Array.from({ length: 900 }, (_, i) => i / 900); // 0 … 1
    const b = Float32Array.from({ length: 100 }, (_, i) => 10 + i / 100); // 10 … 11
    const [lo, hi] = pooledRobustRange([a, b]);
    expect(lo).toBeCloseTo(robustRange(a)[0], 2); // the 2nd percentile lies in the larger face
    expect(hi).toBeGreaterThan(10); // the top 2 % are the small face's
    expect(pooledRobustRange([a])).toEqual(robustRange(a));
  });

  it("loads each face's own maps and merges their names and ranges", async () => {
    const bytes = {
      '/m/faces/obverse/quality/walls.npy': npy([0, 1, 2, 3], 2, 2),
      '/m/faces/obverse/quality/guard.npy': npy([5, 5, 5, 5], 2, 2),
      '/m/faces/left_edge/quality/walls.npy': npy([100, 101, 102], 1, 3),
    };
    const get = async (name) => bytes[assets[name]];
    const faces = ['obverse', 'left edge', 'reverse'].map((n) => classifyFaceAssets(assets, n));
    const { perFace, merged } = await loadFaceQualityMaps(get, faces);
    expect(perFace.map((maps) => maps.map((m) => m.name))).toEqual([['quality/guard.npy', 'quality/walls.npy'], ['quality/walls.npy'], []]);
    expect(perFace[1][0].texture.image.width).toBe(3); // on the face's own grid
    expect(merged.map((m) => m.name)).toEqual(['quality/guard.npy', 'quality/walls.npy']);
    const walls = merged[1].range;
    expect(walls[0]).toBeLessThan(1);
    expect(walls[1]).toBeGreaterThan(100); // both faces' values in one range
  });

  it('binds the chosen map of each face; a face without it shows none', () => {
    const base = createRelightMaterial();
    const m = createPartMaterial(base, { rotation: new THREE.Matrix3(), normals: null, albedo: null }, { seamDepthMm: 0 });
    const walls = { name: 'quality/walls.npy', texture: new THREE.Texture() };
    const guard = { name: 'quality/guard.npy', texture: new THREE.Texture() };
    expect(chooseQualityMap([guard, walls], 'quality/walls.npy')).toBe(walls);
    expect(chooseQualityMap([guard, walls], 'nope')).toBe(guard);
    expect(chooseQualityMap([], 'x')).toBeNull();
    const shading = { mode: 'quality', curvatureScale: 0, quality: 'quality/walls.npy' };
    applyPartShading(m, { quality: [guard, walls] }, shading);
    expect(m.uniforms.uHasQuality.value).toBe(true);
    expect(m.uniforms.uQualityMap.value).toBe(walls.texture);
    // Its own uniform, not the base's: another face binds another map.
    expect(base.uniforms.uQualityMap.value).not.toBe(walls.texture);
    applyPartShading(m, { quality: [] }, shading);
    expect(m.uniforms.uHasQuality.value).toBe(false);
    // Bound for the lens' mode too.
    applyPartShading(m, { quality: [walls] }, { mode: 'clay', lensMode: 'quality', curvatureScale: 0 });
    expect(m.uniforms.uHasQuality.value).toBe(true);
    applyPartShading(m, { quality: [walls] }, { mode: 'clay', curvatureScale: 0 });
    expect(m.uniforms.uHasQuality.value).toBe(false);
  });

  it("offers a streamed tablet's faces' maps, and its faces for the measuring tools", () => {
    const tiled = {
      kind: 'tablet',
      blank: {},
      faceNames: ['obverse', 'left_edge', 'reverse'],
      faceFrame: (n) => (n === 'obverse' ? { toModel: [1], toFace: [2] } : null),
      faceGrid: (n) => ({ pixel_size_um: n === 'obverse' ? 50 : 60 }),
      faceHeights: (n) => ({ name: n }),
      dispose() {},
      setFaceMaps() {},
    };
    const a = tiledAssets(tiled, { 'tiles/index.json': '/m/tiles/index.json', ...assets, 'faces/reverse/uncertainty_um.npy': '/u' });
    expect(a.names.quality).toEqual(['quality/guard.npy', 'quality/walls.npy']);
    expect(a.quality).toBeNull(); // present, loaded on first use
    expect(a.faces.map((f) => f.name)).toEqual(['obverse', 'left_edge', 'reverse']);
    expect(a.faces[0].toModel).toEqual([1]);
    expect(a.faces[1].toFace).toBeNull(); // no tile of it yet
    expect(a.faces[2].assets.uncertainty).toBe('faces/reverse/uncertainty_um.npy');
    expect(a.faces[1].pixelSizeUm).toBe(60);
    expect(a.faces[2].heights()).toEqual({ name: 'reverse' });
    // The tiles carry normals, albedo, curvature, accessibility: no notice for them; the
    // quality mode names the face without quality maps.
    for (const mode of ['natural', 'clay', 'curvature', 'accessibility', 'relief']) expect(missingMessage(mode, a)).toBeNull();
    expect(missingMessage('quality', a)).toMatch(/for reverse/);
  });
});

describe('the tile cache counts the maps the lens draws', () => {
  const tex = (w) => ({ image: { width: w, height: w }, generateMipmaps: false });
  const albedo = tex(10);
  const curvature = tex(20);
  const access = tex(30);
  const own = { textures: new Set([albedo, curvature, access]), lazy: new Map([[curvature, 'curvature'], [access, 'accessibility']]) };
  it('counts a lazily drawn map while its mode is the main one or the lens', () => {
    expect(tileTextureBytes(own, { mode: 'natural' })).toBe(400);
    expect(tileTextureBytes(own, { mode: 'curvature' })).toBe(400 + 1600);
    expect(tileTextureBytes(own, { mode: 'natural', lensMode: 'accessibility' })).toBe(400 + 3600);
    expect(tileTextureBytes(own, { mode: 'curvature', lensMode: 'accessibility' })).toBe(400 + 1600 + 3600);
    expect(tileTextureBytes(own, null)).toBe(400);
  });
});
