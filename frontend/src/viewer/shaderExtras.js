/**
 * GLSL and uniforms of the scholar's shading tools, spliced into material.js' shader:
 *
 * - the "trust" mode (trust.png: R = source class, G = |fringe − final|, B = σ_h; trust.js);
 * - unsharp masking (RTIViewer's "normal unsharp masking" and "luminance unsharp masking",
 *   Palma et al. 2010, "Dynamic shading enhancement for reflectance transformation imaging",
 *   ACM JOCCH 3(2)): n' = normalize(n + k(n − blur_r(n))) for the normals; L' = L + k(L − blur_r(L))
 *   on the diffuse luminance, the colour scaled by L'/L. blur_r: 12 taps on a circle of r
 *   texels, read at mip level log2(r) − 1 (each tap already averages its neighbourhood);
 * - the lens (OpenLIME's lens, Ponchio et al. 2022): inside a circle of the canvas
 *   (gl_FragCoord, device pixels) another shading mode is drawn.
 */
import * as THREE from 'three';

/** Uniforms of the extras, with their defaults (enhancements off, no lens); `blank`: a 1×1 texture. */
export function extraUniforms(blank) {
  return {
    uTrustMap: { value: blank },
    uHasTrust: { value: false },
    uTrustLayer: { value: 0 },
    uTrustColours: { value: TRUST_COLOURS_LINEAR.map((c) => c.clone()) },
    uNormalUnsharp: { value: 0 },
    uLumaUnsharp: { value: 0 },
    uUnsharpRadius: { value: 8 },
    uLensMode: { value: -1 },
    uLensCentre: { value: new THREE.Vector2(0, 0) },
    uLensRadius: { value: 0 },
  };
}

/** sRGB class colours of trust.js (kept here in linear RGB for the shader), classes 1–5. */
const TRUST_COLOURS_SRGB = [
  [0.33, 0.63, 0.42],
  [0.89, 0.47, 0.13],
  [0.36, 0.55, 0.86],
  [0.84, 0.19, 0.56],
  [0.95, 0.84, 0.25],
];
const TRUST_COLOURS_LINEAR = TRUST_COLOURS_SRGB.map((c) => {
  const col = new THREE.Color().setRGB(c[0], c[1], c[2], THREE.SRGBColorSpace);
  return new THREE.Vector3(col.r, col.g, col.b);
});

/** Declarations and functions (after material.js' own helpers, before main). */
export const EXTRAS_GLSL = /* glsl */ `
  uniform sampler2D uTrustMap;
  uniform bool uHasTrust;
  uniform int uTrustLayer;        // 0 sources, 1 uncertainty, 2 disagreement (trust.js)
  uniform vec3 uTrustColours[5];
  uniform float uNormalUnsharp;   // k of the normals' unsharp mask (0: off)
  uniform float uLumaUnsharp;     // k of the luminance's unsharp mask (0: off)
  uniform float uUnsharpRadius;   // r in texels of the normal map
  uniform int uLensMode;          // < 0: no lens
  uniform vec2 uLensCentre;       // device pixels, origin bottom-left (gl_FragCoord)
  uniform float uLensRadius;      // device pixels

  // Mean of 12 taps on a circle of radius r texels (mip level log2(r) − 1).
  vec3 blurNormal(vec2 uv, float r) {
    vec3 s = vec3(0.0);
    float lod = max(log2(r) - 1.0, 0.0);
    for (int i = 0; i < 12; i++) {
      float a = float(i) * 0.52359878;
      s += objectNormal(uv + vec2(cos(a), sin(a)) * r * uTexelSize, lod);
    }
    return normalize(s);
  }

  vec3 unsharpNormal(vec3 n, vec2 uv) {
    return normalize(n + uNormalUnsharp * (n - blurNormal(uv, uUnsharpRadius)));
  }

  float luma(vec3 c) { return dot(c, vec3(0.2126, 0.7152, 0.0722)); }

  // Diffuse luminance at uv (albedo luminance × (ambient + I·max(0, n·l))), on mip level lod.
  float diffuseLuma(vec2 uv, float lod, bool albedo) {
    vec3 n = normalize(uObjectToWorld * objectNormal(uv, lod));
    float a = albedo && uHasAlbedo ? luma(textureLod(uAlbedoMap, uv, lod).rgb) : luma(uClay);
    return a * (uAmbient + uIntensity * max(dot(n, normalize(uLightDir)), 0.0));
  }

  // The colour scaled by L'/L, L' = L + k(L − blur(L)) (natural colour and clay only: the
  // modes whose brightness is the light's).
  vec3 unsharpLuma(vec3 colour, vec2 uv, bool albedo) {
    float r = uUnsharpRadius;
    float lod = max(log2(r) - 1.0, 0.0);
    float centre = diffuseLuma(uv, 0.0, albedo);
    float blur = 0.0;
    for (int i = 0; i < 12; i++) {
      float a = float(i) * 0.52359878;
      blur += diffuseLuma(uv + vec2(cos(a), sin(a)) * r * uTexelSize, lod, albedo);
    }
    blur /= 12.0;
    float sharp = max(centre + uLumaUnsharp * (centre - blur), 0.0);
    return colour * (sharp / max(centre, 1e-4));
  }

  // trust.png: sources as class colours lit by the normals (the wedges stay readable), or
  // σ_h / |fringe − final| on the sequential ramp (grey: no fringe height).
  vec3 trustColour(vec3 n) {
    vec4 t = texture(uTrustMap, faceUv()); // the face's grid (material.js uFaceUv)
    float shade = 0.45 + 0.55 * max(dot(n, normalize(uLightDir)), 0.0);
    if (t.a < 0.5) return vec3(0.05);
    if (uTrustLayer == 0) {
      int code = int(t.r * 255.0 + 0.5);
      vec3 c = code >= 1 && code <= 5 ? uTrustColours[code - 1] : vec3(0.2);
      return c * shade;
    }
    if (uTrustLayer == 2) {
      int code = int(t.r * 255.0 + 0.5);
      if (code == 3) return vec3(0.18) * shade; // normals only: no fringe height to compare
      return sequential(t.g) * shade;
    }
    return sequential(t.b) * shade;
  }

  bool inLens() {
    return uLensMode >= 0 && uLensRadius > 0.0 && distance(gl_FragCoord.xy, uLensCentre) < uLensRadius;
  }
`;
