// The radiance field of a cache (GET /v1/caches/{id}/field): fetched once, decoded here into
// typed-array views on the body, never copied. Layout (api.md): "CGFIELD1", a uint32 LE header
// length H, H bytes of JSON, then little-endian C-order arrays at the header's byte offsets.

export const MAGIC = "CGFIELD1";
const FORMAT = "cloudgraph-field";

/** An error in the field's bytes or header; ``message`` is meant for people. */
export class FieldError extends Error {
  constructor(message) {
    super(message);
    this.name = "FieldError";
  }
}

/** Channels of an ms_shape array: the functions of direction of cloudgraph/phase.py's
 * SHAPE_TERMS (shaders.js writes them out). */
export const SHAPE_TERMS = 14;

const ARRAYS = {
  sigma_t: { dims: 3 },
  tau_light: { dims: 3 },
  radiance_ms: { dims: 4, channels: 3 },
  majorant: { dims: 3 },
};

function vec(v, n, what) {
  if (!Array.isArray(v) || v.length !== n || !v.every(Number.isFinite)) {
    throw new FieldError(`the field's header has no valid ${what} (${n} numbers)`);
  }
  return v.map(Number);
}

/**
 * Decodes a field body (an ArrayBuffer, already gunzipped by fetch).
 *
 * Returns { header, unitToWorld (16 numbers, row-major), worldToUnit (16, row-major),
 * worldBbox, light: { direction, irradiance }, albedo, step (world units), maxDtau (a
 * segment's optical depth at most), edge (world units: where the light enters the box within
 * this, tau_light is integrated from sigma_t),
 * arrays: { name: { data: Uint16Array of float16 bits, shape, scale } }, bytes }.
 * Throws FieldError naming what is wrong.
 */
export function decodeField(buffer) {
  if (!(buffer instanceof ArrayBuffer) || buffer.byteLength < 12) {
    throw new FieldError("the answer is too short to be a cloudgraph field");
  }
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(...bytes.subarray(0, 8));
  if (magic !== MAGIC) throw new FieldError("the answer is not a cloudgraph field (wrong magic bytes)");
  const headerLength = new DataView(buffer).getUint32(8, true);
  if (12 + headerLength > buffer.byteLength) throw new FieldError("the field's header is cut short");
  let header;
  try {
    header = JSON.parse(new TextDecoder().decode(bytes.subarray(12, 12 + headerLength)));
  } catch {
    throw new FieldError("the field's header is not JSON");
  }
  if (header.format !== FORMAT || header.version !== 1) {
    throw new FieldError(`unsupported field format ${JSON.stringify(header.format)} version ${header.version}`);
  }
  const unitToWorld = vec((header.unit_to_world || []).flat(), 16, "unit_to_world");
  const lights = header.lights ? lightComponents(header.lights) : null;
  const specs = { ...ARRAYS };
  if (lights && lights.sky) specs[lights.sky] = ARRAYS.radiance_ms;
  // An anisotropic phase's field: how the sun's L_ms depends on the view (api.md, ms_shape)
  const shapeSpec = lights ? lights.shape : header.ms_shape || null;
  if (shapeSpec) {
    if (typeof shapeSpec.array !== "string") throw new FieldError("the field's ms_shape names no array");
    specs[shapeSpec.array] = { dims: 4, channels: SHAPE_TERMS };
  }
  const arrays = {};
  for (const [name, spec] of Object.entries(specs)) {
    const a = header.arrays && header.arrays[name];
    if (!a) throw new FieldError(`the field has no ${name} array`);
    if (a.dtype !== "float16") throw new FieldError(`${name}: dtype ${a.dtype} is not supported (float16 only)`);
    const shape = a.shape;
    if (!Array.isArray(shape) || shape.length !== spec.dims || !shape.every((n) => Number.isInteger(n) && n > 0)) {
      throw new FieldError(`${name}: bad shape ${JSON.stringify(shape)}`);
    }
    if (spec.channels && shape[3] !== spec.channels) throw new FieldError(`${name}: expected ${spec.channels} channels`);
    const count = shape.reduce((p, n) => p * n, 1);
    if (!Number.isInteger(a.offset) || a.offset % 2 || a.offset < 12 + headerLength || a.offset + 2 * count > buffer.byteLength) {
      throw new FieldError(`${name}: its bytes lie outside the body`);
    }
    const scale = spec.channels ? vec(a.scale, spec.channels, `${name} scale`) : Number(a.scale ?? 1);
    if (!spec.channels && !Number.isFinite(scale)) throw new FieldError(`${name}: bad scale`);
    arrays[name] = { data: new Uint16Array(buffer, a.offset, count), shape, scale, block: a.block };
  }
  if (arrays.sigma_t.shape.join() !== arrays.tau_light.shape.join()) {
    throw new FieldError("sigma_t and tau_light differ in shape");
  }
  if (!(Number.isInteger(arrays.majorant.block) && arrays.majorant.block > 0)) {
    throw new FieldError("majorant: no block size");
  }
  const step = Number(header.step);
  if (!(step > 0)) throw new FieldError("the field's header has no valid step");
  const maxDtau = Number(header.max_dtau);
  const edge = Number(header.edge);
  if (!(maxDtau > 0) || !(edge >= 0)) throw new FieldError("the field's header has no valid max_dtau or edge");
  if (lights && lights.sky && arrays[lights.sky].shape.join() !== arrays.radiance_ms.shape.join()) {
    throw new FieldError("the sky's radiance differs in shape from radiance_ms");
  }
  // A v1.1 field holds its lights at unit intensity (the page mixes them, setMix); a v1 one
  // its light at its irradiance
  const light = lights ? { direction: lights.direction, irradiance: [1, 1, 1] } : header.light || {};
  return {
    header,
    unitToWorld,
    worldToUnit: invertAffine(unitToWorld),
    worldBbox: header.world_bbox,
    light: { direction: vec(light.direction, 3, "light.direction"), irradiance: vec(light.irradiance, 3, "light.irradiance") },
    // v1.1: { sun: whether the first component is a directional light, sky: its radiance
    // array's name or null }; null for a v1 field
    lights,
    // { array: its name, frame: 9 numbers, rows e_x, e_y, e_z (e_z toward the light) } or null
    shape: shapeSpec ? { array: shapeSpec.array, frame: vec((shapeSpec.frame || []).flat(), 9, "ms_shape frame") } : null,
    albedo: vec(header.albedo, 3, "albedo"),
    step,
    maxDtau,
    edge,
    arrays,
    bytes: buffer.byteLength,
  };
}

/**
 * The light components of a v1.1 field's header (api.md): at most one directional light (the
 * first component, with tau_light and radiance_ms) and a sky. Throws FieldError otherwise.
 */
function lightComponents(list) {
  if (!Array.isArray(list) || !list.length) throw new FieldError("the field's header has no valid lights");
  const suns = list.filter((c) => c && c.type === "directional");
  const skies = list.filter((c) => c && c.type === "sky");
  if (list.some((c) => c && c.type === "envmap")) {
    throw new FieldError("the real-time view does not draw environment maps: render this cache on the server");
  }
  if (suns.length + skies.length !== list.length) throw new FieldError("the field's header has a light of unknown type");
  if (suns.length > 1) {
    throw new FieldError(`the real-time view draws one directional light, and this cache has ${suns.length}: render it on the server`);
  }
  const sun = suns[0];
  if (sun && (list[0] !== sun || sun.tau !== "tau_light" || sun.ms !== "radiance_ms")) {
    throw new FieldError("the field's directional light is not its first component");
  }
  const sky = skies[0] || null;
  if (sky && (typeof sky.ms !== "string" || (sun ? sky.ms === "radiance_ms" : sky.ms !== "radiance_ms"))) {
    throw new FieldError("the field's sky has no radiance array of its own");
  }
  return {
    sun: !!sun,
    shape: (sun && sun.shape) || null,
    // without a sun the sky is the first component: its radiance is radiance_ms itself
    sky: sky ? sky.ms : null,
    direction: sun ? sun.direction : [0, -1, 0],
  };
}

/** The inverse of a row-major 4x4 affine map (last row 0 0 0 1), row-major. */
export function invertAffine(m) {
  const [a, b, c, d, e, f, g, h, i] = [m[0], m[1], m[2], m[4], m[5], m[6], m[8], m[9], m[10]];
  const A = e * i - f * h;
  const B = -(d * i - f * g);
  const C = d * h - e * g;
  const det = a * A + b * B + c * C;
  if (!Number.isFinite(det) || Math.abs(det) < 1e-30) throw new FieldError("unit_to_world is not invertible");
  const inv = [
    A, -(b * i - c * h), b * f - c * e,
    B, a * i - c * g, -(a * f - c * d),
    C, -(a * h - b * g), a * e - b * d,
  ].map((v) => v / det);
  const t = [m[3], m[7], m[11]];
  const out = [];
  for (let r = 0; r < 3; r++) {
    const row = inv.slice(3 * r, 3 * r + 3);
    out.push(...row, -(row[0] * t[0] + row[1] * t[1] + row[2] * t[2]));
  }
  out.push(0, 0, 0, 1);
  return out;
}

/** A float16 bit pattern as a number. */
export function halfToFloat(h) {
  const s = h & 0x8000 ? -1 : 1;
  const e = (h >> 10) & 0x1f;
  const f = h & 0x3ff;
  if (e === 0) return s * f * 2 ** -24;
  if (e === 31) return f ? NaN : s * Infinity;
  return s * (1 + f / 1024) * 2 ** (e - 15);
}

/** Downloads and decodes the field of cache ``cacheId``. Resolves with decodeField's object. */
export async function fetchField(api, cacheId, { signal } = {}) {
  const path = `/v1/caches/${encodeURIComponent(cacheId)}/field`;
  const what = "Downloading the radiance field";
  const response = await api.request(path, { signal, what });
  let buffer;
  try {
    buffer = await response.arrayBuffer();
  } catch (err) {
    if (err && err.name === "AbortError") throw err;
    throw new FieldError(`${what} failed: the download broke off (${err.message || err})`);
  }
  try {
    return decodeField(buffer);
  } catch (err) {
    if (err instanceof FieldError) throw new FieldError(`${what} failed: ${err.message}`);
    throw err;
  }
}
