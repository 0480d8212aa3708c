// GLSL ES 3.00 sources of the real-time view: a full-screen triangle and the ray march of the
// radiance field, the same march as the server's `field` estimator (DESIGN.md, "The radiance
// field"; thesis Eq. 4.24 integrated segment by segment in closed form):
//   L_in(x) = E exp(-tau_light(x)) / 4pi + L_ms(x)
//   per segment of length dt at p = o + (t + u dt) d:  a = exp(-sigma_t(p) dt)
//   L += Tr (1 - a) albedo L_in(p);  Tr *= a;  stop when Tr < 1e-3
// then display: clamp(L 2^exposure, 0, 1) through the sRGB transfer.

export const VERTEX = `#version 300 es
// One triangle that covers the viewport; no vertex buffer.
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}
`;

export const MAX_STEPS = 4096;

export const FRAGMENT = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler3D;

uniform sampler3D uDensTau;   // R: sigma_t / sigmaScale, G: tau_light (field grid, linear)
uniform sampler3D uRad;       // RGB: radiance after the first scattering / radScale (linear)
uniform sampler3D uMaj;       // R: majorant / sigmaScale per block (nearest, texelFetch)

uniform vec3 uEye;            // camera, world units
uniform vec3 uForward;
uniform vec3 uRight;
uniform vec3 uUp;
uniform vec2 uTan;            // tan(fov/2), tan(fov/2) * height / width
uniform vec2 uSize;           // image size in pixels
uniform mat4 uWorldToUnit;    // world -> unit cube [0,1]^3 of the field
uniform float uStep;          // largest segment, world units
uniform float uSigmaScale;    // sigma_t per world unit = texel * uSigmaScale
uniform vec3 uRadScale;       // radiance_ms = texel * uRadScale
uniform vec3 uDirect;         // irradiance / 4pi (isotropic phase)
uniform vec3 uAlbedo;
uniform float uGain;          // 2^exposure
uniform vec3 uBlockCells;     // majorant blocks per unit length on each axis (n / B)
uniform ivec3 uBlocks;        // majorant grid size

out vec4 outColor;

const int MAX_STEPS = ${MAX_STEPS};
const float TR_MIN = 1e-3;

// A fixed per-pixel jitter in [0, 1) (a hash of the pixel's column and row).
float jitter(uvec2 px) {
  uint h = px.x * 0x8da6b343u ^ px.y * 0xd8163841u;
  h ^= h >> 16; h *= 0x7feb352du; h ^= h >> 15; h *= 0x846ca68bu; h ^= h >> 16;
  return float(h >> 8) * (1.0 / 16777216.0);
}

float srgb(float x) {
  return x <= 0.0031308 ? 12.92 * x : 1.055 * pow(x, 1.0 / 2.4) - 0.055;
}

void main() {
  // Pinhole ray through the pixel centre; fov along the width, row 0 at the top.
  vec2 ndc = 2.0 * gl_FragCoord.xy / uSize - 1.0;
  vec3 d = normalize(uForward + ndc.x * uTan.x * uRight + ndc.y * uTan.y * uUp);

  // The ray in the field's unit cube; t stays a world distance.
  vec3 ou = (uWorldToUnit * vec4(uEye, 1.0)).xyz;
  vec3 du = mat3(uWorldToUnit) * d;
  vec3 inv = 1.0 / du;
  vec3 ta = -ou * inv;
  vec3 tb = (1.0 - ou) * inv;
  vec3 tlo = min(ta, tb);
  vec3 thi = max(ta, tb);
  float t0 = max(max(max(tlo.x, tlo.y), tlo.z), 0.0);
  float t1 = min(min(thi.x, thi.y), thi.z);
  vec3 L = vec3(0.0);         // radiance accumulator
  if (t1 > t0) {
    float n = ceil((t1 - t0) / uStep);
    float dt = (t1 - t0) / n;  // segments of equal length <= uStep
    float u = jitter(uvec2(gl_FragCoord.xy));
    float Tr = 1.0;            // transmittance from the eye
    float k = 0.0;             // segment index
    float tBlockEnd = -1.0;    // where the ray leaves the current majorant block
    for (int i = 0; i < MAX_STEPS; i++) {
      if (k >= n) break;
      float t = t0 + (k + u) * dt;
      vec3 p = ou + t * du;
      if (t >= tBlockEnd) {
        // Empty-space skipping: a block whose majorant is 0 holds no medium at all.
        vec3 cell = clamp(floor(p * uBlockCells), vec3(0.0), vec3(uBlocks - 1));
        vec3 lo = cell / uBlockCells;
        vec3 hi = (cell + 1.0) / uBlockCells;
        vec3 te = max((lo - ou) * inv, (hi - ou) * inv);
        tBlockEnd = max(min(min(te.x, te.y), te.z), t);
        if (texelFetch(uMaj, ivec3(cell), 0).r <= 0.0) {
          k = max(k + 1.0, ceil((tBlockEnd - t0) / dt - u));
          tBlockEnd = -1.0;
          continue;
        }
      }
      vec2 st = texture(uDensTau, p).rg;
      if (st.r > 0.0) {
        float a = exp(-st.r * uSigmaScale * dt);
        vec3 Lin = uDirect * exp(-st.g) + texture(uRad, p).rgb * uRadScale;
        L += Tr * (1.0 - a) * uAlbedo * Lin;
        Tr *= a;
        if (Tr < TR_MIN) break;
      }
      k += 1.0;
    }
  }
  vec3 x = clamp(L * uGain, 0.0, 1.0);
  outColor = vec4(srgb(x.r), srgb(x.g), srgb(x.b), 1.0);
}
`;
