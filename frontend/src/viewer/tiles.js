/**
 * View-dependent streaming of a tiled model (issue 19): an OGC 3D Tiles 1.1 tileset loaded with
 * the three.js 3D Tiles renderer (npm `3d-tiles-renderer`), meshes decoded with meshoptimizer
 * (EXT_meshopt_compression), every tile drawn with the viewer's relighting material.
 *
 * A model directory with tiles has `tiles/index.json` (docs/tiles.md, the contract between the
 * worker and this module). The renderer loads the root first (a coarse model on screen at once),
 * then refines by screen-space error where the camera looks: a tile is replaced by its children
 * while geometricError / (size of a screen pixel at the tile) > the renderer's target (3D Tiles
 * 1.1, §"Geometric error"). The viewer's target is a texel size on screen (`errorTarget` px,
 * turned into geometric error by `errorPerTexel`): with 1 px the finest level (pixel_step 1,
 * full-resolution normals) is reached when an image pixel covers a screen pixel or more. Tiles
 * no longer in use are kept in an LRU cache bounded in bytes (the budget) and disposed beyond.
 *
 * Frames: tile meshes hold scan-frame millimetres (as model.glb's mesh does) and the tileset's
 * root.transform takes them to glTF metres (docs/tiles.md). The renderer's group carries the
 * inverse, so the viewer's world stays the scan frame in millimetres and geometric errors stay
 * in the tileset's metres (the renderer measures them in its group's local frame).
 */
import * as THREE from 'three';
import { TilesRenderer } from '3d-tiles-renderer/three';
import { GLTFExtensionsPlugin } from '3d-tiles-renderer/three/plugins';
import { MeshoptDecoder } from 'meshoptimizer/decoder';
import { classifyAssets, classifyFaceAssets, disposeTexture, faceAssetPrefix, fetchBytes, loadFaceQualityMaps, loadQualityMaps, loadTrustMap } from './assets.js';
import { createHeightRows } from './heightRows.js';
import { applyPartShading, boundModes, createPartMaterial } from './material.js';
import { bilinearHeight } from './profile.js';
import { facesAway, installFacingError } from './tileFacing.js';
import { installCursorPriority } from './tileFocus.js';
import { mergeTrustMeta } from './trust.js';
import { runQueuesPromptly } from './tileQueues.js';

/** Default GPU memory budget of the tile cache (bytes). */
export const DEFAULT_BUDGET_MB = 256;
/** Size on screen (CSS px) of a texel of the tiles' maps above which a tile is refined. */
export const DEFAULT_ERROR_TARGET_PX = 1;

export { tilesIndexUrl } from './tilesIndex.js';

/**
 * Check a parsed tiles/index.json against the contract; returns it, or throws naming the field.
 * @param {any} index
 */
export function validateIndex(index) {
  const where = 'tiles/index.json';
  if (!index || typeof index !== 'object') throw new Error(`${where}: not a JSON object`);
  if (index.version !== 1) throw new Error(`${where}: version ${index.version} is not supported (expected 1)`);
  if (typeof index.tileset !== 'string' || !index.tileset) throw new Error(`${where}: tileset must name tileset.json`);
  if (index.faces !== undefined) {
    // A whole tablet: its faces' own index.json files carry the image grids.
    const faces = Object.values(index.faces ?? {});
    if (!faces.length || !faces.every((f) => typeof f === 'string' && f)) {
      throw new Error(`${where}: faces must map each face to its index.json`);
    }
    return index;
  }
  for (const k of ['width_px', 'height_px', 'pixel_size_um']) {
    if (!(Number(index[k]) > 0)) throw new Error(`${where}: ${k} must be a positive number, got ${index[k]}`);
  }
  return index;
}

/** Resolve a path of index.json (relative to the tiles/ folder) against the index's URL. */
export function resolveTilesUrl(indexUrl, path) {
  const base = new URL(indexUrl, globalThis.location?.href ?? 'http://localhost/');
  return new URL(path, base).href;
}

/** Bytes of a texture on the GPU, with its mip chain (4/3) when it has one; RGBA8 assumed. */
function textureBytes(t) {
  const img = t?.image;
  if (!img?.width) return 0;
  const bpp = t.type === THREE.FloatType ? 16 : 4;
  return Math.ceil(img.width * img.height * bpp * (t.generateMipmaps ? 4 / 3 : 1));
}

/** Maps a tile carries that only one shading mode draws: decoded when that mode is on. */
const LAZY_MAPS = new Set(['curvature', 'accessibility']);

/** A map texture's sampling: data (never colour-managed), glTF's uv (no flip), mip-mapped. */
function configureMap(tex) {
  tex.colorSpace = THREE.NoColorSpace;
  tex.flipY = false;
  tex.generateMipmaps = true;
  tex.minFilter = THREE.LinearMipmapLinearFilter;
  tex.magFilter = THREE.LinearFilter;
  tex.wrapS = THREE.ClampToEdgeWrapping;
  tex.wrapT = THREE.ClampToEdgeWrapping;
  return tex;
}

/**
 * Bytes a tile's textures hold on the GPU for the cache's accounting: its albedo and normals
 * (every mode draws them), and each lazily drawn map (curvature, accessibility) only while a
 * mode that draws it is bound — the main mode or the lens' (material.js boundModes): three.js
 * uploads a texture when it is first drawn, and applyShading frees it when no longer bound.
 * @param {{textures: Set<object>, lazy: Map<object, string>}} own the tile's textures, and the
 *   mode of each lazily drawn one
 * @param {{mode: string, lensMode?: string | null} | null} shading
 */
export function tileTextureBytes(own, shading) {
  const modes = shading ? boundModes(shading) : new Set();
  let bytes = 0;
  for (const t of own.textures) if (!own.lazy.has(t) || modes.has(own.lazy.get(t))) bytes += textureBytes(t);
  return bytes;
}

/**
 * glTF loader extension: the textures a tile's material names in `extras.dh_maps` (normals,
 * curvature, accessibility: texture indices) are not referenced by any glTF material slot,
 * so GLTFLoader would not load them; this loads them after the root and attaches them to
 * the material as `userData.dhTextures`. The maps of {@link LAZY_MAPS} are not decoded here:
 * their texture holds the encoded image (`userData.dhEncoded`, a Blob of the GLB's bytes) until
 * {@link decodeLazyMap} (the mode that draws it is on): a tile's parse decodes two images of
 * five fewer (issue 19: full detail after a zoom waits for the parses).
 */
class DhMapsGltfExtension {
  constructor(parser) {
    this.parser = parser;
    this.name = 'DH_maps';
  }

  async afterRoot(result) {
    const jobs = [];
    result.scene.traverse((obj) => {
      if (!obj.isMesh) return;
      for (const m of Array.isArray(obj.material) ? obj.material : [obj.material]) {
        const maps = m?.userData?.dh_maps;
        if (!maps || m.userData.dhTextures) continue;
        const out = {};
        m.userData.dhTextures = out;
        for (const [kind, index] of Object.entries(maps)) {
          if (!Number.isInteger(index)) continue;
          const encoded = LAZY_MAPS.has(kind) ? this.encodedImage(index) : null;
          if (encoded) {
            jobs.push(
              encoded.then((blob) => {
                const tex = configureMap(new THREE.Texture());
                tex.userData.dhEncoded = blob;
                out[kind] = tex;
              }),
            );
            continue;
          }
          jobs.push(
            this.parser.getDependency('texture', index).then((t) => {
              // A separate object per use: the normal map is data, never colour-managed.
              const tex = configureMap(t.clone());
              tex.needsUpdate = true;
              out[kind] = tex;
            }),
          );
        }
      }
    });
    await Promise.all(jobs);
  }

  /** The encoded bytes (a Blob) of a texture's image stored in the GLB, or null (a URI). */
  encodedImage(textureIndex) {
    const json = this.parser.json;
    const image = json.images?.[json.textures?.[textureIndex]?.source];
    if (!Number.isInteger(image?.bufferView)) return null;
    return this.parser
      .getDependency('bufferView', image.bufferView)
      .then((view) => new Blob([view], { type: image.mimeType || 'image/png' }));
  }
}

/**
 * Decode a lazily loaded map (see {@link DhMapsGltfExtension}) once; resolves true when its
 * image was set now (three.js uploads it when next drawn), false if there was nothing to do.
 * The options are GLTFLoader's ImageBitmapLoader's: data, neither premultiplied nor converted.
 * @param {THREE.Texture} tex
 */
export function decodeLazyMap(tex) {
  const blob = tex?.userData?.dhEncoded;
  if (!blob) return Promise.resolve(false);
  tex.userData.dhDecoding ??= createImageBitmap(blob, { premultiplyAlpha: 'none', colorSpaceConversion: 'none' }).then((bitmap) => {
    delete tex.userData.dhEncoded;
    if (tex.userData.dhDisposed) {
      bitmap.close?.(); // its tile was unloaded meanwhile
      return false;
    }
    tex.image = bitmap;
    tex.needsUpdate = true;
    return true;
  });
  return tex.userData.dhDecoding;
}

/** `dh_tile` of a tile: {level, x, y, px_rect, pixel_step} from the tileset tile's extras or
 * the content's glTF extras (scene, node or mesh), or null. */
export function tileInfo(tile, object = null) {
  if (tile?.extras?.dh_tile) return tile.extras.dh_tile;
  for (let o = object; o; o = o.parent) if (o.userData?.dh_tile) return o.userData.dh_tile;
  return null;
}

/**
 * Where a tile's uv fall on its face's whole image grid, as [offsetU, offsetV, scaleU, scaleV]
 * (face uv = offset + scale · tile uv; the shader's `uFaceUv`), so that maps of the whole face
 * (trust.png, quality/*.npy: one texture per face, not per tile) are sampled under a tile.
 *
 * A tile of pixel step s covers texels [tx0, tx1) of its level, tx0 = ⌊x0/s⌋, tx1 = ⌈x1/s⌉ of
 * its px_rect [x0, y0, x1, y1); its uv put texel t's centre at (t − tx0 + ½)/(tx1 − tx0)
 * (worker/tiles/tile_mesh.py), and that texel averages full-resolution pixels [t·s, (t+1)·s),
 * whose centre on the face's grid (width W px, pixel c at u = (c + ½)/W, assets.js) is
 * u = (t·s + s/2)/W. Solving for u: u = tx0·s/W + (tx1 − tx0)·s/W · u_tile. (At the right and
 * bottom edges a texel's pixels may stop at W: its centre is then off by under s/2 pixels.)
 * @param {{px_rect: number[], pixel_step: number} | null} info the tile's dh_tile
 * @param {number} widthPx W of the face's grid
 * @param {number} heightPx H
 * @returns {number[] | null} null when the tile does not say its rectangle
 */
export function tileFaceUv(info, widthPx, heightPx) {
  const s = Number(info?.pixel_step);
  const r = info?.px_rect;
  if (!(s > 0) || !Array.isArray(r) || r.length !== 4 || !(widthPx > 0) || !(heightPx > 0)) return null;
  const [x0, y0, x1, y1] = r.map(Number);
  if (![x0, y0, x1, y1].every(Number.isFinite) || !(x1 > x0) || !(y1 > y0)) return null;
  const tx0 = Math.floor(x0 / s);
  const ty0 = Math.floor(y0 / s);
  const tx1 = Math.ceil(x1 / s);
  const ty1 = Math.ceil(y1 / s);
  return [(tx0 * s) / widthPx, (ty0 * s) / heightPx, ((tx1 - tx0) * s) / widthPx, ((ty1 - ty0) * s) / heightPx];
}

/**
 * The face of a whole tablet a tile belongs to: the `dh_face` of the root tileset's child that
 * references the face's tileset (worker/tiles/tablet.py), found up the tile's parents, else
 * read from its content's URL (`…/faces/<name>/3d/…`); null for a face model's tile.
 */
export function tileFace(tile) {
  for (let t = tile; t; t = t.parent) {
    const face = t.extras?.dh_face;
    if (typeof face === 'string' && face) return face;
  }
  const uri = tile?.content?.uri ?? tile?.content?.url ?? '';
  const m = /(?:^|\/)faces\/([^/]+)\/3d\//.exec(uri);
  return m ? decodeURIComponent(m[1]) : null;
}

/**
 * The faces of a whole tablet's root tileset, in its order (the `dh_face` of each child).
 * @param {{children?: Array<{extras?: {dh_face?: string}}>} | null} root the root tile
 * @returns {string[]}
 */
export function tilesetFaces(root) {
  const names = [];
  for (const child of root?.children ?? []) {
    const face = child?.extras?.dh_face;
    if (typeof face === 'string' && face && !names.includes(face)) names.push(face);
  }
  return names;
}

/**
 * A tile's measured gloss for the relighting material: {texture, scale, exponent} from its
 * `gloss` map and its material's `dh_gloss` (worker/tiles/build.py), or null (none, or a
 * scale that is not > 0).
 */
export function tileGloss(texture, info) {
  const scale = Number(info?.strength_scale);
  const exponent = Number(info?.exponent);
  if (!texture || !(scale > 0) || !(exponent > 0)) return null;
  return { texture, scale, exponent };
}

/**
 * Open a tiled model.
 * @param {object} options
 * @param {string} options.indexUrl URL of tiles/index.json
 * @param {THREE.ShaderMaterial} options.baseMaterial the viewer's relighting material (its light,
 *   mode and camera uniforms are shared by every tile's material)
 * @param {() => void} options.invalidate ask the viewer for a frame (tiles arrived)
 * @param {number} [options.budgetMb] GPU memory budget of the tile cache, MB
 * @param {number} [options.errorTarget] screen-space error target, px
 * @param {number} [options.seamDepthMm] a whole tablet's seam depth (material.js `seamDepth`):
 *   where faces overlap, the one of larger weight (its normals' alpha) is drawn
 * @param {AbortSignal} [options.signal]
 * @returns {Promise<object>} the tiled model (see the returned object's members)
 */
export async function openTiledModel({
  indexUrl,
  baseMaterial,
  invalidate,
  budgetMb = DEFAULT_BUDGET_MB,
  errorTarget = DEFAULT_ERROR_TARGET_PX,
  seamDepthMm = 0,
  signal,
}) {
  if (!(budgetMb > 0)) throw new RangeError(`budgetMb must be > 0, got ${budgetMb}`);
  const response = await fetch(indexUrl, { signal, credentials: 'same-origin' });
  if (!response.ok) throw new Error(`${indexUrl}: HTTP ${response.status}`);
  const index = validateIndex(await response.json());
  const tilesetUrl = resolveTilesUrl(indexUrl, index.tileset);
  const kind = index.faces ? 'tablet' : 'face';
  let pixelSizeUm = Number(index.pixel_size_um);
  // A whole tablet's faces' own index.json (their grids, for the whole-face maps' uv); the
  // faces of one tablet are scanned with one pixel size, the first face's says it (fetched
  // while the root tileset loads, not before).
  const faceIndexes = kind === 'tablet' ? fetchFaceIndexes(index, indexUrl, signal) : null;
  faceIndexes?.catch(() => {}); // awaited below; not unhandled if the root fails first
  /** face name (dh_face) → its index.json, once fetched */
  let faceGrids = new Map();

  const tiles = new TilesRenderer(tilesetUrl);
  runQueuesPromptly(tiles); // a tile's steps need not wait for frames (tileQueues.js)
  tiles.fetchOptions = { credentials: 'same-origin' };
  tiles.errorTarget = errorTarget;
  setBudget(tiles, budgetMb);
  tiles.registerPlugin(
    new GLTFExtensionsPlugin({
      meshoptDecoder: MeshoptDecoder,
      metadata: false,
      rtc: false,
      plugins: [(parser) => new DhMapsGltfExtension(parser)],
    }),
  );

  const materials = new Set(); // live tile materials (for shading changes)
  const perScene = new WeakMap(); // scene → {textures, materials}
  let shading = null;
  const hiddenFaces = new Set(); // a whole tablet's faces not drawn (the page's checkboxes)
  const awayFaces = new Set(); // and those turned away from the camera (tileFacing.js facesAway)
  // Maps of a whole face (not tiled): its trust map {texture} and its quality maps
  // [{name, texture}] by face name ('' for a face model), one shared texture per face and map
  // (loaded once, tiledAssets), bound to its every tile.
  const faceMaps = { trust: new Map(), quality: new Map() };
  // A whole tablet's faces: scan frame (mm) → tablet frame, from the first tile of each face
  // (its mesh is in the face's scan frame under the face tileset's transform).
  const faceToModel = new Map();

  const relight = {
    name: 'DH_RELIGHT',
    // Replace each tile's glTF material by a relighting material sharing the base's light, mode
    // and camera uniforms, fed with this tile's albedo and its full-resolution maps.
    processTileModel(scene, tile) {
      const own = { textures: new Set(), originals: new Set(), lazy: new Map() };
      scene.updateMatrixWorld(true);
      scene.traverse((obj) => {
        if (!obj.isMesh) return;
        const gm = Array.isArray(obj.material) ? obj.material[0] : obj.material;
        const maps = gm?.userData?.dhTextures ?? {};
        const albedo = gm?.map ?? null;
        if (albedo) albedo.colorSpace = THREE.SRGBColorSpace;
        for (const t of [albedo, maps.normals, maps.curvature, maps.accessibility, maps.gloss]) if (t) own.textures.add(t);
        if (maps.curvature) own.lazy.set(maps.curvature, 'curvature');
        if (maps.accessibility) own.lazy.set(maps.accessibility, 'accessibility');
        for (const m of Array.isArray(obj.material) ? obj.material : [obj.material]) own.originals.add(m);
        if (!obj.geometry.attributes.normal) obj.geometry.computeVertexNormals();
        // Object-space normals are in the mesh's frame (scan frame); the world is that frame
        // for a face (identity), a face's rotation into the tablet frame for a whole tablet.
        const toWorld = new THREE.Matrix4().multiplyMatrices(tiles.group.matrix, obj.matrixWorld);
        if (kind === 'tablet' && !faceToModel.has(tileFace(tile))) faceToModel.set(tileFace(tile), toWorld.clone());
        const rotation = new THREE.Matrix3().setFromMatrix4(new THREE.Matrix4().extractRotation(toWorld));
        // A whole tablet's faces overlap: each face's normals carry its weight in alpha
        // (docs/tiles.md), which the seam depth turns into "the best-measured face is drawn".
        const gloss = tileGloss(maps.gloss, gm?.userData?.dh_gloss);
        const m = createPartMaterial(
          baseMaterial,
          { rotation, normals: maps.normals ?? null, albedo, gloss },
          { seamDepthMm: kind === 'tablet' ? seamDepthMm : 0 },
        );
        m.userData.tile = tileInfo(tile, obj);
        m.userData.faceName = kind === 'tablet' ? tileFace(tile) : null;
        // The tile's rectangle of its face's grid (whole-face maps: trust, quality).
        const grid = kind === 'face' ? index : faceGrids.get(m.userData.faceName);
        const faceUv = grid ? tileFaceUv(m.userData.tile, grid.width_px, grid.height_px) : null;
        if (faceUv) m.uniforms.uFaceUv.value.fromArray(faceUv);
        m.userData.faceUv = faceUv;
        m.userData.face = {
          curvature: maps.curvature ? curvatureLayers(maps.curvature) : [],
          accessibility: maps.accessibility ?? null,
          trust: faceUv ? (faceMaps.trust.get(m.userData.faceName ?? '') ?? null) : null,
          quality: faceUv ? (faceMaps.quality.get(m.userData.faceName ?? '') ?? null) : null,
        };
        m.visible = !hiddenFaces.has(m.userData.faceName) && !awayFaces.has(m.userData.faceName);
        if (shading) applyPartShading(m, m.userData.face, shading, false);
        obj.material = m;
        materials.add(m);
      });
      perScene.set(scene, own);
      decodeBoundMaps(scene);
    },
    // The renderer counts geometry and the textures it finds on materials; the relighting
    // material holds its textures in uniforms, so count them here (the LRU's accounting):
    // the albedo and normals (every mode draws them), and the curvature or accessibility map
    // only while its mode is on (three.js uploads a texture when first drawn, and
    // applyShading frees the GPU copy of the other mode's maps).
    calculateBytesUsed(tile, scene) {
      const own = scene && perScene.get(scene);
      return own ? tileTextureBytes(own, shading) : 0;
    },
  };
  tiles.registerPlugin(relight);
  // Edge-on tiles need less detail, a whole tablet's faces turned away none (tileFacing.js).
  installFacingError(tiles, { skipAway: kind === 'tablet' });
  const cursor = installCursorPriority(tiles); // tiles under the cursor load first (tileFocus.js)
  const size = new THREE.Vector2();

  tiles.addEventListener('dispose-model', ({ scene }) => {
    scene.traverse((obj) => {
      if (obj.isMesh && materials.has(obj.material)) materials.delete(obj.material);
    });
    const own = perScene.get(scene);
    if (!own) return;
    for (const t of own.textures) {
      t.userData.dhDisposed = true;
      t.dispose();
      if (typeof ImageBitmap !== 'undefined' && t.image instanceof ImageBitmap) t.image.close?.();
    }
    for (const m of own.originals) m.dispose();
    perScene.delete(scene);
  });
  for (const type of ['needs-render', 'needs-update', 'load-model', 'tiles-load-end']) {
    tiles.addEventListener(type, () => invalidate());
  }

  const rootLoaded = new Promise((resolve, reject) => {
    tiles.addEventListener('load-root-tileset', () => resolve());
    tiles.addEventListener('load-error', ({ error, url }) => {
      if (!tiles.rootTileset) reject(new Error(`${url}: ${error?.message ?? error}`));
    });
  });
  // The renderer needs update() calls to start loading; a camera-less one fetches the root.
  tiles.update();
  await abortable(rootLoaded, signal, () => tiles.dispose());
  if (faceIndexes) {
    try {
      faceGrids = await faceIndexes;
      pixelSizeUm = Number(faceGrids.values().next().value.pixel_size_um);
    } catch (err) {
      tiles.dispose();
      throw err;
    }
  }

  // Undo the tileset frame: the GLBs hold scan-frame mm under a node that cancels the
  // renderer's y-up → z-up rotation, so the root's transform applies to scan coordinates
  // (docs/tiles.md); the group carries its inverse and the world is the scan frame (a face)
  // or the tablet frame (a whole tablet: each face's tileset adds its scan → tablet transform).
  const rootTransform = new THREE.Matrix4();
  if (Array.isArray(tiles.root?.transform)) rootTransform.fromArray(tiles.root.transform);
  tiles.group.matrixAutoUpdate = false;
  tiles.group.matrix.copy(rootTransform).invert();
  tiles.group.updateMatrixWorld(true);

  const worldPerTilesetUnit = new THREE.Vector3().setFromMatrixScale(tiles.group.matrix).x;

  const box = new THREE.Box3();
  if (!tiles.getBoundingBox(box)) {
    // No bounding volume usable as a box: the image grid (x, y) and a nominal depth.
    const w = ((index.width_px ?? 1000) * pixelSizeUm) / 1000;
    const h = ((index.height_px ?? 1000) * pixelSizeUm) / 1000;
    box.set(new THREE.Vector3(0, 0, -w / 4), new THREE.Vector3(w, h, 0));
  } else {
    box.applyMatrix4(tiles.group.matrix);
  }
  const sphere = box.getBoundingSphere(new THREE.Sphere());

  // A face's full-resolution heights; a whole tablet's are per face, each on its own grid
  // (faceHeights).
  const heights = kind === 'face' && index.height_raw ? streamedHeights(index, indexUrl) : null;
  const heightsByFace = new Map();
  let cameraInUse = null;
  let disposed = false;
  let fullTarget = tiles.errorTarget; // the renderer's target at full resolution (describeTile)

  /** The LRU's bytes of every loaded tile again (0.5.3's recalculateBytesUsed() iterates its
   * cache Map's values, not its tiles, and so changes nothing). */
  function recount() {
    for (const tile of tiles.lruCache.itemSet.keys()) {
      if (tile.engineData?.scene) tiles.lruCache.setMemoryUsage(tile, tiles.getBytesUsed(tile));
    }
  }

  /**
   * Decode the lazily loaded maps (decodeLazyMap) the shading binds (its mode's and its lens'),
   * of the tiles of `root` (a tile's scene) or of every tile.
   */
  function decodeBoundMaps(root = null) {
    if (!shading) return Promise.resolve();
    const modes = boundModes(shading);
    const jobs = [];
    const each = (m) => {
      const f = m.userData.face;
      const wanted = [];
      if (modes.has('curvature') && f?.curvature?.[0]) wanted.push(f.curvature[0].texture);
      if (modes.has('accessibility') && f?.accessibility) wanted.push(f.accessibility);
      for (const t of wanted) {
        const job = decodeLazyMap(t).then(
          (set) => {
            if (!set || disposed) return;
            recount();
            invalidate();
          },
          (err) => console.warn(`a tile's ${[...modes].join('/')} map: ${err?.message ?? err}`),
        );
        jobs.push(job);
      }
    };
    if (root) {
      root.traverse((o) => {
        if (o.isMesh && materials.has(o.material)) each(o.material);
      });
    } else {
      for (const m of materials) each(m);
    }
    return Promise.all(jobs);
  }

  /** A tile's material is drawn unless its face is hidden or (a whole tablet) turned away. */
  function applyVisibility() {
    for (const m of materials) m.visible = !hiddenFaces.has(m.userData.faceName) && !awayFaces.has(m.userData.faceName);
  }

  const toCamera = new THREE.Vector3();
  const towardCamera = [0, 0, 1];
  /** The faces turned away from `camera` now (a whole tablet's; a face model has one side). */
  function updateAwayFaces(camera) {
    if (kind !== 'tablet') return;
    camera.getWorldDirection(toCamera).negate(); // the view axis: a perspective camera's too
    toCamera.toArray(towardCamera);
    let changed = false;
    for (const m of materials) {
      const face = m.userData.faceName;
      const away = facesAway(m.uniforms.uObjectToWorld.value.elements, towardCamera);
      if (away !== awayFaces.has(face)) {
        if (away) awayFaces.add(face);
        else awayFaces.delete(face);
        changed = true;
      }
    }
    if (changed) applyVisibility();
  }

  function curvatureLayers(texture) {
    // One curvature map per tile; the coarser scales are its mip levels (as assets.js does for
    // a single map): smoothing over 4 and 16 pixels of this tile's level.
    return [
      { texture, lod: 0, label: 'curvature' },
      { texture, lod: 2, label: 'curvature, smoothed over 4 texels' },
      { texture, lod: 4, label: 'curvature, smoothed over 16 texels' },
    ];
  }

  const faceNames = kind === 'tablet' ? tilesetFaces(tiles.root) : [];

  return {
    index,
    /** 'face' (one scan's image grid) or 'tablet' (a whole tablet's faces, external tilesets). */
    kind,
    /** A whole tablet's faces (root tileset order), [] for a face model. */
    faceNames,
    /**
     * Draw exactly the faces not named in `names` (a whole tablet's checkboxes): tiles of a
     * hidden face, loaded now or later, get an invisible material (not drawn, not picked).
     */
    setHiddenFaces(names) {
      hiddenFaces.clear();
      for (const n of names ?? []) hiddenFaces.add(n);
      applyVisibility();
      invalidate();
    },
    /**
     * A whole tablet's face as an image grid, for the measuring tools (faceGrids.js):
     * {toModel, toFace} (scan frame mm ↔ tablet frame mm, 4×4 column-major) once a tile of
     * the face has loaded (null before), as a whole-tablet model.glb's node gives them.
     */
    faceFrame(name) {
      const m = faceToModel.get(name);
      return m ? { toModel: m.elements.slice(), toFace: m.clone().invert().elements.slice() } : null;
    },
    /** A whole tablet's face's grid (its tiles/faces/<label>/index.json), or null. */
    faceGrid(name) {
      return faceGrids.get(name) ?? null;
    },
    /** A whole tablet's face's full-resolution heights (its height.f32 by HTTP Range, as a
     * face's `heights`), or null. */
    faceHeights(name) {
      const grid = faceGrids.get(name);
      if (!grid?.height_raw) return null;
      if (!heightsByFace.has(name)) heightsByFace.set(name, streamedHeights(grid, grid.indexUrl));
      return heightsByFace.get(name);
    },
    /** The face (of a whole tablet) a picked object belongs to, or null. */
    faceOf(object) {
      return materials.has(object?.material) ? (object.material.userData.faceName ?? null) : null;
    },
    blank: baseMaterial.userData.blank,
    tiles,
    /** The Object3D to add to the scene. */
    object: tiles.group,
    /** World (scan-frame mm) bounding box of the tileset. */
    box: { min: box.min.toArray(), max: box.max.toArray() },
    radius: sphere.radius || 1,
    /** Full-resolution heights (height.f32 by HTTP Range), or null: {reader, pixelSizeUm, onSurface}. */
    heights,
    /**
     * Call before each frame: culls, picks levels by screen-space error, queues loads.
     * @param {THREE.Camera} camera
     * @param {THREE.WebGLRenderer} renderer
     * @param {{focus?: {x: number, y: number} | null, detailScale?: number}} [options]
     *   `focus`: the cursor (CSS px from the canvas' top left): tiles nearest it load first;
     *   `detailScale` (0, 1]: the frame's pixel ratio scale (adaptive resolution while the
     *   camera turns): levels are chosen for the pixels drawn, coarser by 1/scale
     */
    update(camera, renderer, { focus = null, detailScale = 1 } = {}) {
      if (disposed) return;
      if (cameraInUse !== camera) {
        if (cameraInUse) tiles.deleteCamera(cameraInUse);
        tiles.setCamera(camera);
        cameraInUse = camera;
      }
      // CSS pixels (getSize), whatever the pixel ratio a frame is drawn at (adaptiveResolution.js).
      tiles.setResolutionFromRenderer(camera, renderer);
      camera.updateMatrixWorld();
      // 3d-tiles-renderer 0.5.3 measures an orthographic camera's pixel in WORLD units (mm
      // here) but geometric errors in its group's frame (the tileset's metres), while the
      // perspective path converts; scale the target so both compare like with like.
      const target = errorTarget * errorPerTexel(tiles, pixelSizeUm);
      fullTarget = camera.isOrthographicCamera ? target / worldPerTilesetUnit : target;
      // A frame drawn at a fraction of the pixels needs a texel per DRAWN pixel, not per CSS
      // pixel: the triangles (SwiftShader's cost that does not shrink with the pixels,
      // docs/benchmarks.md "Streaming speed, session 8") drop by scale² with the level.
      const scale = detailScale > 0 ? Math.min(1, detailScale) : 1;
      tiles.errorTarget = fullTarget / scale;
      renderer.getSize(size);
      cursor.setFocus(focus, camera, size.x, size.y);
      tiles.update();
      updateAwayFaces(camera);
    },
    /**
     * Maps of a whole face shared by its tiles: `trust`, a Map face name → {texture} (a face
     * model's under ''). Not counted in the tile cache's bytes (as the base material's
     * quality map is not): one texture per face for the model's lifetime, held by the
     * model's assets (tiledAssets), not by a tile.
     */
    setFaceMaps(maps = {}) {
      for (const key of ['trust', 'quality']) if (maps[key]) faceMaps[key] = maps[key];
      for (const m of materials) {
        const face = m.userData.faceName ?? '';
        m.userData.face.trust = m.userData.faceUv ? (faceMaps.trust.get(face) ?? null) : null;
        m.userData.face.quality = m.userData.faceUv ? (faceMaps.quality.get(face) ?? null) : null;
        if (shading) applyPartShading(m, m.userData.face, shading, false);
      }
      invalidate();
    },
    /**
     * Apply a shading state ({mode, curvatureScale, lensMode}) to every tile, now and on load;
     * resolves when the loaded tiles' maps it binds are decoded.
     */
    applyShading(s) {
      const before = shading ? boundModes(shading) : new Set();
      shading = { ...s };
      const now = boundModes(shading);
      // Maps no longer bound (by the main mode or the lens'): free their GPU copies (the
      // images stay, for coming back).
      const left = [...before].filter((mode) => !now.has(mode));
      for (const m of materials) {
        applyPartShading(m, m.userData.face, shading, false);
        const f = m.userData.face;
        if (left.includes('curvature') && f.curvature[0]) f.curvature[0].texture.dispose();
        if (left.includes('accessibility') && f.accessibility) f.accessibility.dispose();
      }
      if (left.length || [...now].some((mode) => !before.has(mode))) recount();
      return decodeBoundMaps();
    },
    setBudgetMb(mb) {
      if (!(mb > 0)) throw new RangeError(`budget must be > 0 MB, got ${mb}`);
      setBudget(tiles, mb);
      invalidate();
    },
    /** Streaming figures: bytes in the cache vs the budget, tiles by state, deepest level shown. */
    stats() {
      let maxLevel = -1;
      let minStep = Infinity;
      let visibleTiles = 0;
      tiles.group.traverse((o) => {
        if (!o.isMesh || !o.visible || !materials.has(o.material)) return;
        visibleTiles++;
        const info = o.material.userData.tile;
        if (info) {
          maxLevel = Math.max(maxLevel, info.level);
          minStep = Math.min(minStep, info.pixel_step);
        }
      });
      const s = tiles.stats;
      return {
        bytesUsed: tiles.lruCache.cachedBytes,
        budgetBytes: tiles.budgetBytes,
        queued: s.queued,
        downloading: s.downloading,
        parsing: s.parsing,
        loaded: s.loaded,
        failed: s.failed,
        visibleTiles,
        maxLevel,
        minPixelStep: Number.isFinite(minStep) ? minStep : null,
        loadProgress: tiles.loadProgress,
        idle: s.queued + s.downloading + s.parsing === 0,
      };
    },
    /**
     * The tile a picked object (viewer.pick(x, y).object) belongs to: its dh_tile, whether it
     * is a leaf, its screen-space error at the last update and whether that is within the
     * full-resolution target (`sufficient`: nothing finer is wanted there), or null.
     */
    describeTile(object) {
      const tile = object?.userData?.tile;
      if (!tile) return null;
      const info = object.material?.userData?.tile ?? tileInfo(tile, object);
      const leaf = !tile.children?.length || tile.geometricError === 0;
      const error = tile.traversal?.error ?? Infinity;
      return { ...(info ?? {}), leaf, error, sufficient: leaf || error <= fullTarget };
    },
    /** Whether the material is one of this model's tile materials. */
    has(material) {
      return materials.has(material);
    },
    dispose() {
      if (disposed) return;
      disposed = true;
      tiles.dispose(); // disposes every loaded tile (dispose-model frees our textures)
      materials.clear();
    },
  };
}

/** A whole tablet's faces' index.json, by face name (the last part of its folder, as the
 * root tileset's `dh_face`: worker/tiles/tablet.py), in the index's order. */
async function fetchFaceIndexes(index, indexUrl, signal) {
  const entries = await Promise.all(
    Object.entries(index.faces).map(async ([folder, path]) => {
      const faceUrl = resolveTilesUrl(indexUrl, path);
      const r = await fetch(faceUrl, { signal, credentials: 'same-origin' });
      if (!r.ok) throw new Error(`${faceUrl}: HTTP ${r.status}`);
      // indexUrl: what the face's own paths (height_raw) are relative to
      return [folder.split('/').pop(), { ...validateIndex(await r.json()), indexUrl: faceUrl }];
    }),
  );
  return new Map(entries);
}

/**
 * Geometric error per texel of the tiles' textures: the worker gives each tile the spacing of
 * its mesh as geometricError (docs/tiles.md: 4 texels), while what must stay under a screen
 * pixel is a texel of the normal map. The viewer's error target is in texels on screen, so
 * the renderer's target is that times this ratio: geometricError / (pixel_step · pixel size),
 * read from the first tile that carries dh_tile (the root of a face; a face's root under a
 * whole tablet's), 1 until one is known.
 */
function errorPerTexel(tiles, pixelSizeUm) {
  if (tiles.dhErrorPerTexel) return tiles.dhErrorPerTexel;
  const stack = tiles.root ? [tiles.root] : [];
  for (let n = 0; stack.length && n < 64; n++) {
    const t = stack.shift();
    const info = t.extras?.dh_tile;
    if (info?.pixel_step > 0 && t.geometricError > 0) {
      tiles.dhErrorPerTexel = t.geometricError / (info.pixel_step * pixelSizeUm * 1e-6);
      return tiles.dhErrorPerTexel;
    }
    stack.push(...(t.children ?? []));
  }
  return 1;
}

/**
 * The viewer's `model.assets` record for a tiled model, shaped like assets.js' (modes.js reads
 * it for the "missing map" notices): every tile carries its albedo, normals, curvature and
 * accessibility (the contract), so those never load lazily. The face's trust map and quality
 * maps are whole-face images (not tiled): they load on first use (`ensure`), once, and every
 * tile samples them through its rectangle of the face's grid (tileFaceUv). A whole tablet's
 * tiles get their own face's trust map and quality maps (faces/<label>/trust.png,
 * faces/<label>/quality/*.npy), and its `faces` list each face for the measuring tools.
 * @param {object} tiled from openTiledModel
 * @param {Record<string, string>} [assets] the model's asset name → URL map (the API's)
 * @param {{signal?: AbortSignal}} [options]
 */
export function tiledAssets(tiled, assets = {}, { signal } = {}) {
  const tile = 'tiles (per tile)';
  const found = classifyAssets(assets);
  const face = tiled.kind === 'face';
  // A face model's trust map ('' → names), or each face's of a whole tablet (faces/<label>/).
  const trustNames = new Map();
  if (face && found.trust) trustNames.set('', [found.trust, found.trustMeta]);
  for (const name of face ? [] : tiled.faceNames) {
    const prefix = faceAssetPrefix(name);
    if (assets[`${prefix}/trust.png`]) {
      trustNames.set(name, [`${prefix}/trust.png`, assets[`${prefix}/trust.json`] ? `${prefix}/trust.json` : null]);
    }
  }
  const trustName = trustNames.size ? [...trustNames.values()][0][0] : null;
  // A whole tablet's faces, shaped like assets.js' `faces` for the measuring tools and the
  // notices (faceGrids.js, modes.js): their own assets (faces/<label>/: σ_h, quality maps,
  // trust), their frames once a tile of theirs has loaded, their heights by Range reads. The
  // relighting maps are each tile's own (`streamed`: modes.js does not look for them).
  const faceRecords = face
    ? []
    : tiled.faceNames.map((name) => ({
        name,
        streamed: true,
        assets: classifyFaceAssets(assets, name),
        get toModel() {
          return tiled.faceFrame(name)?.toModel ?? null;
        },
        get toFace() {
          return tiled.faceFrame(name)?.toFace ?? null;
        },
        heights: () => tiled.faceHeights(name),
        pixelSizeUm: Number(tiled.faceGrid?.(name)?.pixel_size_um) || null,
        quality: null,
      }));
  // The quality maps: a face model's (one grid), or each face's of a whole tablet.
  const qualityNames = face ? found.quality : [...new Set(faceRecords.flatMap((f) => f.assets.quality))].sort();
  // The curvature scales the page offers (each tile's map and its mip levels, as
  // curvatureLayers); the textures are the tiles' own, the base material gets the blank.
  const blank = tiled.blank;
  const created = [];
  const get = (name) => fetchBytes(assets[name], { signal });
  const out = {
    names: {
      curvature: [tile],
      accessibility: tile,
      quality: qualityNames,
      height: null,
      trust: trustName,
      trustMeta: trustNames.size ? [...trustNames.values()][0][1] : null,
    },
    // Textures, never flags: the viewer may put these in the base material's uniforms (shared
    // by the tiles' materials when a tile is made); each tile then gets its own maps.
    normals: blank,
    albedo: blank,
    curvature: [
      { name: 'curvature', texture: blank, lod: 0, label: 'curvature (each tile)' },
      { name: 'curvature', texture: blank, lod: 2, label: 'curvature, smoothed over 4 texels' },
      { name: 'curvature', texture: blank, lod: 4, label: 'curvature, smoothed over 16 texels' },
    ],
    accessibility: blank,
    // null: present, not loaded yet (modes.js); false / []: the model has none.
    quality: qualityNames.length ? null : [],
    trust: trustName ? null : false,
    faces: faceRecords,
    parts: [],
  };
  const pending = new Map();
  out.ensure = (kind) => {
    if (out[kind] !== null || !['quality', 'trust'].includes(kind)) return Promise.resolve();
    if (!pending.has(kind)) {
      const job = (async () => {
        if (kind === 'trust') {
          const byFace = new Map();
          for (const [name, [png, meta]] of trustNames) {
            const trust = await loadTrustMap(get, png, meta);
            created.push(trust.texture);
            byFace.set(name, trust);
          }
          const all = [...byFace.values()];
          // One legend for a whole tablet's faces (encoded on the same tops: trust.js).
          out.trust = { texture: all[0].texture, meta: face ? all[0].meta : mergeTrustMeta(all.map((t) => t.meta)) };
          tiled.setFaceMaps({ trust: byFace });
        } else if (face) {
          const maps = await loadQualityMaps(get, qualityNames);
          for (const q of maps) created.push(q.texture);
          out.quality = maps;
          tiled.setFaceMaps({ quality: new Map([['', maps]]) });
        } else {
          // Each face's own maps on its tiles, one legend (pooled range) for the tablet.
          const { perFace, merged } = await loadFaceQualityMaps(get, faceRecords.map((f) => f.assets));
          const byFace = new Map();
          faceRecords.forEach((f, i) => {
            f.quality = perFace[i];
            for (const q of perFace[i]) created.push(q.texture);
            byFace.set(f.name, perFace[i]);
          });
          out.quality = merged;
          tiled.setFaceMaps({ quality: byFace });
        }
      })();
      pending.set(kind, job);
      job.catch(() => pending.delete(kind)); // a failed load may be retried
    }
    return pending.get(kind);
  };
  out.dispose = () => {
    tiled.dispose();
    for (const t of created) disposeTexture(t);
    created.length = 0;
  };
  return out;
}

/**
 * The measuring tools' access to `tiles/height.f32` (index.json `height_raw`).
 * `onSurface(points)` puts picked points (mm) on the full-resolution surface: z = −h(x, y)/1000
 * with h bilinear at the point's pixel (SCAN_BUNDLE.md: pixel (r, c) at (c·s, r·s) µm), so a
 * distance picked on a coarse tile is still measured on the full-resolution surface; a point
 * over a hole (NaN) keeps the mesh's z.
 */
function streamedHeights(index, indexUrl) {
  const raw = index.height_raw;
  if (raw.dtype !== '<f4' || raw.order !== 'row-major' || !Array.isArray(raw.shape) || raw.shape.length !== 2) {
    throw new Error(`tiles/index.json: height_raw must be <f4, row-major, shape [H, W]; got ${JSON.stringify(raw)}`);
  }
  const [rows, cols] = raw.shape;
  const reader = createHeightRows({ url: resolveTilesUrl(indexUrl, raw.path), rows, cols });
  const pixelSizeUm = Number(index.pixel_size_um);
  async function onSurface(points) {
    return Promise.all(
      points.map(async (p) => {
        const c = (p[0] * 1000) / pixelSizeUm;
        const r = (p[1] * 1000) / pixelSizeUm;
        const r0 = Math.max(0, Math.min(rows - 2, Math.floor(r)));
        const two = await reader.readRows(r0, r0 + 2);
        const h = bilinearHeight(two, cols, Math.min(2, rows - r0), c, r - r0);
        return Number.isFinite(h) ? [p[0], p[1], -h / 1000] : [...p];
      }),
    );
  }
  return { reader, pixelSizeUm, onSurface };
}

/**
 * The LRU cache's limits for a budget. The renderer stops requesting tiles once its cache is
 * "full" (maxBytesSize) but lets the downloads already in flight land, and never evicts tiles
 * in use; so the cache is told 75 % of the budget and at most MAX_IN_FLIGHT downloads run at
 * once, keeping the remaining quarter for what lands after the cache filled.
 */
const SOFT_FRACTION = 0.75;
const MAX_IN_FLIGHT = 6;

function setBudget(tiles, mb) {
  const bytes = mb * 1024 * 1024;
  tiles.lruCache.maxBytesSize = SOFT_FRACTION * bytes;
  tiles.lruCache.minBytesSize = 0.6 * bytes; // unused tiles are unloaded down to this
  tiles.budgetBytes = bytes;
  // The renderer's default queue and cache are shared module objects; the viewer shows one
  // tiled model at a time, so setting them here is setting them for that model.
  tiles.downloadQueue.maxJobsPerOrigin = MAX_IN_FLIGHT;
}

function abortable(promise, signal, onAbort) {
  if (!signal) return promise;
  return new Promise((resolve, reject) => {
    const abort = () => {
      onAbort();
      reject(new DOMException('aborted', 'AbortError'));
    };
    if (signal.aborted) return abort();
    signal.addEventListener('abort', abort, { once: true });
    promise.then(resolve, reject);
  });
}
