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
// An anisotropic phase's field adds to L_ms the sun's view terms: E sum_i c_i(x) B_i(d), with
// B_i the functions of direction of cloudgraph/phase.py (in uShapeFrame: z toward the light;
// per ray) and c_i the ms_shape array's 14 channels, then clamps L_ms at 0, as the server does.
// A v1.1 field's sky: its radiance array (in-scattered sky light, single scattering included)
// added to L_ms, and the sky seen behind the medium, L += Tr uSky at the ray's end.
// then display: clamp(L 2^exposure, 0, 1) through the sRGB transfer.

export const VERTEX = `#version 300 es
// One triangle that covers the viewport; no vertex buffer.
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
`;

export const MAX_STEPS = 4096;

/**
 * The fragment shader. packed = false: the exact march, sigma_t and tau_light in one RG texture
 * and radiance_ms in another, L_in formed per sample as the server forms it (two fetches a
 * step). packed = true: one RGBA texture of (sigma_t, L_in) made in the page, one fetch a step,
 * for frames while the camera moves (L_in interpolated instead of exp(-tau)).
 */
export function fragmentShader({ packed = false } = {}) {
  return `#version 300 es
#define PACKED ${packed ? 1 : 0}
precision highp float;
precision highp int;
precision highp sampler3D;

uniform sampler3D uDensTau;   // R: sigma_t / sigmaScale, G: tau_light (field grid, linear);
                              // PACKED: R as above, GBA: L_in
uniform sampler3D uRad;       // RGB: radiance after the first scattering / radScale (linear)
uniform sampler3D uMaj;       // R: majorant / uMajScale per block (nearest, texelFetch)
uniform sampler3D uRadSky;    // RGB: a v1.1 field's sky radiance / its scale (linear)
uniform bool uHasSky;         // whether uRadSky holds a sky beside a sun's radiance
uniform vec3 uSkyRadScale;    // the sky's radiance = texel * uSkyRadScale (its intensity in)
uniform vec3 uSky;            // the sky's radiance seen behind the medium (0 without a sky)

uniform vec3 uEye;            // camera, world units
uniform vec3 uForward;
uniform vec3 uRight;
uniform vec3 uUp;
uniform vec2 uTan;            // tan(fov/2), tan(fov/2) * height / width
uniform vec2 uSize;           // image size in pixels
uniform mat4 uWorldToUnit;    // world -> unit cube [0,1]^3 of the field
uniform float uStep;          // largest segment, world units
uniform float uSigmaScale;    // sigma_t per world unit = texel * uSigmaScale
uniform float uTauScale;      // tau_light = texel * uTauScale
uniform vec3 uRadScale;       // radiance_ms = texel * uRadScale
uniform vec3 uDirect;         // irradiance / 4pi (times phaseFactor per ray)
uniform bool uAnisotropic;    // whether the phase is Henyey-Greenstein, not isotropic
uniform vec3 uPhase;          // its lobes: g1, g2, the first's weight (g > 0 forward)
uniform vec3 uToLight;        // unit direction toward the light, world
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
uniform vec3 uLightUnit;      // the direction toward the light in the unit cube, per world unit
uniform float uEdge;          // where the light enters within this, tau_light is integrated
uniform bool uHasShape;       // whether the field holds the sun's view terms (ms_shape)
uniform sampler3D uShape0;    // ms_shape's channels 0-3 / their scales (linear)
uniform sampler3D uShape1;    // 4-7
uniform sampler3D uShape2;    // 8-11
uniform sampler3D uShape3;    // 12-13 (BA unused)
uniform vec4 uShapeScale[4];  // the channels' scales
uniform mat3 uShapeFrame;     // rows e_x, e_y, e_z of the view terms' frame (e_z toward the light)

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

// The phase factor of single scattering for a ray along d: 4pi p(to_light . d), as the server's
// field estimator takes it (1 for the isotropic phase).
float phaseFactor(vec3 d) {
  if (!uAnisotropic) return 1.0;
  float mu = dot(uToLight, d);
  return uPhase.z * hg4pi(uPhase.x, mu) + (1.0 - uPhase.z) * hg4pi(uPhase.y, mu);
}

// The view terms' functions of direction at the ray's direction d (constant along a ray):
// in the frame's coordinates (x, y, z), y, z, x, 6xy, 3yz, P2(z), 3xz, 3(x^2 - y^2), P3..P8(z).
vec4 gB[4];
void viewBasis(vec3 d) {
  vec3 v = uShapeFrame * d;  // (e_x . d, e_y . d, e_z . d): the frame's rows
  float x = v.x, y = v.y, z = v.z;
  float P[9];
  P[0] = 1.0;
  P[1] = z;
  for (int n = 1; n < 8; n++) P[n + 1] = (float(2 * n + 1) * z * P[n] - float(n) * P[n - 1]) / float(n + 1);
  gB[0] = vec4(y, z, x, 6.0 * x * y);
  gB[1] = vec4(3.0 * y * z, P[2], 3.0 * x * z, 3.0 * (x * x - y * y));
  gB[2] = vec4(P[3], P[4], P[5], P[6]);
  gB[3] = vec4(P[7], P[8], 0.0, 0.0);
}

float srgb(float x) {
  return x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}

// What a segment's end holds: sigma_t per world unit, tau_light and L_ms (PACKED: L_in in ms,
// tau unused).
struct Sample {
  float sigma;
  float tau;
  vec3 ms;
};

Sample sampleAt(vec3 p) {
  Sample s;
#if PACKED
  vec4 v = textureLod(uDensTau, p, uLod);
  s.sigma = v.r * uSigmaScale;
  s.tau = 0.0;
  s.ms = v.gba;
#else
  vec2 st = texture(uDensTau, p).rg;
  s.sigma = st.r * uSigmaScale;
  s.ms = texture(uRad, p).rgb * uRadScale;
  if (uHasSky) s.ms += texture(uRadSky, p).rgb * uSkyRadScale;
  if (uHasShape) {
    float view = dot(texture(uShape0, p) * uShapeScale[0], gB[0]) + dot(texture(uShape1, p) * uShapeScale[1], gB[1])
               + dot(texture(uShape2, p) * uShapeScale[2], gB[2]) + dot(texture(uShape3, p) * uShapeScale[3], gB[3]);
    s.ms = max(s.ms + uDirect * (4.0 * 3.14159265358979) * view, 0.0);
  }
  // Where the light enters the box the grid's texture clamps: integrate sigma_t there instead
  // (a point on the box's surface, where a ray enters it, counts as inside; the light never
  // leaves through the faces it runs parallel to)
  vec3 pc = clamp(p, 0.0, 1.0);
  vec3 te = mix(max(-pc / uLightUnit, (1.0 - pc) / uLightUnit), vec3(1e30), lessThan(abs(uLightUnit), vec3(1e-9)));
  float tExit = max(min(min(te.x, te.y), te.z), 0.0);
  if (tExit <= uEdge) {
    float sum = 0.0;
    for (int k = 0; k < 3; k++) {
      sum += texture(uDensTau, pc + ((float(k) + 0.5) / 3.0) * tExit * uLightUnit).r;
    }
    s.tau = sum * uSigmaScale * tExit / 3.0;
  } else {
    s.tau = st.g * uTauScale;
  }
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
  vec3 direct = uDirect * phaseFactor(d);  // E p: single scattering's, constant along the ray
  if (uHasShape) viewBasis(d);
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
      float a = dtau + f1.tau - f0.tau;
      float single = abs(a) < 1e-4 ? exp(-f0.tau) * (1.0 - 0.5 * a) : (exp(-f0.tau) - exp(-f1.tau - dtau)) / a;
      seg_L += direct * dtau * single;
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
  L += Tr * uSky;               // the sky behind the medium
  if (uLinearOut) {
    outColor = vec4(L * uGain, 1.0);
    return;
  }
  vec3 x = clamp(L * uGain, 0.0, 1.0);
  outColor = vec4(srgb(x.r), srgb(x.g), srgb(x.b), 1.0);
}
`;
}
