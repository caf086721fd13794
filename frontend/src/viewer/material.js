/**
 * The viewer's one material: relighting from full-resolution OBJECT-SPACE normals
 * (`normals.png`, RGB = (n + 1)/2 in the scan frame) on the decimated mesh, so every wedge is
 * lit exactly whatever the mesh resolution, plus the other shading modes.
 *
 * Lighting (scan frame; the model sits in the world untransformed, so world = scan frame):
 *   colour = base · (ambient + intensity · max(0, n·l)) + gloss · intensity · (n·h)^s
 * with l from light.js (SCAN_BUNDLE.md convention) and h the Blinn half vector between l and
 * the direction to the camera. Light is independent of the view: l is fixed in the scan frame.
 */
import * as THREE from 'three';
import { SHADING_MODES } from './permalink.js';
import { EXTRAS_GLSL, extraUniforms } from './shaderExtras.js';

export const MODE_INDEX = Object.freeze(Object.fromEntries(SHADING_MODES.map((m, i) => [m, i])));

/** Colour of fired clay for the "clay" and derived modes (linear RGB). */
const CLAY_LINEAR = new THREE.Color().setRGB(0.78, 0.7, 0.6, THREE.SRGBColorSpace);

const vertexShader = /* glsl */ `
  out vec2 vUv;
  out vec3 vNormalW;
  out vec3 vPosW;
  out vec3 vPosView;
  out float vHeightMm;
  void main() {
    vUv = uv;
    vec4 world = modelMatrix * vec4(position, 1.0);
    vPosW = world.xyz;
    vPosView = (viewMatrix * world).xyz;
    vNormalW = normalize(mat3(modelMatrix) * normal);
    vHeightMm = -position.z; // h is measured toward the camera: z = -h
    gl_Position = projectionMatrix * viewMatrix * world;
  }
`;

const fragmentShader = /* glsl */ `
  precision highp float;
  layout(location = 0) out highp vec4 pc_fragColor;
  #define gl_FragColor pc_fragColor
  in vec2 vUv;
  in vec3 vNormalW;
  in vec3 vPosW;
  in vec3 vPosView;
  in float vHeightMm;

  uniform int uMode;
  uniform mat3 uObjectToWorld;    // rotation of the model (identity: the scan frame is the world)
  uniform sampler2D uNormalMap;
  uniform bool uHasNormalMap;
  uniform sampler2D uAlbedoMap;
  uniform bool uHasAlbedo;
  uniform sampler2D uCurvatureMap;
  uniform float uCurvatureLod;
  uniform sampler2D uAccessMap;
  uniform sampler2D uQualityMap;
  uniform vec2 uQualityRange;
  // Tile-local uv → the face's whole image grid (offset xy, scale zw): a streamed tile's maps
  // cover its own rectangle, the trust and quality maps the whole face (tiles.js tileFaceUv);
  // (0, 0, 1, 1) on a single mesh, whose uv already span the face.
  uniform vec4 uFaceUv;
  // Each lazily loaded map is present (bound for the main mode and for the lens' mode).
  uniform bool uHasCurvature;
  uniform bool uHasAccess;
  uniform bool uHasQuality;
  uniform vec2 uTexelSize;
  uniform vec3 uLightDir;
  uniform float uIntensity;
  uniform float uAmbient;
  uniform float uGloss;
  uniform sampler2D uGlossMap;    // measured specular strength (red), worker/photos.py
  uniform bool uHasGlossMap;
  uniform float uGlossScale;      // k_s of red = 1
  uniform float uGlossExponent;   // the scan's Blinn-Phong sharpness
  uniform float uEmphasis;
  uniform vec2 uHeightRange;
  uniform vec3 uClay;
  uniform bool uOrtho;
  uniform vec3 uViewDirOrtho;     // direction from the scene toward an orthographic camera
  uniform float uSeamDepthMm;     // > 0: faces overlap; the normal map's alpha is a weight
  uniform mat4 uProjection;       // the camera's projection (for the seam's depth offset)

  // Where faces of a whole tablet overlap they measured the same surface (to the registration's
  // tens of µm), so depth testing alone would pick between them at random (z-fighting, seams
  // along the rims). Each fragment is pushed away from the camera by (1 − w)·uSeamDepthMm,
  // w its face's weight (alpha of its normal map: 0 at the mask's rim and on steep slopes,
  // 1 well inside and facing the scan's camera), so in an overlap the face that measured the
  // surface best is the one drawn, and the change of face happens where the weights cross.
  void seamDepth(float w) {
    vec3 p = vPosView;
    float push = uSeamDepthMm * (1.0 - clamp(w, 0.0, 1.0));
    if (uOrtho) p.z -= push; else p += normalize(p) * push;
    vec4 clip = uProjection * vec4(p, 1.0);
    gl_FragDepth = clamp(0.5 * clip.z / clip.w + 0.5, 0.0, 1.0);
  }

  vec2 faceUv() { return uFaceUv.xy + uFaceUv.zw * vUv; }

  vec3 objectNormal(vec2 uv, float lod) {
    return textureLod(uNormalMap, uv, lod).xyz * 2.0 - 1.0;
  }

  // Ramp colours are given in sRGB (as in the page's legend); the output stage encodes
  // linear values to sRGB, so decode them first.
  vec3 fromSrgb(vec3 c) {
    return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(vec3(0.04045), c));
  }

  // Diverging ramp for signed values t in [-1, 1]: blue (concave) - white - red (convex).
  vec3 diverging(float t) {
    t = clamp(t, -1.0, 1.0);
    vec3 neg = vec3(0.230, 0.299, 0.754);
    vec3 mid = vec3(0.865, 0.865, 0.865);
    vec3 pos = vec3(0.706, 0.016, 0.150);
    return fromSrgb(t < 0.0 ? mix(mid, neg, -t) : mix(mid, pos, t));
  }

  // Perceptually ordered ramp (a 5-stop approximation of viridis) for t in [0, 1].
  vec3 sequential(float t) {
    t = clamp(t, 0.0, 1.0);
    vec3 c0 = vec3(0.267, 0.005, 0.329);
    vec3 c1 = vec3(0.231, 0.322, 0.545);
    vec3 c2 = vec3(0.129, 0.569, 0.549);
    vec3 c3 = vec3(0.369, 0.788, 0.384);
    vec3 c4 = vec3(0.993, 0.906, 0.144);
    float s = t * 4.0;
    vec3 c = s < 1.0 ? mix(c0, c1, s) : s < 2.0 ? mix(c1, c2, s - 1.0) : s < 3.0 ? mix(c2, c3, s - 2.0) : mix(c3, c4, s - 3.0);
    return fromSrgb(c);
  }

  vec3 lit(vec3 base, vec3 n) {
    vec3 l = normalize(uLightDir);
    vec3 v = uOrtho ? normalize(uViewDirOrtho) : normalize(cameraPosition - vPosW);
    float diffuse = max(dot(n, l), 0.0);
    vec3 h = normalize(l + v);
    float spec = diffuse > 0.0 ? pow(max(dot(n, h), 0.0), 48.0) : 0.0;
    return base * (uAmbient + uIntensity * diffuse) + vec3(uGloss * uIntensity * spec);
  }

  // The scan's own gloss (worker/photos.py): k_s·max(0, n·h)^alpha, k_s per pixel relative to
  // a white diffuser, the same units as the albedo term, so a burnished surface shines where
  // the photographs showed it shine.
  vec3 measuredGloss(vec3 n) {
    if (!uHasGlossMap) return vec3(0.0);
    vec3 l = normalize(uLightDir);
    vec3 v = uOrtho ? normalize(uViewDirOrtho) : normalize(cameraPosition - vPosW);
    if (dot(n, l) <= 0.0) return vec3(0.0);
    float ks = texture(uGlossMap, vUv).r * uGlossScale;
    return vec3(ks * uIntensity * pow(max(dot(n, normalize(l + v)), 0.0), uGlossExponent));
  }

  ${EXTRAS_GLSL}

  vec3 shade(int mode, vec3 n, vec3 nObj) {
    vec3 colour;
    if (mode == 0) {          // natural colour
      vec3 albedo = uHasAlbedo ? texture(uAlbedoMap, vUv).rgb : uClay;
      colour = lit(albedo, n) + measuredGloss(n);
      if (uLumaUnsharp > 0.0 && uHasNormalMap) colour = unsharpLuma(colour, vUv, true);
    } else if (mode == 1) {   // plain clay
      colour = lit(uClay, n);
      if (uLumaUnsharp > 0.0 && uHasNormalMap) colour = unsharpLuma(colour, vUv, false);
    } else if (mode == 2) {   // signed mean curvature, 8-bit grey 128 = 0
      if (uHasCurvature) {
        float k = textureLod(uCurvatureMap, vUv, uCurvatureLod).r * 255.0 / 127.5 - 1.0;
        colour = diverging(k * uEmphasis);
      } else colour = lit(uClay, n) * 0.5;
    } else if (mode == 3) {   // accessibility / ambient occlusion
      colour = uHasAccess ? uClay * texture(uAccessMap, vUv).r : lit(uClay, n) * 0.5;
    } else if (mode == 4) {   // relief: unsharp-masked normals on a flattened tablet
      // n' = normalize(v + (1 + k)(n - blur(n))): the slow curvature of the tablet (blur) is
      // replaced by the view axis v = (0, 0, -1), and the detail n - blur(n) is amplified, so
      // every wedge reads the same wherever it sits on the curved surface.
      if (uHasNormalMap) {
        vec3 blur = vec3(0.0);
        float radius = 24.0;
        float lod = log2(radius) - 1.0;
        for (int i = 0; i < 12; i++) {
          float a = float(i) * 0.52359878;
          vec2 off = vec2(cos(a), sin(a)) * radius * uTexelSize;
          blur += objectNormal(vUv + off, lod);
        }
        blur = normalize(blur);
        vec3 enhanced = vec3(0.0, 0.0, -1.0) + (1.0 + uEmphasis) * (nObj - blur);
        n = normalize(uObjectToWorld * enhanced);
      }
      colour = lit(uClay, n);
    } else if (mode == 5) {   // depth: height on a colour ramp, lit by exaggerated normals
      float span = max(uHeightRange.y - uHeightRange.x, 1e-6);
      float t = (vHeightMm - uHeightRange.x) / span;
      vec3 ex = uHasNormalMap ? vec3(nObj.xy * uEmphasis, nObj.z) : nObj;
      n = normalize(uObjectToWorld * ex);
      colour = sequential(t) * (0.35 + 0.65 * max(dot(n, normalize(uLightDir)), 0.0));
    } else if (mode == 6) {   // normals as stored: RGB = (n + 1) / 2
      colour = fromSrgb(nObj * 0.5 + 0.5); // shown as the PNG's own values after sRGB output
    } else if (mode == 7) {   // quality map on a sequential ramp
      if (uHasQuality) {
        float q = texture(uQualityMap, faceUv()).r;
        float span = max(uQualityRange.y - uQualityRange.x, 1e-20);
        colour = q != q ? vec3(0.2) : sequential((q - uQualityRange.x) / span);
      } else colour = lit(uClay, n) * 0.5;
    } else {                  // trust: where the heights come from, how far they hold
      colour = uHasTrust ? trustColour(n) : lit(uClay, n) * 0.5;
    }
    return colour;
  }

  void main() {
    if (uSeamDepthMm > 0.0 && uHasNormalMap) seamDepth(texture(uNormalMap, vUv).a);
    else gl_FragDepth = gl_FragCoord.z;
    vec3 nObj = uHasNormalMap ? objectNormal(vUv, 0.0) : vNormalW;
    if (uNormalUnsharp > 0.0 && uHasNormalMap) nObj = unsharpNormal(nObj, vUv);
    vec3 n = normalize(uObjectToWorld * nObj);
    if (!uHasNormalMap) n = normalize(vNormalW);
    vec3 colour = shade(inLens() ? uLensMode : uMode, n, nObj);
    gl_FragColor = vec4(colour, 1.0);
    #include <colorspace_fragment>
  }
`;

/**
 * Create the relighting material. Textures are set later with `material.uniforms.uX.value`.
 * @returns {THREE.ShaderMaterial}
 */
export function createRelightMaterial() {
  const blank = new THREE.DataTexture(new Uint8Array([128, 128, 0, 255]), 1, 1);
  blank.needsUpdate = true;
  return new THREE.ShaderMaterial({
    name: 'RelightMaterial',
    glslVersion: THREE.GLSL3,
    vertexShader,
    fragmentShader,
    side: THREE.DoubleSide,
    uniforms: {
      uMode: { value: 0 },
      uObjectToWorld: { value: new THREE.Matrix3() },
      uNormalMap: { value: blank },
      uHasNormalMap: { value: false },
      uAlbedoMap: { value: blank },
      uHasAlbedo: { value: false },
      uCurvatureMap: { value: blank },
      uCurvatureLod: { value: 0 },
      uAccessMap: { value: blank },
      uQualityMap: { value: blank },
      uQualityRange: { value: new THREE.Vector2(0, 1) },
      uFaceUv: { value: new THREE.Vector4(0, 0, 1, 1) },
      uHasCurvature: { value: false },
      uHasAccess: { value: false },
      uHasQuality: { value: false },
      uTexelSize: { value: new THREE.Vector2(1, 1) },
      uLightDir: { value: new THREE.Vector3(0, 0, -1) },
      uIntensity: { value: 1 },
      uAmbient: { value: 0.15 },
      uGloss: { value: 0 },
      uGlossMap: { value: blank },
      uHasGlossMap: { value: false },
      uGlossScale: { value: 0 },
      uGlossExponent: { value: 32 },
      uEmphasis: { value: 2 },
      uHeightRange: { value: new THREE.Vector2(0, 1) },
      uClay: { value: new THREE.Vector3(CLAY_LINEAR.r, CLAY_LINEAR.g, CLAY_LINEAR.b) },
      uOrtho: { value: true },
      uViewDirOrtho: { value: new THREE.Vector3(0, 0, -1) },
      uSeamDepthMm: { value: 0 },
      uProjection: { value: new THREE.Matrix4() },
      ...extraUniforms(blank),
    },
    userData: { blank },
  });
}

/** Uniforms each face of a whole tablet has of its own; the others are shared with the base. */
export const PART_UNIFORMS = Object.freeze([
  'uObjectToWorld',
  'uNormalMap',
  'uHasNormalMap',
  'uAlbedoMap',
  'uHasAlbedo',
  'uCurvatureMap',
  'uCurvatureLod',
  'uAccessMap',
  'uHasCurvature',
  'uHasAccess',
  'uTexelSize',
  'uSeamDepthMm',
  'uGlossMap', // each face its own scan's measured gloss (worker/photos.py)
  'uHasGlossMap',
  'uGlossScale',
  'uGlossExponent',
  'uTrustMap', // each face its own trust map (worker/register/run.py), on its own grid
  'uHasTrust',
  'uFaceUv', // a streamed tile's rectangle of its face's grid (tiles.js tileFaceUv)
  'uQualityMap', // each face its own quality map, on its own grid (the range is shared)
  'uHasQuality',
]);

/**
 * A material for one face of a whole tablet: the same shaders (so the same compiled program)
 * with the light, mode and camera uniforms SHARED with `base` (the same objects: setting the
 * light once lights every face) and the maps of {@link PART_UNIFORMS} its own.
 * @param {THREE.ShaderMaterial} base from {@link createRelightMaterial}
 * @param {{rotation: THREE.Matrix3, normals: THREE.Texture | null, albedo: THREE.Texture | null,
 *   gloss?: {texture: THREE.Texture, scale: number, exponent: number} | null}} face
 *   the face's scan → tablet rotation and maps (assets.js' `faces`)
 * @param {{seamDepthMm: number}} options how far a fragment of weight 0 is pushed back
 * @returns {THREE.ShaderMaterial}
 */
export function createPartMaterial(base, face, { seamDepthMm }) {
  const uniforms = { ...base.uniforms };
  for (const key of PART_UNIFORMS) {
    const v = base.uniforms[key].value;
    uniforms[key] = { value: v?.clone && !v.isTexture ? v.clone() : v };
  }
  const blank = base.userData.blank;
  uniforms.uObjectToWorld.value.copy(face.rotation);
  uniforms.uNormalMap.value = face.normals ?? blank;
  uniforms.uHasNormalMap.value = Boolean(face.normals);
  uniforms.uAlbedoMap.value = face.albedo ?? blank;
  uniforms.uHasAlbedo.value = Boolean(face.albedo);
  const img = face.normals?.image ?? face.albedo?.image;
  uniforms.uTexelSize.value.set(img ? 1 / img.width : 1, img ? 1 / img.height : 1);
  uniforms.uSeamDepthMm.value = seamDepthMm;
  // The face's measured gloss (assets.js' `gloss`), none for a face whose scan had none.
  uniforms.uGlossMap.value = face.gloss?.texture ?? blank;
  uniforms.uHasGlossMap.value = Boolean(face.gloss);
  uniforms.uGlossScale.value = face.gloss?.scale ?? 0;
  uniforms.uGlossExponent.value = face.gloss?.exponent ?? 32;
  // No map of a lazily loaded kind until applyPartShading binds the face's own.
  uniforms.uHasCurvature.value = false;
  uniforms.uHasAccess.value = false;
  uniforms.uTrustMap.value = blank;
  uniforms.uHasTrust.value = false;
  uniforms.uQualityMap.value = blank;
  uniforms.uHasQuality.value = false;
  return new THREE.ShaderMaterial({
    name: 'RelightPartMaterial',
    glslVersion: THREE.GLSL3,
    vertexShader: base.vertexShader,
    fragmentShader: base.fragmentShader,
    side: base.side,
    uniforms,
  });
}

/**
 * The modes whose maps must be bound: the main mode and the lens' (enhance.js), once each.
 * @param {{mode: string, lensMode?: string | null}} shading
 * @returns {Set<string>}
 */
export function boundModes(shading) {
  return new Set([shading.mode, shading.lensMode].filter(Boolean));
}

/**
 * The quality map of a face chosen by the page's select: the one named `name`, else the
 * face's first (as the base material's), or null when the face has none.
 * @param {{name: string}[] | null | undefined} maps
 * @param {string | null | undefined} name
 */
export function chooseQualityMap(maps, name) {
  if (!maps?.length) return null;
  return maps.find((q) => q.name === name) ?? maps[0];
}

/**
 * The shading-mode maps of one face of a whole tablet (or of one streamed tile): its own
 * curvature, accessibility, quality and trust map, for the main mode and the lens' mode
 * (`shading.lensMode`, {@link boundModes}); the quality map's range is the base material's
 * (shared: one legend for every face).
 * @param {THREE.ShaderMaterial} m from {@link createPartMaterial}
 * @param {object} face assets.js' face record (`curvature` layers, `accessibility` texture,
 *   `quality` [{name, texture}], `trust` {texture} or false/null/undefined)
 * @param {{mode: string, curvatureScale: number, lensMode?: string | null, quality?: string | null}} shading
 */
export function applyPartShading(m, face, shading) {
  const u = m.uniforms;
  const modes = boundModes(shading);
  u.uHasCurvature.value = false;
  u.uHasAccess.value = false;
  u.uHasQuality.value = false;
  const q = modes.has('quality') ? chooseQualityMap(face.quality, shading.quality) : null;
  if (q) {
    u.uQualityMap.value = q.texture;
    u.uHasQuality.value = true;
  }
  if (modes.has('curvature') && face.curvature?.length) {
    const layer = face.curvature[Math.min(shading.curvatureScale, face.curvature.length - 1)];
    u.uCurvatureMap.value = layer.texture;
    u.uCurvatureLod.value = layer.lod;
    u.uHasCurvature.value = true;
  }
  if (modes.has('accessibility') && face.accessibility) {
    u.uAccessMap.value = face.accessibility;
    u.uHasAccess.value = true;
  }
  // The trust map is bound whenever loaded (as the base material's): cheap, and the legend
  // of the lens and of the mode read the same map.
  u.uHasTrust.value = Boolean(face.trust);
  if (face.trust) u.uTrustMap.value = face.trust.texture;
}
