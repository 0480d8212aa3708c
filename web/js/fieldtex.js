// Texture data made in the page from a decoded field (field.js), for glview.js: sigma_t and
// tau_light interleaved into one RG texture, and the moving camera's (sigma_t, L_in) texture.

import { halfToFloat } from "./field.js";

/** Two float16 arrays of one grid as one RG array (a, b alternating). */
export function interleaved(a, b) {
  const out = new Uint16Array(2 * a.length);
  for (let i = 0; i < a.length; i++) {
    out[2 * i] = a[i];
    out[2 * i + 1] = b[i];
  }
  return out;
}

/** Channels [from, from + 4) of a float16 array of ``channels`` per texel, as RGBA (zero past
 * its last channel). */
export function channelGroup(data, channels, from) {
  const n = data.length / channels;
  const out = new Uint16Array(4 * n);
  const k = Math.min(4, channels - from);
  for (let i = 0; i < n; i++) {
    for (let c = 0; c < k; c++) out[4 * i + c] = data[i * channels + from + c];
  }
  return out;
}

const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) HALF[h] = halfToFloat(h);

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
 * The moving camera's texture: per density voxel (sigma_t / scale, L_in r, g, b) with
 * L_in = E exp(-tau_light) / 4pi + radiance_ms (resampled to the density grid), and a v1.1
 * field's sky radiance array added. ``mix`` (glview.js): { direct: E / 4pi, radScale: the
 * scale of radiance_ms in this light, sky: null or { data, scale } }. Float32 RGBA.
 */
export function packedField(field, mix) {
  const { sigma_t, tau_light, radiance_ms } = field.arrays;
  const [nz, ny, nx] = sigma_t.shape;
  const [mz, my, mx] = radiance_ms.shape;
  const [ex, ey, ez] = mix.direct;
  const [sr, sg, sb] = mix.radScale;
  const tauScale = Number(tau_light.scale);
  const rad = radiance_ms.data;
  const sky = mix.sky ? mix.sky.data : null;
  const [kr, kg, kb] = mix.sky ? mix.sky.scale : [0, 0, 0];
  const q = [0, 0, 0]; // the sky's, resampled
  const X = axisWeights(nx, mx);
  const Y = axisWeights(ny, my);
  const Z = axisWeights(nz, mz);
  const out = new Float32Array(4 * nx * ny * nz);
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
        const resample = (src, ch) => {
          const at = (row, col) => HALF[src[3 * (row + col) + ch]];
          const y0 = (1 - wz) * ((1 - wx) * at(r00, a) + wx * at(r00, b)) + wz * ((1 - wx) * at(r10, a) + wx * at(r10, b));
          const y1 = (1 - wz) * ((1 - wx) * at(r01, a) + wx * at(r01, b)) + wz * ((1 - wx) * at(r11, a) + wx * at(r11, b));
          return (1 - wy) * y0 + wy * y1;
        };
        for (let ch = 0; ch < 3; ch++) {
          c[ch] = resample(rad, ch);
          q[ch] = sky ? resample(sky, ch) : 0;
        }
        const direct = Math.exp(-tauScale * HALF[tau_light.data[v]]);
        out[4 * v] = HALF[sigma_t.data[v]];
        out[4 * v + 1] = ex * direct + sr * c[0] + kr * q[0];
        out[4 * v + 2] = ey * direct + sg * c[1] + kg * q[1];
        out[4 * v + 3] = ez * direct + sb * c[2] + kb * q[2];
      }
    }
  }
  return out;
}
