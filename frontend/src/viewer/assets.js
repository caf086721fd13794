/**
 * Loading a model version's assets into GPU-ready three.js objects, with byte progress, and
 * disposing all of them again.
 *
 * Asset names are those of the API's `assets` map (GET /api/v1/models/{id}): `model.glb`
 * (decimated mesh, mm, scan frame), and image-grid textures — `normals.png` (object-space
 * normals, RGB = (n+1)/2), `albedo.png` (sRGB), `curvature*.png` (signed mean curvature, grey
 * 128 = 0), `accessibility.png` (0 = enclosed … 255 = open) — and `quality/*.npy` (float32 maps).
 * Image-grid textures are sampled at v = (r + 0.5)/H: row 0 of the image at v ≈ 0, which is
 * how an ImageBitmap uploads (no flip), and how glTF stores texture coordinates.
 *
 * The mesh, normals and albedo load at once; the other maps on first use (`ensure`).
 */
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { mergeGeometries } from 'three/addons/utils/BufferGeometryUtils.js';
import { parseNpy } from './npy.js';
import { mergeTrustMeta } from './trust.js';

/** Extra smoothing (mip levels) offered when the worker made a single curvature map. */
const SMOOTHED_CURVATURE_LODS = [2, 4];

/** Kinds of map loaded on first use, and how to find their asset names. */
export function classifyAssets(assets) {
  const names = Object.keys(assets ?? {});
  const find = (re) => names.filter((n) => re.test(n)).sort();
  return {
    glb: find(/(^|\/)model\.glb$/)[0] ?? find(/\.glb$/)[0] ?? null,
    normals: find(/(^|\/)normals\.png$/)[0] ?? null,
    albedo: find(/(^|\/)albedo\.png$/)[0] ?? null,
    curvature: find(/(^|\/)curvature[^/]*\.png$/),
    accessibility: find(/(^|\/)accessibility\.png$/)[0] ?? null,
    quality: find(/(^|\/)quality[^/]*\.(npy|png)$|^quality\/[^/]+\.(npy|png)$/),
    height: find(/(^|\/)height\.npy$/)[0] ?? null,
    thumbnail: find(/(^|\/)thumbnail\.png$/)[0] ?? null,
    gloss: find(/^gloss\.png$/)[0] ?? null,
    glossInfo: find(/^gloss\.json$/)[0] ?? null,
    // worker/trust_assets.py: the trust mode's map and legend, and σ_h for the ± of measures
    trust: find(/(^|\/)trust\.png$/)[0] ?? null,
    trustMeta: find(/(^|\/)trust\.json$/)[0] ?? null,
    uncertainty: find(/(^|\/)uncertainty_um\.npy$/)[0] ?? null,
  };
}

/**
 * Fetch a URL as an ArrayBuffer, reporting bytes as they arrive.
 * @param {string} url
 * @param {{signal?: AbortSignal, onBytes?: (loaded: number, total: number) => void}} options
 */
export async function fetchBytes(url, { signal, onBytes = () => {} } = {}) {
  const response = await fetch(url, { signal, credentials: 'same-origin' });
  if (!response.ok) throw new Error(`${url}: HTTP ${response.status}`);
  const total = Number(response.headers.get('Content-Length')) || 0;
  if (!response.body) {
    const buf = await response.arrayBuffer();
    onBytes(buf.byteLength, buf.byteLength);
    return buf;
  }
  const reader = response.body.getReader();
  const chunks = [];
  let loaded = 0;
  for (;;) {
    const { done, value } = await reader.read();
    if (done) break;
    chunks.push(value);
    loaded += value.byteLength;
    onBytes(loaded, Math.max(total, loaded));
  }
  const out = new Uint8Array(loaded);
  let offset = 0;
  for (const c of chunks) {
    out.set(c, offset);
    offset += c.byteLength;
  }
  onBytes(loaded, loaded);
  return out.buffer;
}

async function bytesToTexture(buffer, { srgb, nearest = false }) {
  // 'none' everywhere: normals and curvature are data, not pictures; no colour management.
  const bitmap = await createImageBitmap(new Blob([buffer]), {
    imageOrientation: 'none',
    premultiplyAlpha: 'none',
    colorSpaceConversion: 'none',
  });
  const texture = new THREE.Texture(bitmap);
  texture.flipY = false;
  texture.colorSpace = srgb ? THREE.SRGBColorSpace : THREE.NoColorSpace;
  // nearest: a map of codes (trust.png's classes) must not be interpolated between codes.
  texture.generateMipmaps = !nearest;
  texture.minFilter = nearest ? THREE.NearestFilter : THREE.LinearMipmapLinearFilter;
  texture.magFilter = nearest ? THREE.NearestFilter : THREE.LinearFilter;
  texture.wrapS = THREE.ClampToEdgeWrapping;
  texture.wrapT = THREE.ClampToEdgeWrapping;
  texture.needsUpdate = true;
  return texture;
}

/**
 * A model's trust map (trust.png, nearest-sampled: its red channel holds class codes) and its
 * legend (trust.json, {} when absent): {texture, meta}.
 * @param {(name: string) => Promise<ArrayBuffer>} get
 */
export async function loadTrustMap(get, pngName, metaName) {
  const [png, meta] = await Promise.all([
    get(pngName),
    metaName ? get(metaName).then((b) => JSON.parse(new TextDecoder().decode(b))) : {},
  ]);
  return { texture: await bytesToTexture(png, { srgb: false, nearest: true }), meta };
}

/**
 * A model's quality maps, each {name, texture, range}: .npy as float textures with their
 * robust range, .png as 8-bit on [0, 1].
 * @param {(name: string) => Promise<ArrayBuffer>} get
 * @param {string[]} qualityNames
 */
export async function loadQualityMaps(get, qualityNames) {
  const maps = [];
  for (const name of qualityNames) {
    const buf = await get(name);
    if (name.endsWith('.npy')) {
      const { texture, range } = npyToTexture(buf);
      maps.push({ name, texture, range });
    } else {
      maps.push({ name, texture: await bytesToTexture(buf, { srgb: false }), range: [0, 1] });
    }
  }
  return maps;
}

/**
 * The quality maps of a whole tablet's faces: each face's own ({@link loadQualityMaps}, named
 * as in a face model, `quality/<map>.npy`, relative to the face's folder) and one entry per
 * map name for the page's select and legend, its range the 2nd–98th percentiles of every
 * face's values pooled (one legend reads the whole tablet; a face's map is drawn against it).
 * @param {(name: string) => Promise<ArrayBuffer>} get
 * @param {{prefix: string | null, quality: string[]}[]} faceAssets {@link classifyFaceAssets} per face
 * @returns {Promise<{perFace: object[][], merged: {name: string, texture: object, range: number[]}[]}>}
 */
export async function loadFaceQualityMaps(get, faceAssets) {
  const perFace = await Promise.all(
    faceAssets.map(async (fa) => {
      if (!fa.prefix || !fa.quality?.length) return [];
      const maps = await loadQualityMaps(get, fa.quality.map((n) => `${fa.prefix}${n}`));
      return maps.map((m, i) => ({ ...m, name: fa.quality[i] }));
    }),
  );
  const all = perFace.flat();
  const merged = [...new Set(all.map((m) => m.name))].sort().map((name) => {
    const maps = all.filter((m) => m.name === name);
    const values = maps.map((m) => m.texture.image?.data);
    const range = values.every((v) => v instanceof Float32Array)
      ? pooledRobustRange(values)
      : [Math.min(...maps.map((m) => m.range[0])), Math.max(...maps.map((m) => m.range[1]))];
    return { name, texture: maps[0].texture, range };
  });
  return { perFace, merged };
}

/**
 * A float map (.npy, rows × cols) as a single-channel float texture plus a robust display
 * range (2nd to 98th percentile of its finite values).
 */
export function npyToTexture(buffer) {
  const { shape, data } = parseNpy(buffer);
  if (shape.length !== 2) throw new Error(`expected a 2-D map, got shape (${shape.join(', ')})`);
  const [rows, cols] = shape;
  const values = Float32Array.from(data);
  const texture = new THREE.DataTexture(values, cols, rows, THREE.RedFormat, THREE.FloatType);
  texture.minFilter = THREE.NearestFilter;
  texture.magFilter = THREE.NearestFilter;
  texture.needsUpdate = true;
  return { texture, range: robustRange(values) };
}

/** 2nd and 98th percentiles of the finite values (a subsample of at most ~100k). */
export function robustRange(values) {
  return pooledRobustRange([values]);
}

/**
 * 2nd and 98th percentiles of the finite values of several maps taken together (a whole
 * tablet's faces, one legend for all), each subsampled with the same step so that every
 * face weighs by its pixel count (at most ~100k values in all).
 * @param {ArrayLike<number>[]} arrays
 * @returns {[number, number]}
 */
export function pooledRobustRange(arrays) {
  const total = arrays.reduce((n, a) => n + a.length, 0);
  const step = Math.max(1, Math.floor(total / 100000));
  const sample = [];
  for (const values of arrays) {
    for (let i = 0; i < values.length; i += step) if (Number.isFinite(values[i])) sample.push(values[i]);
  }
  if (!sample.length) return [0, 1];
  sample.sort((a, b) => a - b);
  const lo = sample[Math.floor(0.02 * (sample.length - 1))];
  const hi = sample[Math.ceil(0.98 * (sample.length - 1))];
  return hi > lo ? [lo, hi] : [lo, lo + 1];
}

/**
 * Folder of a face's maps among a whole-tablet model's assets (`faces/<name>/normals.png`, …):
 * the node name with every character but ASCII letters, digits, '-', '_' and '.' replaced by
 * '_' (worker/register/io.py's `face_asset_dir`, the same rule).
 */
export function faceAssetPrefix(name) {
  const safe = [...String(name)].map((ch) => (/^[A-Za-z0-9._-]$/.test(ch) ? ch : '_')).join('');
  return `faces/${safe.replace(/^\.+|\.+$/g, '') || '_'}`;
}

/** A face's own maps among the assets: {normals, curvature: [], accessibility, gloss, glossInfo,
 * trust, trustMeta, uncertainty, height} (names or null). */
export function classifyFaceAssets(assets, name) {
  const prefix = `${faceAssetPrefix(name)}/`;
  const own = Object.fromEntries(
    Object.entries(assets ?? {})
      .filter(([n]) => n.startsWith(prefix) && !n.slice(prefix.length).includes('/'))
      .map(([n, url]) => [n.slice(prefix.length), url]),
  );
  const c = classifyAssets(own);
  const full = (n) => (n ? prefix + n : null);
  // Its quality maps, named as in a face model (quality/<map>.npy), so one name picks the
  // same map on every face (the quality mode's select).
  const quality = Object.keys(assets ?? {})
    .filter((n) => n.startsWith(`${prefix}quality/`) && /^[^/]+\.(npy|png)$/.test(n.slice(prefix.length + 8)))
    .map((n) => n.slice(prefix.length))
    .sort();
  return {
    normals: full(c.normals),
    curvature: c.curvature.map(full),
    accessibility: full(c.accessibility),
    gloss: full(c.gloss),
    glossInfo: full(c.glossInfo),
    // worker/register/run.py: the face's trust assets and its full-resolution heights
    trust: full(c.trust),
    trustMeta: full(c.trustMeta),
    uncertainty: full(c.uncertainty),
    height: full(c.height),
    quality,
    prefix,
  };
}

/** A face without an image grid: none of its maps. */
const NO_FACE_ASSETS = Object.freeze({
  normals: null,
  curvature: [],
  accessibility: null,
  gloss: null,
  glossInfo: null,
  trust: null,
  trustMeta: null,
  uncertainty: null,
  height: null,
  quality: [],
  prefix: null,
});

/**
 * The GLB's meshes as one geometry in the scene's frame. A scene of several nodes (the
 * whole-tablet model: one node per scanned face) becomes one draw group per mesh, named after
 * its node (`parts`), so faces can be hidden; each part keeps its own albedo (the node's
 * baseColorTexture) and the rotation of its node (scan → tablet), under which its object-space
 * normal map (`faces/<name>/normals.png`, scan frame) is turned into the tablet frame.
 */
async function glbToGeometry(buffer) {
  const gltf = await new GLTFLoader().parseAsync(buffer, '');
  gltf.scene.updateMatrixWorld(true);
  // model.glb is in glTF's convention (metres, +Y up) through one root node that records the
  // scan frame in its extras (SCAN_BUNDLE.md); the viewer works in scan-frame millimetres, so
  // that node's transform is undone. Older GLBs without it are in scan-frame mm already.
  const toScanFrame = new THREE.Matrix4();
  gltf.scene.traverse((obj) => {
    if (obj.userData?.scan_frame) toScanFrame.copy(obj.matrixWorld).invert();
  });
  const geometries = [];
  const partInfo = [];
  const junk = new Set();
  gltf.scene.traverse((obj) => {
    if (!obj.isMesh) return;
    const g = obj.geometry.clone();
    const toWorld = new THREE.Matrix4().multiplyMatrices(toScanFrame, obj.matrixWorld);
    g.applyMatrix4(toWorld);
    for (const name of Object.keys(g.attributes)) {
      if (!['position', 'normal', 'uv'].includes(name)) g.deleteAttribute(name);
    }
    if (!g.attributes.normal) g.computeVertexNormals();
    geometries.push(g);
    obj.geometry.dispose();
    const mats = Array.isArray(obj.material) ? obj.material : [obj.material];
    let albedo = null;
    for (const m of mats) {
      if (!albedo && m.map) albedo = m.map;
      for (const v of Object.values(m)) if (v?.isTexture && v !== albedo) junk.add(v);
      m.dispose();
    }
    partInfo.push({
      // A one-primitive node is the Mesh itself; a multi-primitive node is its parent Group.
      name: obj.name || obj.parent?.name || '',
      albedo,
      rotation: new THREE.Matrix3().setFromMatrix4(new THREE.Matrix4().extractRotation(toWorld)),
      toWorld,
      hasUv: Boolean(obj.geometry.attributes.uv),
    });
  });
  if (!geometries.length) throw new Error('model.glb holds no mesh');
  const multi = geometries.length > 1;
  for (const t of junk) disposeTexture(t);
  if (multi) {
    for (const g of geometries) {
      // Parts without texture coordinates still merge (uv unused: no image-grid maps).
      if (!g.attributes.uv) {
        g.setAttribute('uv', new THREE.BufferAttribute(new Float32Array(g.attributes.position.count * 2), 2));
      }
    }
    if (geometries.some((g) => g.index) && !geometries.every((g) => g.index)) {
      for (let i = 0; i < geometries.length; i++) {
        if (!geometries[i].index) continue;
        const flat = geometries[i].toNonIndexed();
        geometries[i].dispose();
        geometries[i] = flat;
      }
    }
  }
  const geometry = multi ? mergeGeometries(geometries, true) : geometries[0];
  if (multi) for (const g of geometries) g.dispose();
  if (!geometry) throw new Error('model.glb: its meshes have different attributes');
  if (!geometry.attributes.uv) throw new Error('model.glb has no texture coordinates (TEXCOORD_0)');
  const glbAlbedo = multi ? null : partInfo[0].albedo;
  if (multi) {
    // The albedo of a part without an image grid cannot be mapped; drop it.
    for (const p of partInfo) if (!p.hasUv && p.albedo) disposeTexture(p.albedo), (p.albedo = null);
  }
  return { geometry, glbAlbedo, parts: multi ? partInfo : [] };
}

export function disposeTexture(t) {
  if (!t) return;
  t.dispose();
  if (typeof ImageBitmap !== 'undefined' && t.image instanceof ImageBitmap) t.image.close();
}

/**
 * Load a model's mesh and first textures.
 * @param {Record<string, string>} assets name → URL
 * @param {{onProgress?: (fraction: number, label: string) => void, signal?: AbortSignal}} options
 * @returns {Promise<object>} {geometry, parts, normals, albedo, curvature, accessibility,
 *   quality, names, ensure(kind), dispose()}; `parts`: node names of a multi-node GLB, one per
 *   draw group of `geometry` (empty for a one-mesh model)
 */
export async function loadModelAssets(assets, { onProgress = () => {}, signal } = {}) {
  const names = classifyAssets(assets);
  if (!names.glb) throw new Error('this model version has no model.glb');
  const progress = new Map();
  const report = (name) => (loaded, total) => {
    progress.set(name, [loaded, total]);
    let l = 0;
    let t = 0;
    for (const [a, b] of progress.values()) {
      l += a;
      t += b;
    }
    onProgress(t ? l / t : 0, `${(l / 1e6).toFixed(1)} / ${(t / 1e6).toFixed(1)} MB`);
  };
  const get = (name) => fetchBytes(assets[name], { signal, onBytes: report(name) });

  const out = {
    names,
    geometry: null,
    parts: [],
    faces: [],
    normals: null,
    albedo: null,
    curvature: null,
    accessibility: null,
    quality: null,
    gloss: null, // {texture, scale, exponent}: the scan's measured gloss (worker/photos.py)
    trust: null, // {texture, meta} once loaded, false when the model has no trust.png
  };
  const created = [];
  const track = (t) => {
    if (t) created.push(t);
    return t;
  };
  /** {texture, scale, exponent} of a gloss.png + gloss.json pair, or null (a fit that stood down). */
  async function loadGloss(pngName, infoName) {
    const [pngBuf, infoBuf] = await Promise.all([get(pngName), get(infoName)]);
    const info = JSON.parse(new TextDecoder().decode(infoBuf));
    if (!(Number(info.strength_scale) > 0 && Number(info.exponent) > 0)) return null;
    return {
      texture: track(await bytesToTexture(pngBuf, { srgb: false })),
      scale: Number(info.strength_scale),
      exponent: Number(info.exponent),
    };
  }
  out.dispose = () => {
    out.geometry?.dispose();
    for (const t of created) disposeTexture(t);
    created.length = 0;
  };

  try {
    const [glbBuf, normalsBuf, albedoBuf] = await Promise.all([
      get(names.glb),
      names.normals ? get(names.normals) : null,
      names.albedo ? get(names.albedo) : null,
    ]);
    const { geometry, glbAlbedo, parts } = await glbToGeometry(glbBuf);
    out.geometry = geometry;
    out.parts = parts.map((p) => p.name);
    out.faces = parts.map((p) => ({
      name: p.name,
      assets: p.hasUv ? classifyFaceAssets(assets, p.name) : NO_FACE_ASSETS,
      rotation: p.rotation,
      // scan frame (mm) → model frame and back (faceGrids.js), column-major
      toModel: p.toWorld.elements.slice(),
      toFace: p.toWorld.clone().invert().elements.slice(),
      albedo: track(p.albedo),
      normals: null,
      curvature: null,
      accessibility: null,
      gloss: null,
      trust: null, // {texture, meta} once loaded, false when the face has no trust.png
      quality: null, // its quality maps once loaded ([] when it has none)
    }));
    // A whole tablet's quality maps are its faces' (quality/<map>.npy in each face's folder).
    if (out.faces.length) names.quality = [...new Set(out.faces.flatMap((f) => f.assets.quality))].sort();
    // Every face's full-resolution normals load with the mesh (they are what relights it),
    // and its measured gloss (natural colour) where its scan had one.
    await Promise.all(
      out.faces.map(async (f) => {
        if (f.assets.normals) f.normals = track(await bytesToTexture(await get(f.assets.normals), { srgb: false }));
        if (f.assets.gloss && f.assets.glossInfo) f.gloss = await loadGloss(f.assets.gloss, f.assets.glossInfo);
      }),
    );
    out.normals = normalsBuf ? track(await bytesToTexture(normalsBuf, { srgb: false })) : null;
    if (albedoBuf) {
      out.albedo = track(await bytesToTexture(albedoBuf, { srgb: true }));
      disposeTexture(glbAlbedo);
    } else {
      out.albedo = track(glbAlbedo); // the GLB's baseColorTexture is the same albedo
    }
    if (names.gloss && names.glossInfo) out.gloss = await loadGloss(names.gloss, names.glossInfo);
  } catch (err) {
    out.dispose();
    throw err;
  }

  const pending = new Map();
  /**
   * Load a lazily loaded kind ('curvature', 'accessibility', 'quality') once.
   * @returns {Promise<void>}
   */
  out.ensure = (kind) => {
    if (out[kind] !== null || !['curvature', 'accessibility', 'quality', 'trust'].includes(kind)) {
      return Promise.resolve();
    }
    if (!pending.has(kind)) {
      pending.set(kind, loadKind(kind));
    }
    return pending.get(kind);
  };

  async function loadKind(kind) {
    if (kind === 'trust' && out.faces.length) {
      // A whole tablet: each face's own trust map, on its own grid, all on one legend
      // (worker/register/run.py encodes every face with the same legend tops).
      await Promise.all(
        out.faces.map(async (f) => {
          if (!f.assets.trust) {
            f.trust = false;
            return;
          }
          const [png, meta] = await Promise.all([
            get(f.assets.trust),
            f.assets.trustMeta ? get(f.assets.trustMeta).then((b) => JSON.parse(new TextDecoder().decode(b))) : {},
          ]);
          f.trust = { texture: track(await bytesToTexture(png, { srgb: false, nearest: true })), meta };
        }),
      );
      const withTrust = out.faces.filter((f) => f.trust);
      out.trust = withTrust.length
        ? { texture: withTrust[0].trust.texture, meta: mergeTrustMeta(withTrust.map((f) => f.trust.meta)) }
        : false;
      return;
    }
    if (kind === 'trust') {
      if (!names.trust) {
        out.trust = false;
        return;
      }
      out.trust = await loadTrustMap(get, names.trust, names.trustMeta);
      track(out.trust.texture);
      return;
    }
    if (kind === 'quality' && out.faces.length) {
      // A whole tablet: each face's own quality maps on its own grid, one legend for all.
      const { perFace, merged } = await loadFaceQualityMaps(
        get,
        out.faces.map((f) => f.assets),
      );
      out.faces.forEach((f, i) => {
        f.quality = perFace[i];
        for (const q of perFace[i]) track(q.texture);
      });
      out.quality = merged;
      return;
    }
    if (out.faces.length && kind !== 'quality') {
      // A whole tablet: each face's own map, on its own image grid.
      let any = false;
      await Promise.all(
        out.faces.map(async (f) => {
          if (kind === 'accessibility') {
            f.accessibility = f.assets.accessibility
              ? track(await bytesToTexture(await get(f.assets.accessibility), { srgb: false }))
              : false;
            any ||= Boolean(f.accessibility);
          } else {
            f.curvature = await curvatureLayers(f.assets.curvature);
            any ||= f.curvature.length > 0;
          }
        }),
      );
      // The model-level entry says whether any face has it (for the mode's "missing" notice).
      if (kind === 'accessibility') out.accessibility = any ? out.faces.find((f) => f.accessibility).accessibility : false;
      else out.curvature = any ? out.faces.find((f) => f.curvature.length).curvature : [];
      return;
    }
    if (kind === 'accessibility') {
      out.accessibility = names.accessibility
        ? track(await bytesToTexture(await get(names.accessibility), { srgb: false }))
        : false;
    } else if (kind === 'curvature') {
      out.curvature = await curvatureLayers(names.curvature);
    } else if (kind === 'quality') {
      out.quality = await loadQualityMaps(get, names.quality);
      for (const q of out.quality) track(q.texture);
    }
  }

  async function curvatureLayers(curvatureNames) {
    const layers = [];
    for (const name of curvatureNames) {
      const texture = track(await bytesToTexture(await get(name), { srgb: false }));
      const short = name.split('/').pop();
      layers.push({ name: short, texture, lod: 0, label: short });
    }
    if (layers.length === 1) {
      for (const lod of SMOOTHED_CURVATURE_LODS) {
        layers.push({ ...layers[0], lod, label: `${layers[0].name}, smoothed over ${2 ** lod} px` });
      }
    }
    return layers;
  }

  return out;
}
