import { describe, expect, it } from 'vitest';
import { resolveTilesUrl, tileFace, tileGloss, tileInfo, tilesetFaces, validateIndex } from '../../src/viewer/tiles.js';
import { tileOptionsFromSearch, tilesIndexUrl } from '../../src/viewer/tilesIndex.js';

const FACE = {
  version: 1,
  width_px: 10000,
  height_px: 8000,
  pixel_size_um: 26.8,
  tileset: '3d/tileset.json',
  height_raw: { path: 'height.f32', dtype: '<f4', shape: [8000, 10000], order: 'row-major' },
};

describe('tiles/index.json', () => {
  it('is what makes a model streamed', () => {
    expect(tilesIndexUrl({ 'model.glb': '/a/model.glb' })).toBeNull();
    expect(tilesIndexUrl({ 'tiles/index.json': '/api/v1/models/3/assets/tiles/index.json' })).toBe(
      '/api/v1/models/3/assets/tiles/index.json',
    );
  });

  it('accepts a face and a whole tablet, and names what is wrong otherwise', () => {
    expect(validateIndex(FACE)).toBe(FACE);
    const tablet = { version: 1, tileset: '3d/tileset.json', faces: { 'faces/obverse': 'faces/obverse/index.json' } };
    expect(validateIndex(tablet)).toBe(tablet);
    expect(() => validateIndex({ ...FACE, version: 2 })).toThrow(/version 2 is not supported/);
    expect(() => validateIndex({ ...FACE, pixel_size_um: 0 })).toThrow(/pixel_size_um must be a positive number/);
    expect(() => validateIndex({ ...FACE, tileset: '' })).toThrow(/tileset/);
    expect(() => validateIndex({ ...tablet, faces: {} })).toThrow(/faces must map/);
    expect(() => validateIndex(null)).toThrow(/not a JSON object/);
  });

  it('resolves its paths against the asset route', () => {
    const index = 'http://lib.example/api/v1/models/3/assets/tiles/index.json';
    expect(resolveTilesUrl(index, '3d/tileset.json')).toBe('http://lib.example/api/v1/models/3/assets/tiles/3d/tileset.json');
    expect(resolveTilesUrl(index, 'height.f32')).toBe('http://lib.example/api/v1/models/3/assets/tiles/height.f32');
  });

  it('finds dh_tile on the tileset tile or up the glTF objects', () => {
    const info = { level: 2, x: 1, y: 3, px_rect: [0, 0, 512, 512], pixel_step: 1 };
    expect(tileInfo({ extras: { dh_tile: info } })).toBe(info);
    const scene = { userData: { dh_tile: info }, parent: null };
    expect(tileInfo({}, { userData: {}, parent: scene })).toBe(info);
    expect(tileInfo({}, null)).toBeNull();
  });
});

describe('streaming settings in the URL', () => {
  it('reads the budget and the error target, and reports what it ignored', () => {
    expect(tileOptionsFromSearch('?id=3&tile_budget_mb=128&tile_error_px=2')).toEqual({
      options: { budgetMb: 128, errorTarget: 2 },
      ignored: [],
    });
    const bad = tileOptionsFromSearch('?tile_budget_mb=0&tile_error_px=abc');
    expect(bad.options).toEqual({});
    expect(bad.ignored).toEqual(['tile_budget_mb=0 (1 to 4096)', 'tile_error_px=abc (0.25 to 64)']);
    expect(tileOptionsFromSearch('')).toEqual({ options: {}, ignored: [] });
  });
});

describe('a whole tablet streamed face by face', () => {
  // The root tileset of worker/tiles/tablet.py: one child per face, each an external tileset.
  const root = {
    children: [
      { extras: { dh_face: 'obverse' }, content: { uri: '../faces/obverse/3d/tileset.json' } },
      { extras: { dh_face: 'reverse' }, content: { uri: '../faces/reverse/3d/tileset.json' } },
      { extras: {} },
    ],
  };

  it('lists its faces in the root tileset order', () => {
    expect(tilesetFaces(root)).toEqual(['obverse', 'reverse']);
    expect(tilesetFaces(null)).toEqual([]);
    expect(tilesetFaces({ children: [{ extras: { dh_face: 'a' } }, { extras: { dh_face: 'a' } }] })).toEqual(['a']);
  });

  it('tells which face a tile belongs to, up its parents or from its URL', () => {
    const faceRoot = { parent: root.children[1], extras: { dh_tile: { level: 0 } } };
    const leaf = { parent: { parent: faceRoot }, content: { uri: '2/1_0.glb' } };
    expect(tileFace(leaf)).toBe('reverse');
    const orphan = { content: { uri: 'http://h/api/v1/models/4/assets/tiles/faces/top%20edge/3d/1/0_0.glb' } };
    expect(tileFace(orphan)).toBe('top edge');
    expect(tileFace({ content: { uri: '3d/0/0_0.glb' } })).toBeNull(); // a face model's tile
  });

  it("takes a tile's measured gloss only with a usable scale", () => {
    const texture = { isTexture: true };
    expect(tileGloss(texture, { strength_scale: 0.3, exponent: 40 })).toEqual({ texture, scale: 0.3, exponent: 40 });
    expect(tileGloss(texture, { strength_scale: 0, exponent: 40 })).toBeNull();
    expect(tileGloss(texture, undefined)).toBeNull();
    expect(tileGloss(null, { strength_scale: 0.3, exponent: 40 })).toBeNull();
  });
});
