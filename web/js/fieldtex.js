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
 * L_in = E exp(-tau_light) / 4pi + radiance_ms (resampled to the density grid). Float32 RGBA.
 */
export function packedField(field) {
  const { sigma_t, tau_light, radiance_ms } = field.arrays;
  const [nz, ny, nx] = sigma_t.shape;
  const [mz, my, mx] = radiance_ms.shape;
  const [ex, ey, ez] = field.light.irradiance.map((e) => e / (4 * Math.PI));
  const [sr, sg, sb] = radiance_ms.scale;
  const tauScale = Number(tau_light.scale);
  const rad = radiance_ms.data;
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
        for (let ch = 0; ch < 3; ch++) {
          const at = (row, col) => HALF[rad[3 * (row + col) + ch]];
          const y0 = (1 - wz) * ((1 - wx) * at(r00, a) + wx * at(r00, b)) + wz * ((1 - wx) * at(r10, a) + wx * at(r10, b));
          const y1 = (1 - wz) * ((1 - wx) * at(r01, a) + wx * at(r01, b)) + wz * ((1 - wx) * at(r11, a) + wx * at(r11, b));
          c[ch] = (1 - wy) * y0 + wy * y1;
        }
        const direct = Math.exp(-tauScale * HALF[tau_light.data[v]]);
        out[4 * v] = HALF[sigma_t.data[v]];
        out[4 * v + 1] = ex * direct + sr * c[0];
        out[4 * v + 2] = ey * direct + sg * c[1];
        out[4 * v + 3] = ez * direct + sb * c[2];
      }
    }
  }
  return out;
}
