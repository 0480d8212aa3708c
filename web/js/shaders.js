// GLSL ES 3.00 sources of the real-time view: a full-screen triangle and the ray march of the
// radiance field, the march of the server's `field` estimator (cloudgraph/integrators/graph.py;
// thesis Eq. 4.24 integrated segment by segment in closed form,
// docs/method.md, "The radiance field"):
//   L_in(x) = E p(mu) exp(-tau_light(x)) + L_ms(x),  p = 1/4pi isotropic, else the header's
//   Henyey-Greenstein phase at mu = to_light . d: constant along a ray, so per pixel
//   tau_light: the grid's, or within uEdge of where the light enters the box the integral of
//   sigma_t to the box (3 midpoints)
//   per segment [t, t + dt]: sigma_t the mean of its end values, dtau = sigma_t dt; L_ms linear
//   in optical depth between its end values M0, M1, tau_light too (a = dtau + tau1 - tau0):
//     L += Tr albedo [E p dtau (e^-tau0 - e^-(tau1 + dtau)) / a
//                     + M0 (1 - e^-dtau) + (M1 - M0) (1 - e^-dtau (1 + dtau)) / dtau];  Tr *= e^-dtau
//   segments of at most uMaxDtau at the block's majorant, and uStep; the first (1 - u) of one
//   long, with one jitter u per pixel; stop when Tr < 1e-3
// Several directional lights (a v1.1 field): single scattering summed over them, each with its
// own tau_light (a channel of uTauA, suns 1-4, or uTauB, 5-8), its E p
// per ray and its edge integral. L_ms is every component's radiance array mixed in the page by
// the lights' intensities (one texture, glview.js), a sky's included.
// An anisotropic phase's field adds to L_ms each sun's view terms: E sum_i c_i(x) B_i(d), with
// B_i the functions of direction of cloudgraph/phase.py (in the sun's frame: z toward it; per
// ray) and c_i its ms_shape array's 20 channels, then clamps L_ms at 0, as the server does.
// The sky and environment maps seen behind the medium: L += Tr (uSky + the maps' lat-long
// background along d) at the ray's end.
// then display: clamp(L 2^exposure, 0, 1) through the sRGB transfer.

import { MAX_FORWARD } from "./field.js";

export const VERTEX = `#version 300 es
// One triangle that covers the viewport; no vertex buffer.
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
`;

export const MAX_STEPS = 4096;

/** Texture units a program of ``suns`` directional lights, ``shaped`` of them with view terms,
 * binds: uDens, uRad, uMaj, the tau textures, one of view sums for each shaped sun, and with
 * ``sunMs`` (a field whose header has ms_light) one of L_ms for each sun. */
export function textureUnits(suns, shaped, sunMs = false) {
  return 3 + tauTextures(suns) + shaped + (sunMs ? suns : 0);
}

/** Textures of the suns' tau_light texels, a channel each: suns 1-4 (uTauA), 5-8 (uTauB). */
function tauTextures(suns) {
  return Math.ceil(suns / 4);
}

/** The GLSL of sun k's tau_light texel at p (the exact march's). */
function tauTexel(k) {
  return `texture(uTau${k < 4 ? "A" : "B"}, p).${"rgba"[k % 4]}`;
}

/**
 * The fragment shader. packed = false: the exact march, sigma_t, tau_light and L_ms in a
 * texture each, L_in formed per sample as the server forms it (three fetches a step, one more
 * for each four suns past the first four). packed = true: one RGBA texture of (sigma_t, L_in) made in the page, one
 * fetch a step, for frames while the camera moves (L_in interpolated instead of exp(-tau)).
 * suns: the field's directional lights (0 .. MAX_SUNS of field.js); shaped: the indices of
 * those whose view terms the field holds (an anisotropic phase; the exact march only).
 */
export function fragmentShader({ packed = false, suns = 1, shaped = [], env = false, phase = false, sunMs = false } = {}) {
  const ns = Math.max(1, suns); // GLSL arrays are never empty
  const range = (n) => Array.from({ length: n }, (_, k) => k);
  const shapedSuns = packed ? [] : shaped;
  const shapeDecls = shapedSuns
    .map(
      (k) => `uniform sampler3D uView${k};      // R: sun ${k}'s view terms summed toward the camera (glview.js; linear)
uniform float uShapePower${k};   // its terms are over exp(-min(P tau_light, uMsRange)), P this`,
    )
    .join("\n");
  const tauLines = range(suns)
    .map((k) => `  s.tau[${k}] = tauAt(pc, uLightUnit[${k}], depthOf(${tauTexel(k)}));`)
    .join("\n");
  const viewLines = shapedSuns
    .map(
      (k) => `  view += uDirect[${k}] * exp(-min(uShapePower${k} * s.tau[${k}], uMsRange)) * texture(uView${k}, p).r;
  beam += beamLight(${k}, s.tau[${k}], exp(-s.tau[${k}]));`,
    )
    .join("\n");
  // with ms_light each sun's L_ms is a texture of its own, over its light factor
  const apart = sunMs && !packed;
  const sunMsDecls = apart ? range(suns).map((k) => `uniform sampler3D uSunRad${k}; // RGB: sun ${k}'s L_ms over its light factor / uSunRadScale (linear)`).join("\n") : "";
  const sunMsLines = apart
    ? range(suns)
        .map((k) => `  s.ms += texture(uSunRad${k}, p).rgb * uSunRadScale[${k}] * exp(-min(uMsPower * s.tau[${k}], vec3(uMsRange)));`)
        .join("\n")
    : "";
  return `#version 300 es
#define PACKED ${packed ? 1 : 0}
#define SUNS ${suns}
#define NS ${ns}
#define ENV ${env ? 1 : 0}
#define SUN_T ${packed && phase ? 1 : 0}
precision highp float;
precision highp int;
precision highp sampler3D;

uniform sampler3D uDens;      // R: sigma_t / sigmaScale (field grid, linear); PACKED: R as above,
                              // GBA: L_in
uniform sampler3D uTauA;      // R..RGBA: suns 1-4's tau_light texels (their grid: the field's or
                              // twice as fine; linear; depthOf)
uniform sampler3D uTauB;      // suns 5-8's
uniform sampler3D uSunT;      // SUN_T: RGBA, suns 1-4's exp(-tau_light) (linear, mipmapped)
uniform sampler3D uRad;       // RGB: L_ms, the lights' components mixed / uRadScale (linear)
uniform sampler3D uMaj;       // R: majorant / uMajScale per block (nearest, texelFetch)
uniform vec3 uSky;            // the sky's radiance seen behind the medium (0 without a sky)
uniform sampler2D uEnv;       // ENV: the environment maps' radiance seen behind it / uEnvScale,
                              // lat-long: u = atan2(x, -z) / 2pi, v = acos(y) / pi (api.md)
uniform vec3 uEnvScale;

uniform vec3 uEye;            // camera, world units
uniform vec3 uForward;
uniform vec3 uRight;
uniform vec3 uUp;
uniform vec2 uTan;            // tan(fov/2), tan(fov/2) * height / width
uniform vec2 uSize;           // image size in pixels
uniform mat4 uWorldToUnit;    // world -> unit cube [0,1]^3 of the field
uniform float uStep;          // largest segment, world units
uniform float uSigmaScale;    // sigma_t per world unit = texel * uSigmaScale
uniform float uTauPower;      // the tau texels hold q = exp(-uTauPower tau_light) (0: tau_light)
uniform vec3 uRadScale;       // L_ms = texel * uRadScale (with ms_light: the sky's and maps' only)
uniform vec3 uSunRadScale[NS]; // with ms_light: each sun's L_ms = texel * scale *
uniform vec3 uMsPower;        // exp(-min(uMsPower tau_light, uMsRange)) (the header's ms_light)
uniform float uMsRange;
${sunMsDecls}
uniform vec3 uDirect[NS];     // each sun's irradiance / 4pi (times phaseFactor per ray)
uniform bool uAnisotropic;    // whether the phase is Henyey-Greenstein, not isotropic
uniform vec3 uPhase;          // its lobes: g1, g2, the first's weight (g > 0 forward)
uniform int uBeamOrders;      // the header's ms_forward: orders of the suns' light in their beam
                              // in closed form (0: none; at most MAX_FORWARD)
uniform vec3 uToLight[NS];    // unit direction toward each sun, world
uniform vec3 uAlbedo;
uniform float uGain;          // 2^exposure
uniform vec3 uBlockCells;     // majorant blocks per unit length on each axis (n / B)
uniform ivec3 uBlocks;        // majorant grid size
uniform uint uSeed;           // jitter set (0 for the view; others to average several)
uniform vec2 uPixelOffset;    // where in its pixel a ray starts (0.5, 0.5: the centre)
uniform bool uLinearOut;      // write linear radiance x 2^exposure (to average), not sRGB
uniform float uLod;           // PACKED: mip level of the field for long steps
uniform float uMajScale;      // majorant per world unit = texel * uMajScale
uniform float uMaxDtau;       // optical depth of a segment at most, at the block's majorant
uniform vec3 uLightUnit[NS];  // the direction toward each sun in the unit cube, per world unit
uniform float uEdge;          // where the light enters within this, tau_light is integrated
${shapeDecls}

out vec4 outColor;

const int MAX_STEPS = ${MAX_STEPS};
const float TR_MIN = 1e-3;

// A fixed per-pixel jitter in [0, 1) (a hash of the pixel's column and row).
float jitter(uvec2 px) {
  uint h = px.x * 0x8da6b343u ^ px.y * 0xd8163841u ^ uSeed * 0xcb1ab31fu;
  h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
  return float(h >> 8) * (1.0 / 16777216.0);
}

// 4pi times the Henyey-Greenstein phase at cosine mu (1 at g = 0).
float hg4pi(float g, float mu) {
  float denom = 1.0 + g * g - 2.0 * g * mu;
  return (1.0 - g * g) / (denom * sqrt(denom));
}

// The phase factor of single scattering for a ray along d from a light toward toLight:
// 4pi p(toLight . d), as the server's field estimator takes it (1 for the isotropic phase).
float phaseFactor(vec3 toLight, vec3 d) {
  if (!uAnisotropic) return 1.0;
  float mu = dot(toLight, d);
  return uPhase.z * hg4pi(uPhase.x, mu) + (1.0 - uPhase.z) * hg4pi(uPhase.y, mu);
}

// The phase convolved with itself n times at cosine mu, per steradian: its lobes' products,
// sum_k C(n, k) w^k (1 - w)^(n - k) HG(g1^k g2^(n - k)) (HG lobes convolve into HG lobes).
float phasePower(int n, float mu) {
  float p = 0.0;
  for (int k = 0; k <= n; k++) {
    float c = 1.0, g = 1.0;
    for (int j = 0; j < n; j++) {  // C(n, k) w^k (1 - w)^(n - k), g1^k g2^(n - k), no pow(0, 0)
      bool first = j < k;
      c *= first ? uPhase.z * float(n - j) / float(k - j) : 1.0 - uPhase.z;
      g *= first ? uPhase.x : uPhase.y;
    }
    p += c * hg4pi(g, mu);
  }
  return p / (4.0 * 3.14159265358979);
}

const int MAX_FORWARD = ${MAX_FORWARD};
// per sun, the coefficients of tau^n in its beam's light, n = 1 .. MAX_FORWARD, at the ray's mu:
// 4pi E albedo^n / n! p^(n+1) (p^m the phase convolved m times; 0 past uBeamOrders)
vec3 gBeam[NS * MAX_FORWARD];

// The sun's light of the first uBeamOrders orders still in its beam, scattered into the ray
// (cloudgraph/phase.py forward_light times 4pi E): sum_n T (albedo tau)^n / n! p^(n+1), T =
// e^-tau, in Horner's form: no exp and no branch a step (the moving march's step pays one log
// for it).
vec3 beamLight(int k, float tau, float T) {
  vec3 sum = vec3(0.0);
  for (int n = MAX_FORWARD; n >= 1; n--) sum = tau * (sum + gBeam[k * MAX_FORWARD + n - 1]);
  return T * sum;
}

// Optical depth to a sun at the unit point pc (clamped to the box): the grid's ("grid"), or
// where the light enters the box, within uEdge, the integral of sigma_t to it (3 midpoints; the
// grid's texture clamps there). A point on the box's surface, where a ray enters it, counts as
// inside; the light never leaves through the faces it runs parallel to.
// A sun's tau_light from its texel, interpolated as q = exp(-uTauPower tau) (the server's field;
// q >= exp(-16 uTauPower): the light march stops at optical depth 16).
float depthOf(float q) {
  return uTauPower > 0.0 ? -log(max(q, exp(-16.0 * uTauPower))) / uTauPower : q;
}

float tauAt(vec3 pc, vec3 lu, float grid) {
  vec3 te = mix(max(-pc / lu, (1.0 - pc) / lu), vec3(1e30), lessThan(abs(lu), vec3(1e-9)));
  float tExit = max(min(min(te.x, te.y), te.z), 0.0);
  if (tExit > uEdge) return grid;
  float sum = 0.0;
  for (int k = 0; k < 3; k++) {
    sum += texture(uDens, pc + ((float(k) + 0.5) / 3.0) * tExit * lu).r;
  }
  return sum * uSigmaScale * tExit / 3.0;
}

float srgb(float x) {
  return x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}

vec3 gDirect[NS];             // main's E p per sun, for sampleAt (SUN_T)

// What a segment's end holds: sigma_t per world unit, tau_light per sun and L_ms (PACKED:
// L_in in ms, tau unused).
struct Sample {
  float sigma;
  float tau[NS];
  vec3 ms;
};

Sample sampleAt(vec3 p) {
  Sample s;
#if PACKED
  vec4 v = textureLod(uDens, p, uLod);
  s.sigma = v.r * uSigmaScale;
  s.ms = v.gba;
#if SUN_T
  vec4 sunT = textureLod(uSunT, p, uLod);
  for (int k = 0; k < SUNS; k++) {
    s.ms += gDirect[k] * sunT[k];
    if (uBeamOrders > 0) s.ms += beamLight(k, -log(max(sunT[k], 1e-7)), sunT[k]);
  }
#endif
#else
  s.sigma = texture(uDens, p).r * uSigmaScale;
  vec3 pc = clamp(p, 0.0, 1.0);
${tauLines}
  s.ms = texture(uRad, p).rgb * uRadScale;
${sunMsLines}
  vec3 view = vec3(0.0), beam = vec3(0.0);
${viewLines}
  s.ms = ${shapedSuns.length ? "max(s.ms + (4.0 * 3.14159265358979) * view + beam, 0.0)" : "s.ms"};
#endif
  return s;
}

void main() {
  // Pinhole ray through the pixel centre; fov along the width, row 0 at the top.
  vec2 ndc = 2.0 * (floor(gl_FragCoord.xy) + uPixelOffset) / uSize - 1.0;
  vec3 d = normalize(uForward + ndc.x * uTan.x * uRight + ndc.y * uTan.y * uUp);

  // The ray in the field's unit cube; t stays a world distance.
  vec3 ou = (uWorldToUnit * vec4(uEye, 1.0)).xyz;
  vec3 du = mat3(uWorldToUnit) * d;
  vec3 inv = 1.0 / du;
  vec3 ta = -ou * inv;
  vec3 tb = (1.0 - ou) * inv;
  vec3 tlo = min(ta, tb);
  vec3 thi = max(ta, tb);
  float t = max(max(max(tlo.x, tlo.y), tlo.z), 0.0);
  float tEnd = min(min(thi.x, thi.y), thi.z);
  vec3 L = vec3(0.0);           // radiance accumulator
  vec3 direct[NS];              // E p per sun: single scattering's, constant along the ray
  for (int k = 0; k < SUNS; k++) direct[k] = uDirect[k] * phaseFactor(uToLight[k], d);
  gDirect = direct;
  for (int k = 0; k < SUNS; k++) {
    vec3 c = (4.0 * 3.14159265358979) * uDirect[k];
    for (int n = 1; n <= MAX_FORWARD; n++) {
      c *= uAlbedo / float(n);
      gBeam[k * MAX_FORWARD + n - 1] = vec3(0.0);
      if (n <= uBeamOrders) gBeam[k * MAX_FORWARD + n - 1] = c * phasePower(n + 1, dot(uToLight[k], d));
    }
  }
  float Tr = 1.0;               // transmittance from the eye
  if (tEnd > t) {
    float frac = 1.0 - jitter(uvec2(gl_FragCoord.xy));  // the first segment's share of a step
    Sample f0;                  // values at the segment's start
    bool fresh = false;         // whether f0 holds the values at t
    float tBlockEnd = -1.0;     // where the ray leaves the current majorant block
    bool empty = false;         // whether that block holds no medium
    float step = uStep;         // segment length in this block
    for (int i = 0; i < MAX_STEPS; i++) {
      if (t >= tBlockEnd) {
        // Empty-space skipping: a block whose majorant is 0 holds no medium at all.
        vec3 cell = clamp(floor((ou + t * du) * uBlockCells), vec3(0.0), vec3(uBlocks - 1));
        vec3 te = max((cell / uBlockCells - ou) * inv, ((cell + 1.0) / uBlockCells - ou) * inv);
        tBlockEnd = min(min(te.x, te.y), te.z);
        float maj = texelFetch(uMaj, ivec3(cell), 0).r * uMajScale;
        empty = maj <= 0.0;
#if PACKED
        step = uStep;
#else
        step = min(uStep, uMaxDtau / max(maj, 1e-12));
#endif
      }
      if (empty) {
        // nothing to add across an empty block; the field is read again where medium starts
        t = min(max(tBlockEnd, t) + 1e-3 * uStep, tEnd);
        fresh = false;
        if (t >= tEnd) break;
        continue;
      }
      if (!fresh) f0 = sampleAt(ou + t * du);
      float seg = min(frac * step, tEnd - t);
      Sample f1 = sampleAt(ou + (t + seg) * du);
      // One segment in closed form (exponential integrator)
      float dtau = 0.5 * (f0.sigma + f1.sigma) * seg;
      float segTr = exp(-dtau);
      float w1 = dtau > 1e-3 ? (1.0 - segTr * (1.0 + dtau)) / dtau : 0.5 * dtau;
      vec3 seg_L = f0.ms * (1.0 - segTr) + (f1.ms - f0.ms) * w1;
#if !PACKED
      for (int k = 0; k < SUNS; k++) {
        float a = dtau + f1.tau[k] - f0.tau[k];
        float single = abs(a) < 1e-4 ? exp(-f0.tau[k]) * (1.0 - 0.5 * a) : (exp(-f0.tau[k]) - exp(-f1.tau[k] - dtau)) / a;
        seg_L += direct[k] * dtau * single;
      }
#endif
      L += Tr * uAlbedo * seg_L;
      Tr *= segTr;
      t += seg;
      f0 = f1;
      fresh = true;
      frac = 1.0;
      if (t >= tEnd || Tr < TR_MIN) break;
    }
  }
  vec3 behind = uSky;           // the sky behind the medium, and the environment maps
#if ENV
  behind += texture(uEnv, vec2(atan(d.x, -d.z) * (0.5 / 3.14159265358979), acos(clamp(d.y, -1.0, 1.0)) * (1.0 / 3.14159265358979))).rgb * uEnvScale;
#endif
  L += Tr * behind;
  if (uLinearOut) {
    outColor = vec4(L * uGain, 1.0);
    return;
  }
  vec3 x = clamp(L * uGain, 0.0, 1.0);
  outColor = vec4(srgb(x.r), srgb(x.g), srgb(x.b), 1.0);
}
`;
}
