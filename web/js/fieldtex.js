// Texture data made in the page from a decoded field (field.js), for glview.js: sigma_t and
// tau_light interleaved into one RG texture, the lights' radiance arrays mixed into one, and
// the moving camera's (sigma_t, L_in) texture.

import { halfToFloat } from "./field.js";

/** Arrays of one grid (float16 bits or float32, all of one type) as one array of ``channels``
 * per texel (the arrays in turn, zero past the last). */
export function interleaved(arrays, channels = arrays.length) {
  const n = arrays[0].length;
  const out = new arrays[0].constructor(channels * n);
  arrays.forEach((a, c) => {
    for (let i = 0; i < n; i++) out[channels * i + c] = a[i];
  });
  return out;
}

const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) HALF[h] = halfToFloat(h);

/** Float16 bits as float32. */
export function halfFloats(data) {
  return Float32Array.from(data, (h) => HALF[h]);
}

/** A sun's optical-depth array as the texels the shader reads (shaders.js depthOf): q =
 * exp(-power tau), interpolated between grid points as the server's field is (power 0, a
 * field of before the header's tau_power: tau itself). */
export function depthTexels(array, power) {
  const scale = Number(array.scale);
  const out = new Float32Array(array.data.length);
  for (let i = 0; i < out.length; i++) {
    const tau = scale * HALF[array.data[i]];
    out[i] = power > 0 ? Math.exp(-power * tau) : tau;
  }
  return out;
}

/** exp(-tau_light) of a sun's optical-depth array at the centres of the density grid's
 * ``shape`` (nz, ny, nx) voxels, as the exact march reads it there: the texel's own value, or
 * from a grid twice as fine (field.js) the mean of the eight texels around the centre in q =
 * exp(-power tau), raised to 1 / power. Kept per array: a re-mix reads it again. */
export function voxelTransmittance(array, power, shape) {
  if (!TRANSMITTANCE.has(array)) TRANSMITTANCE.set(array, transmittanceOf(array, power, shape));
  return TRANSMITTANCE.get(array);
}

const TRANSMITTANCE = new WeakMap();

function transmittanceOf(array, power, shape) {
  const [nz, ny, nx] = shape;
  const scale = Number(array.scale);
  const out = new Float32Array(nx * ny * nz);
  if (array.shape[0] === nz) {
    for (let v = 0; v < out.length; v++) out[v] = Math.exp(-scale * HALF[array.data[v]]);
    return out;
  }
  const q = depthTexels(array, power);
  const [fy, fx] = [2 * ny, 2 * nx];
  let v = 0;
  for (let k = 0; k < nz; k++) {
    for (let j = 0; j < ny; j++) {
      for (let i = 0; i < nx; i++, v++) {
        let sum = 0;
        for (let c = 0; c < 8; c++) sum += q[((2 * k + (c >> 2)) * fy + 2 * j + ((c >> 1) & 1)) * fx + 2 * i + (c & 1)];
        out[v] = Math.pow(sum / 8, 1 / power);
      }
    }
  }
  return out;
}

/** Trilinear weights that resample an axis of m texel centres at n texel centres. */
function axisWeights(n, m) {
  const i0 = new Int32Array(n);
  const i1 = new Int32Array(n);
  const w = new Float32Array(n);
  for (let i = 0; i < n; i++) {
    const x = Math.min(m - 1, Math.max(0, ((i + 0.5) * m) / n - 0.5));
    i0[i] = Math.floor(x);
    i1[i] = Math.min(m - 1, i0[i] + 1);
    w[i] = x - i0[i];
  }
  return { i0, i1, w };
}

/**
 * A sum of float16 RGB arrays of one grid, each times an RGB weight: ``terms`` [{ a: a decoded
 * array ({ data, scale }), e: [3] }]. Returns { data: Float32Array RGB divided by scale, scale:
 * [3] the peak per channel (float16 holds the data whatever the weights) }.
 */
function weightedSum(terms) {
  const n = terms[0].a.data.length;
  const sum = new Float32Array(n);
  for (const { a, e } of terms) {
    const w = a.scale.map((s, ch) => s * e[ch]);
    if (w.every((v) => v === 0)) continue;
    const d = a.data;
    for (let i = 0; i < n; i += 3) {
      sum[i] += w[0] * HALF[d[i]];
      sum[i + 1] += w[1] * HALF[d[i + 1]];
      sum[i + 2] += w[2] * HALF[d[i + 2]];
    }
  }
  const scale = [0, 1, 2].map((ch) => {
    let peak = 0;
    for (let i = ch; i < n; i += 3) peak = Math.max(peak, Math.abs(sum[i]));
    return peak > 0 ? peak : 1;
  });
  for (let i = 0; i < n; i++) sum[i] /= scale[i % 3];
  return { data: sum, scale };
}

/**
 * L_ms in the lights' intensities: each component's radiance array (field.components) times its
 * RGB intensity (``intensities``, in the same order), summed (weightedSum's { data, scale }, over
 * the radiance grid).
 */
export function mixedRadiance(field, intensities) {
  return weightedSum(field.components.map((c, k) => ({ a: field.arrays[c.ms], e: intensities[k] })));
}

/**
 * What a camera ray sees of the environment maps behind the medium: each map's lat-long
 * background (field.components' ``background``) times its intensity, summed (weightedSum's
 * { data, scale } and the image's width and height), or null without a map.
 */
export function mixedBackground(field, intensities) {
  const terms = field.components.flatMap((c, k) => (c.background ? [{ a: field.arrays[c.background], e: intensities[k] }] : []));
  if (!terms.length) return null;
  const [height, width] = terms[0].a.shape;
  return { ...weightedSum(terms), width, height };
}

/** Suns whose transmittance the moving camera's texture of an anisotropic field holds apart
 * (one texture: packedField's ``sunT``). */
export const MOVING_PHASE_SUNS = 4;

/** Channels a GPU keeps per texel of a texture of a channel a sun for the next ``suns`` suns, at
 * most four (RGB padded to RGBA). */
export function texelChannels(suns) {
  const n = Math.min(4, Math.max(0, suns));
  return n === 3 ? 4 : n;
}

/**
 * The moving camera's texture: per density voxel (sigma_t / scale, L_in r, g, b) with
 * L_in = sum over suns E exp(-tau_light) / 4pi + L_ms (resampled to the density grid; with
 * ms_light each sun's apart, times its light factor at the voxel).
 * ``mix`` (glview.js): { direct: per sun E / 4pi, ms: mixedRadiance's, sunMs: per sun its own
 * (with ms_light; else empty) }. With ``phase`` (an
 * anisotropic field, at most MOVING_PHASE_SUNS suns) L_in is L_ms alone, whose view terms it
 * leaves out, and ``sunT`` holds each sun's exp(-tau_light) per voxel (texelChannels a voxel: a
 * moving step's second fetch reads no more than it needs): the shader weights them by E p per
 * ray. Returns { packed (float32 RGBA), sunT (or null) }.
 */
export function packedField(field, mix, { phase = false } = {}) {
  const { sigma_t, radiance_ms } = field.arrays;
  const [nz, ny, nx] = sigma_t.shape;
  const [mz, my, mx] = radiance_ms.shape;
  const taus = field.suns.map((s) => voxelTransmittance(field.arrays[s.tau], field.tauPower, sigma_t.shape));
  // what is resampled: the mixed L_ms, and each sun's apart (mix.sunMs, with ms_light) with its
  // light factor at the voxel's transmittance
  const sources = [{ ms: mix.ms, sun: -1 }, ...(mix.sunMs || []).map((ms, sun) => ({ ms, sun }))].filter((s) => !s.ms.empty);
  const { power, range } = field.msLight || { power: [0, 0, 0], range: 0 };
  const X = axisWeights(nx, mx);
  const Y = axisWeights(ny, my);
  const Z = axisWeights(nz, mz);
  const out = new Float32Array(4 * nx * ny * nz);
  const nt = texelChannels(taus.length);
  const sunT = phase ? new Float32Array(nt * nx * ny * nz) : null;
  const c = [0, 0, 0];
  let v = 0;
  for (let k = 0; k < nz; k++) {
    const wz = Z.w[k];
    const z0 = Z.i0[k] * my;
    const z1 = Z.i1[k] * my;
    for (let j = 0; j < ny; j++) {
      const wy = Y.w[j];
      const r00 = (z0 + Y.i0[j]) * mx;
      const r01 = (z0 + Y.i1[j]) * mx;
      const r10 = (z1 + Y.i0[j]) * mx;
      const r11 = (z1 + Y.i1[j]) * mx;
      for (let i = 0; i < nx; i++, v++) {
        const wx = X.w[i];
        const a = X.i0[i];
        const b = X.i1[i];
        let er = 0;
        let eg = 0;
        let eb = 0;
        for (const { ms, sun } of sources) {
          const rad = ms.data;
          for (let ch = 0; ch < 3; ch++) {
            const at = (row, col) => rad[3 * (row + col) + ch];
            const y0 = (1 - wz) * ((1 - wx) * at(r00, a) + wx * at(r00, b)) + wz * ((1 - wx) * at(r10, a) + wx * at(r10, b));
            const y1 = (1 - wz) * ((1 - wx) * at(r01, a) + wx * at(r01, b)) + wz * ((1 - wx) * at(r11, a) + wx * at(r11, b));
            c[ch] = ms.scale[ch] * ((1 - wy) * y0 + wy * y1);
          }
          if (sun >= 0) {
            const tau = -Math.log(Math.max(taus[sun][v], 1e-30));
            for (let ch = 0; ch < 3; ch++) c[ch] *= Math.exp(-Math.min(power[ch] * tau, range));
          }
          er += c[0];
          eg += c[1];
          eb += c[2];
        }
        for (let s = 0; s < taus.length; s++) {
          const direct = taus[s][v];
          if (sunT) {
            sunT[nt * v + s] = direct;
          } else {
            er += mix.direct[s][0] * direct;
            eg += mix.direct[s][1] * direct;
            eb += mix.direct[s][2] * direct;
          }
        }
        out[4 * v] = HALF[sigma_t.data[v]];
        out[4 * v + 1] = er;
        out[4 * v + 2] = eg;
        out[4 * v + 3] = eb;
      }
    }
  }
  return { packed: out, sunT };
}

/**
 * A shaped sun's view terms (an ms_shape array: float16 bits, SHAPE_TERMS channels, a scale
 * each) as floats with their scales applied, and its grid's texel centres in the world
 * (``unitToWorld``: 16 numbers, row-major), for viewSums: { terms, points, channels }.
 */
export function viewGrid(array, unitToWorld) {
  const [nz, ny, nx, channels] = array.shape;
  const terms = new Float32Array(array.data.length);
  for (let i = 0; i < terms.length; i++) terms[i] = HALF[array.data[i]] * Number(array.scale[i % channels]);
  const m = unitToWorld;
  const points = new Float32Array(3 * nx * ny * nz);
  for (let z = 0, i = 0; z < nz; z++) {
    for (let y = 0; y < ny; y++) {
      for (let x = 0; x < nx; x++, i += 3) {
        const u = [(x + 0.5) / nx, (y + 0.5) / ny, (z + 0.5) / nz];
        for (let r = 0; r < 3; r++) points[i + r] = m[4 * r] * u[0] + m[4 * r + 1] * u[1] + m[4 * r + 2] * u[2] + m[4 * r + 3];
      }
    }
  }
  return { terms, points, channels };
}

/**
 * A shaped sun's view terms summed toward a pinhole camera at ``eye`` (world): at each texel x
 * of its grid (viewGrid's), sum_i c_i B_i(d) with d = (x - eye) / |x - eye| in the sun's
 * ``frame`` (9 numbers, rows e_x, e_y, e_z), the direction of every camera ray through x, as
 * the server's march takes it (cloudgraph/field_textures.py, look_from): the march reads
 * one channel where it would read SHAPE_TERMS.
 */
export function viewSums(grid, frame, eye) {
  const { terms, points, channels } = grid;
  const out = new Float32Array(points.length / 3);
  const B = new Float64Array(channels);
  const P = new Float64Array(9);
  for (let i = 0; i < out.length; i++) {
    const dx = points[3 * i] - eye[0];
    const dy = points[3 * i + 1] - eye[1];
    const dz = points[3 * i + 2] - eye[2];
    const r = Math.hypot(dx, dy, dz) || 1;
    const x = (frame[0] * dx + frame[1] * dy + frame[2] * dz) / r;
    const y = (frame[3] * dx + frame[4] * dy + frame[5] * dz) / r;
    const z = (frame[6] * dx + frame[7] * dy + frame[8] * dz) / r;
    viewBasis(x, y, z, B, P);
    let sum = 0;
    for (let c = 0; c < channels; c++) sum += terms[i * channels + c] * B[c];
    out[i] = sum;
  }
  return out;
}

/**
 * The view terms' functions of direction (x, y, z) in a sun's frame, into B (api.md's order,
 * cloudgraph/phase.py's shape_basis): y, z, x, 6xy, 3yz, P2(z), 3xz, 3(x^2 - y^2), P3..P8(z),
 * then degree 3's 15(3x^2 y - y^3), 30xyz, 1.5(5z^2 - 1) y, 1.5(5z^2 - 1) x, 15z(x^2 - y^2),
 * 15(x^3 - 3xy^2) (their weights are in the coefficients).
 */
function viewBasis(x, y, z, B, P) {
  // (B and P, the Legendre polynomials' scratch, are the caller's: no array a texel)
  P[0] = 1;
  P[1] = z;
  for (let n = 1; n < 8; n++) P[n + 1] = ((2 * n + 1) * z * P[n] - n * P[n - 1]) / (n + 1);
  const q = 1.5 * (5 * z * z - 1);
  B[0] = y;
  B[1] = z;
  B[2] = x;
  B[3] = 6 * x * y;
  B[4] = 3 * y * z;
  B[5] = P[2];
  B[6] = 3 * x * z;
  B[7] = 3 * (x * x - y * y);
  for (let n = 3; n <= 8; n++) B[5 + n] = P[n]; // B[8..13] = P3..P8
  B[14] = 15 * (3 * x * x * y - y * y * y);
  B[15] = 30 * x * y * z;
  B[16] = q * y;
  B[17] = q * x;
  B[18] = 15 * z * (x * x - y * y);
  B[19] = 15 * (x * x * x - 3 * x * y * y);
}
