import { describe, expect, it } from 'vitest';
import { resolveTilesUrl, tiledAssets, tileFace, tileFaceUv, tileGloss, tileInfo, tilesetFaces, validateIndex } from '../../src/viewer/tiles.js';
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

describe('tileFaceUv', () => {
  /** Face uv of a tile's texel centre t (level texels), the way tile_mesh.py writes tile uv. */
  const tileUv = (t, t0, t1) => (t - t0 + 0.5) / (t1 - t0);
  const apply = (tr, u, v) => [tr[0] + tr[2] * u, tr[1] + tr[3] * v];

  it('is the identity for the root tile of a face whose size is a multiple of its step', () => {
    const tr = tileFaceUv({ px_rect: [0, 0, 2048, 1536], pixel_step: 4 }, 2048, 1536);
    expect(tr).toEqual([0, 0, 1, 1]);
  });

  it('puts a finest-level texel centre on its pixel centre of the face grid', () => {
    const W = 2048;
    const H = 1536;
    const tr = tileFaceUv({ px_rect: [1024, 512, 1536, 1024], pixel_step: 1 }, W, H);
    // texel 1030 (column), 700 (row) of this tile → pixel (700, 1030): u = (1030 + ½)/W
    const [u, v] = apply(tr, tileUv(1030, 1024, 1536), tileUv(700, 512, 1024));
    expect(u).toBeCloseTo((1030 + 0.5) / W, 12);
    expect(v).toBeCloseTo((700 + 0.5) / H, 12);
  });

  it('puts a coarse texel centre at the centre of the pixels it averages', () => {
    const W = 2048;
    const H = 1536;
    const s = 2;
    const tr = tileFaceUv({ px_rect: [1024, 0, 2048, 1024], pixel_step: s }, W, H);
    // texel 600 of the level (x) averages pixels 1200, 1201: centre at 1201.0 (edges at 1200, 1202)
    const [u, v] = apply(tr, tileUv(600, 512, 1024), tileUv(10, 0, 512));
    expect(u * W).toBeCloseTo(600 * s + s / 2, 9);
    expect(v * H).toBeCloseTo(10 * s + s / 2, 9);
  });

  it('covers whole texels at a ragged edge (px_rect not a multiple of the step)', () => {
    // 1000 px wide face at step 4: texels 0..250 (250 = ⌈1000/4⌉), tile uv 0 → 0, 1 → 1000/1000
    const tr = tileFaceUv({ px_rect: [0, 0, 1000, 998], pixel_step: 4 }, 1000, 998);
    expect(tr[2]).toBeCloseTo(1, 12);
    expect(tr[3]).toBeCloseTo((250 * 4) / 998, 12); // ⌈998/4⌉ = 250 texels: 1000 px of 998
  });

  it('is null without a rectangle, a step or a grid', () => {
    expect(tileFaceUv(null, 10, 10)).toBeNull();
    expect(tileFaceUv({ px_rect: [0, 0, 8, 8] }, 10, 10)).toBeNull();
    expect(tileFaceUv({ px_rect: [0, 0, 8, 8], pixel_step: 1 }, 0, 10)).toBeNull();
    expect(tileFaceUv({ px_rect: [4, 0, 4, 8], pixel_step: 1 }, 10, 10)).toBeNull();
  });
});

describe('tiledAssets', () => {
  const fake = (kind) => ({ kind, blank: {}, dispose() {}, setFaceMaps() {} });
  const assets = {
    'tiles/index.json': '/a/tiles/index.json',
    'trust.png': '/a/trust.png',
    'trust.json': '/a/trust.json',
    'quality/guard.npy': '/a/quality/guard.npy',
  };

  it("offers a streamed face's trust and quality maps, to load on first use", () => {
    const a = tiledAssets(fake('face'), assets);
    expect(a.names.trust).toBe('trust.png');
    expect(a.names.trustMeta).toBe('trust.json');
    expect(a.names.quality).toEqual(['quality/guard.npy']);
    expect(a.trust).toBeNull(); // present, not loaded (modes.js: "Loading …")
    expect(a.quality).toBeNull();
  });

  it('says a face without them has none', () => {
    const a = tiledAssets(fake('face'), { 'tiles/index.json': '/a/tiles/index.json' });
    expect(a.names.trust).toBeNull();
    expect(a.trust).toBe(false);
    expect(a.quality).toEqual([]);
  });

  it("offers a whole tablet's faces' own trust maps", () => {
    const a = tiledAssets(
      { ...fake('tablet'), faceNames: ['obverse', 'left edge'] },
      {
        ...assets,
        'faces/obverse/trust.png': '/a/faces/obverse/trust.png',
        'faces/left_edge/trust.png': '/a/faces/left_edge/trust.png',
        'faces/left_edge/trust.json': '/a/faces/left_edge/trust.json',
      },
    );
    expect(a.names.trust).toBe('faces/obverse/trust.png'); // a face's, not the top-level one
    expect(a.trust).toBeNull();
    expect(a.quality).toEqual([]);
  });

  it('says a whole tablet whose faces have none has none', () => {
    const a = tiledAssets({ ...fake('tablet'), faceNames: ['obverse'] }, assets);
    expect(a.names.trust).toBeNull();
    expect(a.trust).toBe(false);
  });
});
