/**
 * The relighting viewer: `createViewer(canvas)` → `{load, setLight, setShading, setView, …}`.
 *
 * Follows three.js' own one-model examples: one scene, one mesh, render on demand (only when
 * the camera, light, shading or size changes), and every GPU resource disposed when a model is
 * replaced or the viewer is destroyed. The model sits untransformed in the scene, so world
 * coordinates are the scan frame in millimetres (x right, y down, z away from the camera).
 */
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { loadModelAssets } from './assets.js';
import {
  cameraLightToWorld,
  cameraLightToWorldAngles,
  lightAngles,
  lightDirection,
  worldLightToCameraAngles,
} from './light.js';
import { createMarks, pickPoint, projectPoint } from './marks.js';
import { LAZY_KINDS, lensMissingMessage, missingMessage as missingMessageOf } from './modes.js';
import { applyPartShading, boundModes, chooseQualityMap, createPartMaterial, createRelightMaterial, MODE_INDEX } from './material.js';
import { defaultViewState, SHADING_MODES } from './permalink.js';
import { applyHiddenParts, createPartToggles, hiddenParts } from './parts.js';
import { availableViews, canonicalView } from './views.js';
import { applyEnhance, defaultEnhance } from './enhance.js';
import { TRUST_LAYERS } from './trust.js';
import { tilesIndexUrl } from './tilesIndex.js';
import { groupOfPoint, groupVertexSpans } from './faceGrids.js';
import { createAdaptiveResolution } from './adaptiveResolution.js';

/**
 * The streaming module (tiles.js: 3d-tiles-renderer and meshoptimizer's decoder, whose
 * WebAssembly compiles when the module loads), asked for once. Started when the viewer is
 * created so that its download and compilation overlap the page's API requests instead of
 * following them (issue 19: first render).
 */
let tilesModule = null;
function loadTilesModule() {
  tilesModule ??= import('./tiles.js').catch((err) => {
    tilesModule = null; // a later load may try again
    throw err;
  });
  return tilesModule;
}

const PERSPECTIVE_FOV_DEG = 30;

/**
 * How far (mm) the fragments of a whole tablet's face are pushed back where its weight is 0
 * (material.js, `seamDepth`): more than the registration's misfit between two faces (tens of
 * µm) and than a pixel's depth on a steep rim, less than the tablet's features (a wedge is
 * ~0.5–1 mm deep, but a push only decides between surfaces within it of each other).
 */
const SEAM_DEPTH_MM = 0.4;

/**
 * @param {HTMLCanvasElement} canvas
 * @param {object} [options]
 * @param {(what: string) => void} [options.onChange] called after the view, light or shading
 *   changed (e.g. to update a permalink or a scale bar)
 */
export function createViewer(canvas, { onChange = () => {} } = {}) {
  loadTilesModule().catch(() => {}); // prefetch; a failure is reported by load()
  const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, alpha: false });
  const fullPixelRatio = Math.min(window.devicePixelRatio || 1, 2);
  renderer.setPixelRatio(fullPixelRatio);
  // Reduced resolution while the camera moves under the user's hand, full when it stops.
  const adaptive = createAdaptiveResolution({
    onSettle: () => {
      zooming = false;
      invalidate();
    },
  });
  // This move zooms (wheel, keys): it asks for new detail, so the tiles' levels stay those of
  // full resolution (an orbit or pan frame takes levels for its reduced pixels: tiles.js).
  let zooming = false;
  // The last frame's cost on the page's thread (bench/streaming_profile.py): the tiles' update
  // and the render call (WebGL commands issued; the GPU process draws them afterwards).
  const frameStats = { lastScale: 1, firstTileRenderMs: null, frames: 0, updateMs: 0, renderMs: 0, drawCalls: 0, triangles: 0 };
  let standIn = null; // a mesh with the tiles' material, for precompileTileProgram
  renderer.setClearColor(0x1d1f24, 1);
  renderer.outputColorSpace = THREE.SRGBColorSpace;

  const scene = new THREE.Scene();
  const marks = createMarks(scene); // measuring marks, drawn on top of the model

  const ortho = new THREE.OrthographicCamera(-1, 1, 1, -1, 0.01, 1000);
  const persp = new THREE.PerspectiveCamera(PERSPECTIVE_FOV_DEG, 1, 0.01, 1000);
  let camera = ortho;
  let controls = null;
  let orthoHalfHeight = 50; // mm visible above the target at zoom 1

  const material = createRelightMaterial();
  // Material 1 of a multi-part mesh: three.js skips draw groups whose material is invisible.
  const hiddenMaterial = new THREE.MeshBasicMaterial({ visible: false });
  let model = null; // {mesh, assets, box, missing: Set}
  const state = defaultViewState();
  state.enhance = defaultEnhance();
  const pendingLoads = new Set();
  let frameRequested = false;
  let disposed = false;

  function makeControls() {
    // OrbitControls fixes its orbit axis from camera.up when constructed, so a new view with a
    // different up needs new controls.
    const target = controls ? controls.target.clone() : new THREE.Vector3();
    controls?.dispose();
    controls = new OrbitControls(camera, canvas);
    controls.target.copy(target);
    controls.enableDamping = false; // render on demand: no animation loop to settle damping
    controls.zoomToCursor = true;
    controls.screenSpacePanning = true;
    controls.addEventListener('change', () => {
      adaptive.moved();
      invalidate();
      onChange('camera');
    });
    controls.update();
  }

  function invalidate() {
    if (frameRequested || disposed) return;
    frameRequested = true;
    requestAnimationFrame(render);
  }

  function updateProjection() {
    const w = canvas.clientWidth || canvas.width || 1;
    const h = canvas.clientHeight || canvas.height || 1;
    const aspect = w / h;
    ortho.left = -orthoHalfHeight * aspect;
    ortho.right = orthoHalfHeight * aspect;
    ortho.top = orthoHalfHeight;
    ortho.bottom = -orthoHalfHeight;
    persp.aspect = aspect;
    ortho.updateProjectionMatrix();
    persp.updateProjectionMatrix();
  }

  function resize() {
    const w = canvas.clientWidth;
    const h = canvas.clientHeight;
    if (!w || !h) return;
    renderer.setSize(w, h, false);
    updateProjection();
    invalidate();
    onChange('size');
  }

  function render(timeMs = performance.now()) {
    frameRequested = false;
    if (disposed) return;
    const ratio = fullPixelRatio * adaptive.frame(timeMs);
    if (renderer.getPixelRatio() !== ratio) {
      renderer.setPixelRatio(ratio);
      // The lens is placed in drawing-buffer pixels (enhance.js): follow the new ratio.
      state.enhance = applyEnhance(material.uniforms, state.enhance, { pixelRatio: ratio, canvasHeight: canvas.clientHeight || 1 }, MODE_INDEX);
    }
    frameStats.lastScale = ratio / fullPixelRatio;
    draw();
  }

  /** Draw one frame at the renderer's current size (the screenshot's own, or the canvas'). */
  function draw() {
    const u = material.uniforms;
    u.uOrtho.value = camera.isOrthographicCamera;
    camera.getWorldDirection(u.uViewDirOrtho.value).negate();
    u.uProjection.value.copy(camera.projectionMatrix);
    if (state.light.follow) updateLightDirection();
    const t0 = performance.now();
    // Streaming: levels by screen-space error, loads (those under the cursor first).
    const detailScale = adaptive.moving && !zooming ? renderer.getPixelRatio() / fullPixelRatio : 1;
    model?.tiles?.update(camera, renderer, { focus: cursor, detailScale });
    const firstTile = frameStats.firstTileRenderMs === null && model?.tiles?.stats().visibleTiles > 0;
    const t1 = performance.now();
    renderer.render(scene, camera);
    const t2 = performance.now();
    // The first frame with a tile: how long its draw call took (shader program, uploads).
    if (firstTile) frameStats.firstTileRenderMs = t2 - t1;
    frameStats.frames++;
    frameStats.updateMs = t1 - t0;
    frameStats.renderMs = t2 - t1;
    frameStats.drawCalls = renderer.info.render.calls;
    frameStats.triangles = renderer.info.render.triangles;
  }

  // The cursor over the canvas (CSS px from its top left), null when outside: the tiles
  // under it load first (tileFocus.js), e.g. where a wheel zoom went.
  let cursor = null;
  const onPointer = (e) => {
    const r = canvas.getBoundingClientRect();
    cursor = { x: e.clientX - r.left, y: e.clientY - r.top };
    if (e.type === 'wheel') zooming = true;
  };
  const onLeave = () => {
    cursor = null;
  };
  canvas.addEventListener('pointermove', onPointer);
  canvas.addEventListener('wheel', onPointer, { passive: true });
  canvas.addEventListener('pointerleave', onLeave);

  const resizeObserver = new ResizeObserver(resize);
  resizeObserver.observe(canvas);
  makeControls();
  resize();

  // --- light and shading ------------------------------------------------------------------

  /** Unit screen-right, screen-up and viewing direction of the camera, in the world frame. */
  function cameraBasis() {
    camera.updateMatrixWorld();
    const e = camera.matrixWorld.elements;
    return { right: [e[0], e[1], e[2]], up: [e[4], e[5], e[6]], dir: [-e[8], -e[9], -e[10]] };
  }

  function updateLightDirection() {
    const { azimuthDeg, polarDeg, follow } = state.light;
    const l = follow ? cameraLightToWorld(azimuthDeg, polarDeg, cameraBasis()) : lightDirection(azimuthDeg, polarDeg);
    material.uniforms.uLightDir.value.set(l[0], l[1], l[2]);
  }

  /**
   * Set the light. `follow: true` makes the angles relative to the camera (the light turns with
   * the view, like a lamp on the camera); false keeps it fixed to the model, angles in the
   * model's frame. Switching keeps the light where it is at that moment.
   */
  function setLight(light) {
    if (light.follow !== undefined && Boolean(light.follow) !== state.light.follow) {
      const basis = cameraBasis();
      const { azimuthDeg, polarDeg } = state.light;
      const world = state.light.follow ? cameraLightToWorld(azimuthDeg, polarDeg, basis) : lightDirection(azimuthDeg, polarDeg);
      // Express the current direction in the new frame (the call's own angles, if any, follow).
      state.light.follow = Boolean(light.follow);
      Object.assign(state.light, state.light.follow ? worldLightToCameraAngles(world, basis) : lightAngles(world));
    }
    const { follow, ...rest } = light;
    Object.assign(state.light, rest);
    updateLightDirection();
    const u = material.uniforms;
    u.uIntensity.value = state.light.intensity;
    u.uAmbient.value = state.light.ambient;
    u.uGloss.value = state.light.gloss;
    invalidate();
    onChange('light');
  }

  /**
   * A light given relative to the view (the raking presets: "from the left of the screen"):
   * when the light follows the camera these are its angles; when it is fixed to the model they
   * are turned into the model's frame, so the face in view is lit from that side and the light
   * stays on the tablet afterwards.
   */
  function setLightFromView({ azimuthDeg, polarDeg }) {
    if (state.light.follow) setLight({ azimuthDeg, polarDeg });
    else setLight(cameraLightToWorldAngles(azimuthDeg, polarDeg, cameraBasis()));
  }

  /**
   * The light's angles relative to the current view (x = screen right, y = screen down,
   * z = viewing direction): what the light widget shows, whichever frame the light is in.
   * @returns {{azimuthDeg: number, polarDeg: number}}
   */
  function lightInView() {
    const { azimuthDeg, polarDeg, follow } = state.light;
    if (follow) return { azimuthDeg, polarDeg };
    return worldLightToCameraAngles(lightDirection(azimuthDeg, polarDeg), cameraBasis());
  }

  function setShading(shading) {
    const next = { ...state.shading, ...shading };
    if (!SHADING_MODES.includes(next.mode)) {
      throw new RangeError(`mode must be one of ${SHADING_MODES.join(', ')}, got ${next.mode}`);
    }
    Object.assign(state.shading, next);
    applyShading();
    invalidate();
    onChange('shading');
    ensureKind(LAZY_KINDS[next.mode]);
  }

  /** Load a lazily loaded kind of map (modes.js' LAZY_KINDS) once, then apply it. */
  function ensureKind(kind) {
    if (kind && model && model.assets[kind] === null) {
      const m = model;
      const job = m.assets
        .ensure(kind)
        .catch((err) => {
          m.errors[kind] = err.message;
        })
        .then(() => {
          pendingLoads.delete(job);
          if (model !== m) return;
          applyShading();
          invalidate();
          onChange('shading');
        });
      pendingLoads.add(job);
    }
  }

  /**
   * Unsharp masking of the normals and of the luminance, and the lens (enhance.js): shader
   * options shared by every face. `lens`: null, or {mode, x, y, radius} in CSS pixels of the
   * canvas (x right, y down from its top-left corner).
   */
  function setEnhance(next) {
    const lensMode = state.enhance.lens?.mode ?? null;
    state.enhance = applyEnhance(
      material.uniforms,
      { ...state.enhance, ...next },
      { pixelRatio: renderer.getPixelRatio(), canvasHeight: canvas.clientHeight || 1 },
      MODE_INDEX,
    );
    if (state.enhance.lens) ensureKind(LAZY_KINDS[state.enhance.lens.mode]);
    // The lens' mode may need maps the main mode does not bind.
    if (lensMode !== (state.enhance.lens?.mode ?? null)) applyShading();
    invalidate();
    onChange('enhance');
  }

  /**
   * Resolves once a streamed model's tiles for the current view are in: after a drawn frame
   * (which runs the renderer's update) nothing is queued, downloading or parsing, twice in a
   * row; at once for a single mesh. A streamed tablet's faces get their frames from their
   * tiles (tiles.js faceFrame), which a measurement restored from a link needs.
   * @param {number} [timeoutMs] give up (resolve) after this long
   */
  async function whenTilesSettled(timeoutMs = 30000) {
    const deadline = performance.now() + timeoutMs;
    const frame = () => new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)));
    for (let calm = 0; calm < 2 && model?.tiles && performance.now() < deadline; ) {
      invalidate();
      await frame();
      calm = model?.tiles?.stats().idle ? calm + 1 : 0;
    }
  }

  /** Resolves when the maps requested so far have loaded (or failed). */
  async function whenIdle() {
    while (pendingLoads.size) await Promise.all([...pendingLoads]);
  }

  function applyShading() {
    const u = material.uniforms;
    const s = state.shading;
    u.uMode.value = MODE_INDEX[s.mode];
    u.uEmphasis.value = s.exaggeration;
    const a = model?.assets;
    // The maps of the main mode and of the lens' mode (enhance.js: any mode in the lens).
    // The quality map by name (the select's), the same on every face of a whole tablet.
    const q = chooseQualityMap(a?.quality, s.quality);
    const bound = { ...s, lensMode: state.enhance.lens?.mode ?? null, quality: q?.name ?? null };
    const modes = boundModes(bound);
    u.uHasCurvature.value = false;
    u.uHasAccess.value = false;
    u.uHasQuality.value = false;
    if (modes.has('curvature')) {
      const layers = a?.curvature ?? [];
      const layer = layers[Math.min(s.curvatureScale, layers.length - 1)];
      if (layer) {
        u.uCurvatureMap.value = layer.texture;
        u.uCurvatureLod.value = layer.lod;
        u.uHasCurvature.value = true;
      }
    }
    if (modes.has('accessibility') && a?.accessibility) {
      u.uAccessMap.value = a.accessibility;
      u.uHasAccess.value = true;
    }
    if (modes.has('quality') && q) {
      u.uQualityMap.value = q.texture;
      u.uQualityRange.value.set(q.range[0], q.range[1]);
      u.uHasQuality.value = true;
    }
    // The trust map is bound whenever it is loaded: the lens may show it over another mode.
    u.uHasTrust.value = Boolean(a?.trust?.texture);
    if (a?.trust?.texture) u.uTrustMap.value = a.trust.texture;
    u.uTrustLayer.value = Math.max(0, TRUST_LAYERS.indexOf(s.trustLayer));
    // A streamed model decodes the maps its tiles need for this mode (tiles.js decodeLazyMap).
    const decoding = model?.tiles?.applyShading(bound);
    if (decoding) {
      const job = decoding.finally(() => pendingLoads.delete(job));
      pendingLoads.add(job);
    }
    for (const [i, m] of (model?.partMaterials ?? []).entries()) applyPartShading(m, a.faces[i], bound);
  }

  /**
   * What the current shading mode lacks, as a sentence for the UI, or null.
   * @returns {string | null}
   */
  function missingMessage() {
    if (!model) return null;
    const notes = [
      missingMessageOf(state.shading.mode, model.assets, model.errors),
      lensMissingMessage(state.enhance.lens?.mode ?? null, state.shading.mode, model.assets, model.errors),
    ];
    return notes.filter(Boolean).join(' ') || null;
  }

  // --- camera -----------------------------------------------------------------------------

  function setView(name) {
    if (!model) return;
    if (!model.views.includes(name)) {
      throw new RangeError(`this model has no ${name} view; it has ${model.views.join(', ')}`);
    }
    const w = canvas.clientWidth || 1;
    const h = canvas.clientHeight || 1;
    const v = canonicalView(name, model.box, { aspect: w / h });
    placeCamera({
      position: v.position,
      target: v.target,
      up: v.up,
      halfHeight: v.halfHeight,
    });
  }

  function placeCamera({ position, target, up, halfHeight, zoom }) {
    for (const cam of [ortho, persp]) {
      cam.up.set(...up);
      cam.position.set(...position);
      cam.lookAt(...target);
    }
    const distance = Math.hypot(...position.map((p, i) => p - target[i]));
    if (halfHeight !== undefined) {
      // Same visible size at the target in both projections.
      orthoHalfHeight = halfHeight;
      ortho.zoom = 1;
      const d = halfHeight / Math.tan((PERSPECTIVE_FOV_DEG * Math.PI) / 360);
      const dir = position.map((p, i) => (p - target[i]) / distance);
      persp.position.set(...target.map((t, i) => t + dir[i] * d));
    } else {
      ortho.zoom = zoom ?? 1;
    }
    if (controls) controls.target.set(...target);
    updateClipping();
    updateProjection();
    makeControls();
    invalidate();
    onChange('camera');
  }

  function updateClipping() {
    const radius = model ? model.radius : 100;
    for (const cam of [ortho, persp]) {
      const d = cam.position.distanceTo(controls ? controls.target : new THREE.Vector3());
      cam.near = Math.max(0.01, d - radius * 4);
      cam.far = d + radius * 4;
      if (cam.isPerspectiveCamera) cam.near = Math.max(d / 1000, 0.01);
    }
  }

  /** Zoom by a factor (> 1: closer), about the orbit target; for keyboard use. */
  function zoomBy(factor) {
    if (!(factor > 0)) throw new RangeError(`factor must be > 0, got ${factor}`);
    if (camera.isOrthographicCamera) {
      ortho.zoom *= factor;
      ortho.updateProjectionMatrix();
    } else {
      const offset = persp.position.clone().sub(controls.target).divideScalar(factor);
      persp.position.copy(controls.target).add(offset);
      updateClipping();
      updateProjection();
    }
    controls.update();
    zooming = true;
    adaptive.moved();
    invalidate();
    onChange('camera');
  }

  /** Turn the tablet about the screen's vertical axis through the target, in degrees. */
  function orbitBy(degrees) {
    const offset = camera.position.clone().sub(controls.target);
    offset.applyAxisAngle(camera.up.clone().normalize(), (degrees * Math.PI) / 180);
    camera.position.copy(controls.target).add(offset);
    camera.lookAt(controls.target);
    makeControls();
    adaptive.moved();
    invalidate();
    onChange('camera');
  }

  function setProjection(projection) {
    if (projection !== 'orthographic' && projection !== 'perspective') {
      throw new RangeError(`projection must be orthographic or perspective, got ${projection}`);
    }
    const next = projection === 'orthographic' ? ortho : persp;
    if (next === camera) return;
    const target = controls.target;
    const tanHalf = Math.tan((PERSPECTIVE_FOV_DEG * Math.PI) / 360);
    const dir = camera.position.clone().sub(target).normalize();
    if (next === persp) {
      const visibleHalf = orthoHalfHeight / ortho.zoom;
      persp.position.copy(target).addScaledVector(dir, visibleHalf / tanHalf);
    } else {
      const visibleHalf = persp.position.distanceTo(target) * tanHalf;
      ortho.position.copy(target).addScaledVector(dir, Math.max(visibleHalf / tanHalf, model?.radius * 3 || 100));
      ortho.zoom = orthoHalfHeight / visibleHalf;
    }
    next.up.copy(camera.up);
    next.lookAt(target);
    camera = next;
    updateClipping();
    updateProjection();
    makeControls();
    invalidate();
    onChange('camera');
  }

  // --- loading ----------------------------------------------------------------------------

  /**
   * Load a model version, replacing (and disposing) the current one.
   * @param {object} source
   * @param {Record<string, string>} source.assets asset name → URL (the API's `assets` map)
   * @param {(fraction: number, label: string) => void} [source.onProgress]
   * @param {AbortSignal} [source.signal]
   */
  async function load({ assets, onProgress = () => {}, signal, tiles = {} } = {}) {
    if (tilesIndexUrl(assets)) return loadTiled(assets, { signal, ...tiles });
    const loaded = await loadModelAssets(assets, { onProgress, signal });
    if (disposed || signal?.aborted) {
      loaded.dispose();
      return null;
    }
    unloadModel();
    const { geometry } = loaded;

    geometry.computeBoundingBox();
    geometry.computeBoundingSphere();
    const multi = loaded.parts.length > 1;
    // A whole tablet: one material per face (its own maps and rotation, the light shared),
    // then the invisible one for hidden faces.
    const partMaterials = multi ? loaded.faces.map((face) => createPartMaterial(material, face, { seamDepthMm: SEAM_DEPTH_MM })) : [];
    const mesh = new THREE.Mesh(geometry, multi ? [...partMaterials, hiddenMaterial] : material);
    scene.add(mesh);
    const bb = geometry.boundingBox;
    const box = { min: bb.min.toArray(), max: bb.max.toArray() };
    const parts = multi ? createPartToggles(loaded.parts) : null;
    const views = availableViews(multi ? 'tablet' : 'face');
    model = { mesh, assets: loaded, box, radius: geometry.boundingSphere.radius || 1, errors: {}, parts, partMaterials, views };
    if (parts) assignGroupMaterials();
    const u = material.uniforms;
    u.uNormalMap.value = loaded.normals ?? material.userData.blank;
    u.uHasNormalMap.value = Boolean(loaded.normals);
    u.uAlbedoMap.value = loaded.albedo ?? material.userData.blank;
    u.uHasAlbedo.value = Boolean(loaded.albedo);
    u.uGlossMap.value = loaded.gloss?.texture ?? material.userData.blank;
    u.uHasGlossMap.value = Boolean(loaded.gloss);
    u.uGlossScale.value = loaded.gloss?.scale ?? 0;
    u.uGlossExponent.value = loaded.gloss?.exponent ?? 32;
    const img = loaded.normals?.image ?? loaded.albedo?.image;
    if (img) u.uTexelSize.value.set(1 / img.width, 1 / img.height);
    u.uHeightRange.value.set(-bb.max.z, -bb.min.z);
    u.uObjectToWorld.value.setFromMatrix4(mesh.matrixWorld);
    setShading({}); // applies the mode and starts loading its maps
    setView('obverse');
    onChange('model');
    return model;
  }

  /**
   * A model with tiles/index.json: streamed (tiles.js) instead of the single mesh; the same
   * material's light, mode and camera uniforms drive every tile.
   * @param {{budgetMb?: number, errorTarget?: number}} options the tile cache's GPU budget
   */
  async function loadTiled(assets, { signal, budgetMb, errorTarget }) {
    // The tiles' shader program, compiled while the tileset and the first tile download.
    precompileTileProgram();
    const { openTiledModel, tiledAssets } = await loadTilesModule();
    const tiled = await openTiledModel({
      indexUrl: tilesIndexUrl(assets),
      baseMaterial: material,
      invalidate,
      budgetMb,
      errorTarget,
      seamDepthMm: SEAM_DEPTH_MM,
      signal,
    });
    if (disposed || signal?.aborted) {
      tiled.dispose();
      return null;
    }
    markOnce('dh:tileset-ready'); // for bench/streaming.py's first-render steps
    const onTile = () => {
      markOnce('dh:tile-parsed');
      tiled.tiles.removeEventListener('load-model', onTile);
    };
    tiled.tiles.addEventListener('load-model', onTile);
    unloadModel();
    scene.add(tiled.object);
    const views = availableViews(tiled.kind);
    // A whole tablet's faces get the checkboxes of the single-mesh path (parts.js).
    const parts = tiled.faceNames.length > 1 ? createPartToggles(tiled.faceNames) : null;
    model = { mesh: tiled.object, tiles: tiled, assets: tiledAssets(tiled, assets, { signal }), box: tiled.box, radius: tiled.radius, errors: {}, parts, partMaterials: [], views };
    material.uniforms.uHeightRange.value.set(-tiled.box.max[2], -tiled.box.min[2]);
    setShading({});
    setView('obverse');
    onChange('model');
    return model;
  }

  /**
   * Compile the relighting program the tiles' materials use (createPartMaterial: the base
   * material's shaders, so one program for every tile) on a stand-in mesh, without drawing:
   * compileAsync lets the browser compile it in parallel (KHR_parallel_shader_compile) while
   * the first tiles download, instead of in the first frame that draws one.
   */
  function precompileTileProgram() {
    if (standIn) return;
    // Kept until the viewer is disposed: three.js frees a program no material uses.
    standIn = new THREE.Mesh(
      new THREE.PlaneGeometry(1, 1), // position, normal, uv: as a tile's mesh
      createPartMaterial(material, { rotation: new THREE.Matrix3(), normals: null, albedo: null }, { seamDepthMm: 0 }),
    );
    renderer.compileAsync(standIn, camera).catch((err) => {
      console.warn('shader precompilation skipped:', err); // the first frame compiles it then
    });
  }

  function markOnce(name) {
    if (!performance.getEntriesByName?.(name).length) performance.mark?.(name);
  }

  function unloadModel() {
    if (!model) return;
    scene.remove(model.mesh);
    for (const m of model.partMaterials) m.dispose();
    model.assets.dispose(); // geometry and every texture
    clearOverlay();
    const u = material.uniforms;
    const blank = material.userData.blank;
    for (const key of ['uNormalMap', 'uAlbedoMap', 'uCurvatureMap', 'uAccessMap', 'uQualityMap', 'uGlossMap']) {
      u[key].value = blank;
    }
    u.uHasGlossMap.value = false;
    model = null;
    invalidate();
  }

  // --- parts (faces of the whole-tablet model) ---------------------------------------------

  /** Names of the model's parts (glTF nodes; the faces of a whole-tablet model), or []. */
  function partNames() {
    return model?.parts ? [...model.parts.names] : [];
  }

  /** Show or hide one part; renders (once) only when something changed. */
  function setPartVisible(name, visible) {
    if (!model?.parts) throw new RangeError('this model has no parts to show or hide');
    if (model.parts.set(name, visible)) partsChanged();
  }

  /** mergeGeometries numbers the groups 0, 1, 2…: group i is drawn with face i's material, or
   * with the invisible one (last) when that face is hidden. */
  function assignGroupMaterials() {
    const { parts, partMaterials } = model;
    model.mesh.geometry.groups.forEach((g, i) => {
      g.materialIndex = parts.isVisible(parts.names[i]) ? i : partMaterials.length;
    });
  }

  function partsChanged() {
    if (model.tiles) model.tiles.setHiddenFaces(hiddenParts(model.parts));
    else assignGroupMaterials();
    invalidate();
    onChange('parts');
  }

  // --- picking and overlay ----------------------------------------------------------------

  /** The model point under a page (CSS pixel) position: {point (mm), uv, part} or null
   * (part: the whole tablet's face that was hit, else null). */
  function pick(clientX, clientY) {
    const hit = model ? pickPoint(canvas, camera, model.mesh, clientX, clientY) : null;
    if (hit && model.tiles) hit.part = model.parts ? model.tiles.faceOf(hit.object) : null;
    else if (hit) hit.part = model.parts && hit.group !== null ? (model.parts.names[hit.group] ?? null) : null;
    return hit;
  }

  /**
   * The index (in `model.assets.faces`) of the shown face of a whole tablet a model point lies
   * on (faceGrids.js: the face of its nearest vertex), or -1 (a one-mesh model, no face).
   * @param {number[]} point mm
   */
  function faceOfPoint(point) {
    if (!model?.parts || !model.assets.faces?.length) return -1;
    if (model.tiles) {
      // A streamed tablet has no one mesh to search: the face drawn at the point, i.e. the
      // tile hit by the line of sight through it (the point was picked there), when that hit
      // is the point itself (within a coarse tile's deviation from the surface).
      const { x, y } = project(point);
      const hit = pick(x, y);
      const tol = Math.max(0.5, 0.03 * model.radius);
      if (!hit?.part || Math.hypot(...hit.point.map((v, k) => v - point[k])) > tol) return -1;
      return model.assets.faces.findIndex((f) => f.name === hit.part);
    }
    const g = model.mesh.geometry;
    model.faceSpans ??= groupVertexSpans(g.index?.array ?? null, g.groups);
    const names = model.parts.names;
    return groupOfPoint(g.attributes.position.array, model.faceSpans, point, (i) => model.parts.isVisible(names[i]));
  }

  /** Draw an object over the model (annotation regions); returns a function removing it. */
  function addOverlay(object) {
    scene.add(object);
    invalidate();
    return () => {
      scene.remove(object);
      invalidate();
    };
  }

  /** The light's unit direction in the world frame (a face model's scan frame). */
  function lightWorld() {
    return material.uniforms.uLightDir.value.toArray();
  }

  /** Page (CSS pixel) position of a point in mm. */
  function project(point) {
    return projectPoint(canvas, camera, point);
  }

  /** Millimetres per CSS pixel at the orbit target (for the scale bar). */
  function mmPerPixel() {
    const h = canvas.clientHeight || 1;
    if (camera.isOrthographicCamera) return (2 * orthoHalfHeight) / ortho.zoom / h;
    const d = persp.position.distanceTo(controls.target);
    return (2 * d * Math.tan((PERSPECTIVE_FOV_DEG * Math.PI) / 360)) / h;
  }

  /**
   * Add a three.js object (in model mm) to the scene, drawn with the model (e.g. a section's
   * outline); returns a function that removes it. The caller owns and disposes the object.
   */
  function addOverlay(object) {
    scene.add(object);
    invalidate();
    return () => {
      scene.remove(object);
      invalidate();
    };
  }

  /** The camera, for tools that project or render regions (read-only use). */
  function getCamera() {
    return camera;
  }

  function clearOverlay() {
    marks.clear();
    invalidate();
  }

  /** Draw marks (points and a polyline) for measurements; replaces the previous marks. */
  function setMarks(points) {
    if (!model) return;
    marks.set(points, model.radius * 0.012);
    invalidate();
  }

  // --- state, screenshot, cleanup ---------------------------------------------------------

  function getState() {
    const t = controls.target;
    return {
      model: state.model,
      camera: {
        projection: camera.isOrthographicCamera ? 'orthographic' : 'perspective',
        position: camera.position.toArray(),
        target: t.toArray(),
        up: camera.up.toArray(),
        zoom: camera.isOrthographicCamera ? ortho.zoom : 1,
      },
      light: { ...state.light },
      shading: { ...state.shading },
      hidden: hiddenParts(model?.parts),
      enhance: { ...state.enhance, lens: state.enhance.lens ? { ...state.enhance.lens } : null },
    };
  }

  /**
   * Restore a state from {@link getState} or a permalink (camera null: keep the framing;
   * `hidden` absent: keep the parts as they are, else exactly those parts are hidden).
   * @returns {{unknownParts: string[]}} hidden names this model has no part for (ignored)
   */
  function setState(next) {
    let unknownParts = [];
    if (Array.isArray(next.hidden)) {
      const { changed, unknown } = applyHiddenParts(model?.parts ?? null, next.hidden);
      unknownParts = unknown;
      if (changed) partsChanged();
    }
    if (next.model !== undefined) state.model = next.model;
    if (next.light) setLight(next.light);
    if (next.shading) setShading(next.shading);
    if (next.enhance) setEnhance(next.enhance);
    if (next.camera) {
      if (next.camera.projection === 'perspective') {
        camera = persp;
      } else {
        camera = ortho;
      }
      camera.up.set(...next.camera.up);
      camera.position.set(...next.camera.position);
      camera.lookAt(...next.camera.target);
      if (camera.isOrthographicCamera) ortho.zoom = next.camera.zoom;
      controls.target.set(...next.camera.target);
      updateClipping();
      updateProjection();
      makeControls();
      invalidate();
    }
    return { unknownParts };
  }

  /**
   * Render the current view at a chosen size and return it as a PNG.
   * @param {{width: number, height: number}} size in pixels (clamped to the GPU's limit)
   * @returns {Promise<Blob>}
   */
  async function screenshot({ width, height }) {
    await whenIdle(); // the maps asked for (a mode's lazily loaded or decoded ones) drawn too
    const max = renderer.capabilities.maxTextureSize;
    if (!(width >= 16 && height >= 16)) throw new RangeError('width and height must be ≥ 16 px');
    const scale = Math.min(1, max / width, max / height);
    const w = Math.round(width * scale);
    const h = Math.round(height * scale);
    const prevRatio = renderer.getPixelRatio();
    const prev = renderer.getSize(new THREE.Vector2());
    // Render at the requested size, read it back in the same task (no preserveDrawingBuffer
    // needed), then restore: nothing is composited in between, so nothing flickers.
    renderer.setPixelRatio(1);
    renderer.setSize(w, h, false);
    // Contain: the shot shows at least what the canvas shows, whatever its aspect ratio.
    const aspect = w / h;
    const canvasAspect = (canvas.clientWidth || 1) / (canvas.clientHeight || 1);
    const grow = Math.max(1, canvasAspect / aspect);
    const saved = { t: ortho.top, b: ortho.bottom, l: ortho.left, r: ortho.right, pa: persp.aspect, fov: persp.fov };
    ortho.top = orthoHalfHeight * grow;
    ortho.bottom = -orthoHalfHeight * grow;
    ortho.left = -orthoHalfHeight * grow * aspect;
    ortho.right = orthoHalfHeight * grow * aspect;
    persp.aspect = aspect;
    persp.fov = (2 * Math.atan(Math.tan((PERSPECTIVE_FOV_DEG * Math.PI) / 360) * grow) * 180) / Math.PI;
    ortho.updateProjectionMatrix();
    persp.updateProjectionMatrix();
    const u = material.uniforms;
    const savedLens = [u.uLensCentre.value.clone(), u.uLensRadius.value];
    const lens = state.enhance.lens;
    if (lens) {
      // The lens where it is on the canvas: canvas NDC → view → the shot's wider frame.
      const ch = canvas.clientHeight || 1;
      const nx = (2 * lens.x) / (canvas.clientWidth || 1) - 1;
      const ny = 1 - (2 * lens.y) / ch;
      const sx = (nx * canvasAspect) / (grow * aspect);
      const sy = ny / grow;
      u.uLensCentre.value.set(((sx + 1) / 2) * w, ((sy + 1) / 2) * h);
      u.uLensRadius.value = (lens.radius * h) / (ch * grow);
    }
    draw();
    u.uLensCentre.value.copy(savedLens[0]);
    u.uLensRadius.value = savedLens[1];
    const blobPromise = new Promise((resolve, reject) =>
      canvas.toBlob((b) => (b ? resolve(b) : reject(new Error('the browser could not encode the PNG'))), 'image/png'),
    );
    renderer.setPixelRatio(prevRatio);
    renderer.setSize(prev.x, prev.y, false);
    Object.assign(ortho, { top: saved.t, bottom: saved.b, left: saved.l, right: saved.r });
    persp.aspect = saved.pa;
    persp.fov = saved.fov;
    updateProjection();
    draw();
    return blobPromise;
  }

  /** GPU memory in use (three.js' renderer.info.memory): geometries and textures. */
  function memory() {
    return { ...renderer.info.memory };
  }

  /** A streamed model's figures (tiles.js `stats`), or null for a single-mesh model. */
  function streaming() {
    return model?.tiles?.stats() ?? null;
  }

  function dispose() {
    if (disposed) return;
    unloadModel();
    disposed = true;
    adaptive.dispose();
    standIn?.geometry.dispose();
    standIn?.material.dispose();
    resizeObserver.disconnect();
    canvas.removeEventListener('pointermove', onPointer);
    canvas.removeEventListener('wheel', onPointer);
    canvas.removeEventListener('pointerleave', onLeave);
    controls.dispose();
    material.userData.blank.dispose();
    material.dispose();
    hiddenMaterial.dispose();
    renderer.renderLists.dispose();
    renderer.dispose();
  }

  setLight(state.light);
  applyShading();

  return {
    load,
    unload: unloadModel,
    setLight,
    setLightFromView,
    lightInView,
    setShading,
    setView,
    setProjection,
    zoomBy,
    orbitBy,
    resetView: () => setView('obverse'),
    getState,
    lightWorld,
    setState,
    pick,
    faceOfPoint,
    addOverlay,
    project,
    mmPerPixel,
    setMarks,
    clearMarks: clearOverlay,
    missingMessage,
    screenshot,
    memory,
    streaming,
    /** Figures of the drawing: the last frame's resolution scale (1: full; lower while the
     * camera moves) and the first tile frame's render call, ms. */
    frameStats: () => ({ ...frameStats, moving: adaptive.moving, learnedScale: adaptive.scale }),
    /** Adaptive resolution while moving on (default) or off (every frame at full resolution). */
    setAdaptiveResolution: (on) => adaptive.setEnabled(on),
    whenIdle,
    whenTilesSettled,
    invalidate,
    setEnhance,
    addOverlay,
    getCamera,
    partNames,
    setPartVisible,
    dispose,
    /** Canonical views this model has (a face model: its own side only, views.js). */
    get views() {
      return model ? [...model.views] : [];
    },
    get model() {
      return model;
    },
    get light() {
      return { ...state.light };
    },
    get shading() {
      return { ...state.shading };
    },
    get enhance() {
      return { ...state.enhance, lens: state.enhance.lens ? { ...state.enhance.lens } : null };
    },
    get projection() {
      return camera.isOrthographicCamera ? 'orthographic' : 'perspective';
    },
  };
}
