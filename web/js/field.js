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

/** The most orders of the suns' light in their beam a field's header may name (ms_forward;
 * cloudgraph/field_ms.py FORWARD_ORDERS). */
export const MAX_FORWARD = 3;

/** Channels of an ms_shape array: the functions of direction of cloudgraph/phase.py's
 * SHAPE_TERMS (fieldtex.js writes them out). */
export const SHAPE_TERMS = 20;

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

/** A sun's ms_shape entry (api.md): its array, frame and the grey power of the light factor
 * its terms are kept over (absent: 0, the terms themselves). */
function shapeEntry(shape) {
  const lightPower = Number(shape.light_power ?? 0);
  if (!(lightPower >= 0)) throw new FieldError("the field's ms_shape has no valid light_power (>= 0)");
  return { array: shape.array, frame: vec((shape.frame || []).flat(), 9, "ms_shape frame"), lightPower };
}

/**
 * Decodes a field body (an ArrayBuffer, already gunzipped by fetch).
 *
 * Returns { header, unitToWorld (16 numbers, row-major), worldToUnit (16, row-major),
 * worldBbox, light: { direction, irradiance }, albedo, step (world units), maxDtau (a
 * segment's optical depth at most), edge (world units: where the light enters the box within
 * this, tau_light is integrated from sigma_t), tauPower (the tau arrays are interpolated as
 * exp(-tauPower tau); 0: as tau), arrays: { name: { data: Uint16Array of float16 bits, shape,
 * scale } }, bytes }.
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
  const lights = header.lights ? lightComponents(header.lights) : v1Light(header);
  const specs = { ...ARRAYS };
  for (const c of lights.components) {
    specs[c.ms] = ARRAYS.radiance_ms;
    if (c.background) specs[c.background] = { dims: 3, channels: 3 }; // an environment's, lat-long
  }
  for (const sun of lights.suns) {
    specs[sun.tau] = ARRAYS.tau_light;
    // An anisotropic phase's field: how the sun's L_ms depends on the view (api.md, ms_shape)
    if (sun.shape) specs[sun.shape.array] = { dims: 4, channels: SHAPE_TERMS };
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
    if (spec.channels && shape[spec.dims - 1] !== spec.channels) throw new FieldError(`${name}: expected ${spec.channels} channels`);
    const count = shape.reduce((p, n) => p * n, 1);
    if (!Number.isInteger(a.offset) || a.offset % 2 || a.offset < 12 + headerLength || a.offset + 2 * count > buffer.byteLength) {
      throw new FieldError(`${name}: its bytes lie outside the body`);
    }
    const scale = spec.channels ? vec(a.scale, spec.channels, `${name} scale`) : Number(a.scale ?? 1);
    if (!spec.channels && !Number.isFinite(scale)) throw new FieldError(`${name}: bad scale`);
    arrays[name] = { data: new Uint16Array(buffer, a.offset, count), shape, scale, block: a.block };
  }
  // tau_light at sigma_t's resolution, or twice it on every axis (cloudgraph/light_depth.py)
  const tauShape = arrays.tau_light.shape;
  const fineTau = tauShape.join() !== arrays.sigma_t.shape.join();
  if (fineTau && !tauShape.every((n, i) => n === 2 * arrays.sigma_t.shape[i])) {
    throw new FieldError("tau_light is neither at sigma_t's resolution nor at twice it");
  }
  if (!(Number.isInteger(arrays.majorant.block) && arrays.majorant.block > 0)) {
    throw new FieldError("majorant: no block size");
  }
  const step = Number(header.step);
  if (!(step > 0)) throw new FieldError("the field's header has no valid step");
  const maxDtau = Number(header.max_dtau);
  const edge = Number(header.edge);
  if (!(maxDtau > 0) || !(edge >= 0)) throw new FieldError("the field's header has no valid max_dtau or edge");
  const tauPower = Number(header.tau_power ?? 0); // (absent: a field of before it, tau interpolated)
  if (!(tauPower >= 0)) throw new FieldError("the field's header has no valid tau_power");
  if (fineTau && !(tauPower > 0)) {
    throw new FieldError("a tau_light finer than sigma_t needs the header's tau_power");
  }
  // each sun's L_ms held over its own light factor exp(-min(P tau, range)) (absent: L_ms itself)
  const ml = header.ms_light;
  const msLight = ml ? { power: vec(ml.power, 3, "ms_light.power"), range: Number(ml.range) } : null;
  if (msLight && (!lights.suns.length || !(msLight.range >= 0) || !msLight.power.every((p) => p >= 0))) {
    throw new FieldError("the field's header has no valid ms_light (power >= 0, range >= 0, a sun)");
  }
  // an anisotropic phase's suns: the orders of their light in its beam the march adds in
  // closed form (absent: none)
  const forward = Number(header.ms_forward ?? 0);
  if (!(Number.isInteger(forward) && forward >= 0 && forward <= MAX_FORWARD)) {
    throw new FieldError(`the field's header has no valid ms_forward (an integer 0..${MAX_FORWARD})`);
  }
  const backgrounds = lights.components.filter((c) => c.background).map((c) => arrays[c.background].shape);
  for (const c of lights.components) {
    if (arrays[c.ms].shape.join() !== arrays.radiance_ms.shape.join()) {
      throw new FieldError(`${c.ms} differs in shape from radiance_ms`);
    }
  }
  if (backgrounds.some((b) => b.join() !== backgrounds[0].join() || b[1] !== 2 * b[0])) {
    throw new FieldError("the environments' backgrounds are not lat-long images of one size");
  }
  for (const sun of lights.suns) {
    if (arrays[sun.tau].shape.join() !== tauShape.join()) throw new FieldError(`${sun.tau} differs in shape from tau_light`);
  }
  return {
    header,
    unitToWorld,
    worldToUnit: invertAffine(unitToWorld),
    worldBbox: header.world_bbox,
    // A v1.1 field holds its lights at unit intensity (the page mixes them, glview's setMix); a
    // v1 one its light at its irradiance
    unit: !!header.lights,
    // the directional lights: { direction (the way light travels), tau: its tau array's name,
    // shape: null or { array, frame: 9 numbers, rows e_x, e_y, e_z (e_z toward the light),
    // lightPower: the grey P of the light factor its terms are kept over (0: none) }, base: its
    // colour at scale 1 that the mix multiplies (1, or a sunsky's sun's: the model's) }
    suns: lights.suns.map((s) => ({
      direction: vec(s.direction, 3, "light.direction"),
      tau: s.tau,
      shape: s.shape ? shapeEntry(s.shape) : null,
      base: s.base,
    })),
    // every light component in the header's order: { type, ms: its radiance array's name,
    // background: an environment map's lat-long background array's name, else null }
    components: lights.components,
    // a v1 field's light: { irradiance }
    irradiance: lights.irradiance ? vec(lights.irradiance, 3, "light.irradiance") : null,
    albedo: vec(header.albedo, 3, "albedo"),
    step,
    maxDtau,
    edge,
    tauPower,
    msLight,
    forward,
    arrays,
    bytes: buffer.byteLength,
  };
}

/** The most lights, and so directional lights, a field has (api.md). */
export const MAX_LIGHTS = 8;
export const MAX_SUNS = MAX_LIGHTS;

/** A v1 field's one light as lightComponents' object. */
function v1Light(header) {
  const light = header.light || {};
  const shape = header.ms_shape || null;
  if (shape && typeof shape.array !== "string") throw new FieldError("the field's ms_shape names no array");
  return {
    suns: [{ direction: light.direction, tau: "tau_light", shape }],
    components: [{ type: "directional", ms: "radiance_ms" }],
    irradiance: light.irradiance,
  };
}

/**
 * The light components of a v1.1 field's header (api.md): directional lights, each with its
 * tau array (the first's tau_light), a sky and environment maps (each with its background),
 * each with its radiance array (the first component's radiance_ms). Throws FieldError
 * otherwise.
 */
function lightComponents(list) {
  if (!Array.isArray(list) || !list.length || list.length > MAX_LIGHTS) {
    throw new FieldError("the field's header has no valid lights");
  }
  if (!list.every((c) => c && ["directional", "sky", "envmap"].includes(c.type))) {
    throw new FieldError("the field's header has a light of unknown type");
  }
  if (list.some((c) => c.type === "envmap" && typeof c.background !== "string")) {
    throw new FieldError("the field keeps no background of its environment map: render this cache on the server");
  }
  const names = list.map((c) => c.ms);
  if (names[0] !== "radiance_ms" || !names.every((n) => typeof n === "string") || new Set(names).size !== names.length) {
    throw new FieldError("the field's lights do not each name a radiance array of their own");
  }
  const suns = list.filter((c) => c.type === "directional");
  if (suns.length > MAX_SUNS || list.filter((c) => c.type === "sky").length > 1) {
    throw new FieldError("the field's header has too many lights");
  }
  const taus = suns.map((s) => s.tau);
  if (suns.length && (taus[0] !== "tau_light" || list[0] !== suns[0] || !taus.every((n) => typeof n === "string") || new Set(taus).size !== taus.length)) {
    throw new FieldError("the field's directional lights do not each name a tau array of their own");
  }
  for (const s of suns) {
    if (s.shape && typeof s.shape.array !== "string") throw new FieldError("a directional light's shape names no array");
    const rgb = (b) => Array.isArray(b) && b.length === 3 && b.every((v) => Number.isFinite(v) && v >= 0);
    if (s.base !== undefined && !rgb(s.base)) throw new FieldError("a directional light's base is not an RGB colour");
  }
  return {
    // base: a sunsky's sun's colour at its sun_scale 1, which the mix scales (api.md)
    suns: suns.map((s) => ({ direction: s.direction, tau: s.tau, shape: s.shape || null, base: s.base || [1, 1, 1] })),
    components: list.map((c) => ({ type: c.type, ms: c.ms, background: c.background || null })),
    irradiance: null,
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
