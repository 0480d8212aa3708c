// The WebGL2 renderer of a radiance field: 3D textures on the GPU, one draw per frame, and a
// read-back of an image at a given size for comparisons. Knows nothing of the DOM around it.

import { fragmentShader, textureUnits, VERTEX } from "./shaders.js";
import { depthTexels, halfFloats, interleaved, mixedBackground, mixedRadiance, MOVING_PHASE_SUNS, packedField, texelChannels, viewGrid, viewSums } from "./fieldtex.js";
import { linearToSrgb8, srgbToLinear } from "./imagemath.js";
import { cross, normalize, sub } from "./camera.js";

/** [internal format, format] of a 16F texture of 1-4 channels (the suns' tau and transmittance
 * textures). */
const TAU_FORMATS = [
  ["R16F", "RED"],
  ["RG16F", "RG"],
  ["RGB16F", "RGB"],
  ["RGBA16F", "RGBA"],
];

/** Why this browser cannot draw the real-time view, or "" when it can. */
export function webgl2Missing(canvas) {
  if (typeof WebGL2RenderingContext === "undefined") return "this browser has no WebGL2";
  return canvas.getContext("webgl2") ? "" : "WebGL2 is disabled or unavailable in this browser";
}

function compile(gl, type, source) {
  const s = gl.createShader(type);
  gl.shaderSource(s, source);
  gl.compileShader(s);
  if (!gl.getShaderParameter(s, gl.COMPILE_STATUS) && !gl.isContextLost()) {
    throw new Error(`the ray-march shader does not compile: ${gl.getShaderInfoLog(s)}`);
  }
  return s;
}

/** Pinhole basis of a scene-spec camera {eye, target, up, fov, width, height} (as the server's). */
export function cameraBasis(cam) {
  const forward = normalize(sub(cam.target, cam.eye));
  const right = normalize(cross(forward, cam.up));
  const up = cross(right, forward);
  return { forward, right, up };
}

/**
 * A field in a light: { suns: per directional light its RGB irradiance, components: per light
 * component (field.components) the intensity its arrays are scaled by, sky: the sky's radiance
 * seen behind the medium }. A v1 field is in its own light; a v1.1 one (unit components) in
 * ``mix`` ({ suns: [[3] per directional light], sky: [3], envmaps: [[3] scale per map] }; none
 * given: each sun and map 1, no sky; a sun or map past the mix's list is off), each sun's times
 * its ``base`` (a sunsky's sun: the model's colour, the mix its sun_scale).
 */
export function lightsOf(field, mix) {
  if (!field.unit) return { suns: [field.irradiance], components: [[1, 1, 1]], sky: [0, 0, 0] };
  const nth = (list, i) => (mix ? (list && list[i]) || [0, 0, 0] : [1, 1, 1]);
  const sunE = field.suns.map((s, i) => nth(mix && mix.suns, i).map((e, c) => e * (s.base ? s.base[c] : 1)));
  const sky = (mix && mix.sky) || [0, 0, 0];
  let sun = 0;
  let map = 0;
  const components = field.components.map((c) => {
    if (c.type === "sky") return sky;
    return c.type === "envmap" ? nth(mix && mix.envmaps, map++) : sunE[sun++];
  });
  return { suns: sunE, components, sky: field.components.some((c) => c.type === "sky") ? sky : [0, 0, 0] };
}

/** The shader's uniforms of a field in a light (lightsOf) and its mixed L_ms (fieldtex.js):
 * with ms_light each sun's L_ms apart (sunMs, over its light factor), the others' mixed (ms). */
function mixOf(field, mix) {
  const lights = lightsOf(field, mix);
  const apart = field.components.map((c) => !!field.msLight && c.type === "directional");
  const only = (keep) => lights.components.map((e, k) => (keep(k) ? e : [0, 0, 0]));
  // (every component a sun's: the others' texture is one zero texel, not a grid of zeros)
  const ms = apart.every((a) => a) ? { data: new Float32Array(3), scale: [1, 1, 1], empty: true } : mixedRadiance(field, only((k) => !apart[k]));
  const sunMs = apart.flatMap((a, k) => (a ? [mixedRadiance(field, only((j) => j === k))] : []));
  const env = mixedBackground(field, lights.components);
  const direct = lights.suns.map((E) => E.map((e) => e / (4 * Math.PI)));
  const uniforms = {
    direct,
    radScale: ms.scale,
    sunRadScale: sunMs.map((s) => s.scale),
    background: lights.sky,
    envScale: env ? env.scale : [0, 0, 0],
  };
  return { ms, sunMs, env, direct, uniforms };
}

export class GLView {
  /** canvas: the <canvas> to draw on. Throws if WebGL2 is missing. */
  constructor(canvas) {
    this.canvas = canvas;
    const gl = canvas.getContext("webgl2", {
      alpha: false,
      depth: false,
      stencil: false,
      antialias: false,
      premultipliedAlpha: false,
      preserveDrawingBuffer: false,
      powerPreference: "high-performance",
    });
    if (!gl) throw new Error(webgl2Missing(document.createElement("canvas")) || "WebGL2 is unavailable");
    this.gl = gl;
    this.programs = new Map(); // by layout (program())
    this.program({ packed: false, suns: 1, shaped: [] }); // a shader that does not build fails here
    this.vao = gl.createVertexArray();
    this.textures = null;
    this.field = null;
    this.mix = null; // the lights' intensities for a v1.1 field (setMix)
    this.maxSize = gl.getParameter(gl.MAX_3D_TEXTURE_SIZE);
  }

  /** The ray-march program of a layout { packed, suns, shaped } (shaders.js) and its uniform
   * locations, linked once per layout (a new field may need another; the camera never does). */
  program(layout) {
    const id = JSON.stringify(layout);
    if (!this.programs.has(id)) this.programs.set(id, this.link(layout));
    return this.programs.get(id);
  }

  link(layout) {
    const gl = this.gl;
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, fragmentShader(layout)));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS) && !gl.isContextLost()) {
      throw new Error(`the ray-march shader does not link: ${gl.getProgramInfoLog(program)}`);
    }
    const loc = {};
    const n = gl.getProgramParameter(program, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const name = gl.getActiveUniform(program, i).name;
      loc[name] = gl.getUniformLocation(program, name);
    }
    return { program, loc };
  }

  /**
   * Why ``field`` cannot be drawn on this device, or "". ``maxBytes`` caps the texture memory.
   */
  tooLarge(field, maxBytes = 1 << 30) {
    const dims = Object.values(field.arrays).map((a) => a.shape.slice(0, 3));
    for (const [nz, ny, nx] of dims) {
      if (Math.max(nx, ny, nz) > this.maxSize) {
        return `the field (${nx}×${ny}×${nz}) exceeds this device's 3D texture limit of ${this.maxSize}`;
      }
    }
    const shaped = shapedSuns(field).length;
    const units = textureUnits(field.suns.length, shaped, !!field.msLight) + (hasEnv(field) ? 1 : 0);
    const have = this.gl.getParameter(this.gl.MAX_TEXTURE_IMAGE_UNITS);
    if (units > have) {
      return `its ${shaped} lights' view terms need ${units} texture units and this device has ${have}: render it on the server`;
    }
    const bytes = GLView.textureBytes(field);
    if (bytes > maxBytes) return `the field needs ${(bytes / 2 ** 20).toFixed(0)} MiB of textures`;
    return "";
  }

  /**
   * GPU bytes of a field's textures: R16F density, 16F textures of the suns' tau (a channel
   * each, at the tau grid's resolution), RGBA16F-padded radiance (with ms_light each sun's apart too), R16F majorant, the RGBA16F (sigma_t, L_in) texture of the
   * moving camera with its mipmaps (and of an anisotropic field its suns' transmittance, 16F a
   * channel each, RGB padded), an R16F texture of view sums a shaped sun, and an
   * RGBA16F-padded lat-long background of the environment maps.
   */
  static textureBytes(field) {
    const count = (a) => a.shape[0] * a.shape[1] * a.shape[2];
    const { sigma_t, radiance_ms, majorant } = field.arrays;
    const moving = ((8 + (movingPhase(field) ? 2 * texelChannels(field.suns.length) : 0)) * 8) / 7; // with mips
    const density = 2 + moving;
    const taus = [0, 4].reduce((b, from) => b + 2 * texelChannels(field.suns.length - from) * count(field.arrays.tau_light), 0);
    const shape = shapedSuns(field).reduce((n, k) => n + 2 * count(field.arrays[field.suns[k].shape.array]), 0);
    const env = field.components.find((c) => c.background);
    const background = env ? 8 * field.arrays[env.background].shape[0] * field.arrays[env.background].shape[1] : 0;
    // the others' L_ms (with ms_light: none where every light is a sun), each sun's apart
    const others = !field.msLight || field.components.some((c) => c.type !== "directional");
    const rads = (others ? 1 : 0) + (field.msLight ? field.suns.length : 0);
    return Math.round(density * count(sigma_t) + taus + 8 * rads * count(radiance_ms) + 2 * count(majorant) + shape + background);
  }

  /**
   * The lights' intensities for a v1.1 field (held at unit intensity): { suns: [[3] irradiance
   * per directional light], sky: [3] radiance }. Re-draws need no request: uniforms, L_ms mixed
   * again and the moving camera's texture made again. A v1 field keeps its own light.
   */
  setMix(mix) {
    this.mix = mix;
    if (!this.unitField || !this.textures) return;
    const m = mixOf(this.unitField, mix);
    Object.assign(this.field, m.uniforms);
    const rads = this.makeRadiance(this.unitField, m);
    const moving = this.makeMoving(this.unitField, m);
    const env = m.env && this.makeBackground(m.env);
    for (const name of [...Object.keys(rads), "packed", "sunT", "env"]) if (this.textures[name]) this.gl.deleteTexture(this.textures[name]);
    Object.assign(this.textures, { ...rads, ...moving, env });
  }

  /** The environment maps' lat-long background (mixedBackground's): RGB16F, wrapping around
   * in u, clamped at the poles. */
  makeBackground(env) {
    const gl = this.gl;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB16F, env.width, env.height, 0, gl.RGB, gl.FLOAT, env.data);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.REPEAT);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return t;
  }

  /** A 3D texture of ``data`` (float16 bits, or floats when type is gl.FLOAT) over arr's grid. */
  makeTexture(arr, internal, format, data, filter, type = this.gl.HALF_FLOAT) {
    const gl = this.gl;
    const [nz, ny, nx] = arr.shape;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_3D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, type === gl.FLOAT ? 4 : 1);
    gl.texImage3D(gl.TEXTURE_3D, 0, internal, nx, ny, nz, 0, format, type, data);
    gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, filter);
    gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, filter);
    for (const w of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T, gl.TEXTURE_WRAP_R]) {
      gl.texParameteri(gl.TEXTURE_3D, w, gl.CLAMP_TO_EDGE);
    }
    return t;
  }

  /** The L_ms textures of a field in a light (mixOf's): { rad, sunRad0, ... }, RGB16F. */
  makeRadiance(field, m) {
    const gl = this.gl;
    const grid = (ms) => (ms.empty ? { shape: [1, 1, 1] } : field.arrays.radiance_ms);
    const make = (ms) => this.makeTexture(grid(ms), gl.RGB16F, gl.RGB, ms.data, gl.LINEAR, gl.FLOAT);
    return Object.fromEntries([["rad", make(m.ms)], ...m.sunMs.map((ms, k) => [`sunRad${k}`, make(ms)])]);
  }

  /** The moving camera's textures of a field in a light (packedField's): { packed, sunT }. */
  makeMoving(field, m) {
    const phase = movingPhase(field);
    const data = packedField(field, m, { phase });
    const sunT = phase ? this.makePacked(field.arrays.sigma_t, data.sunT, texelChannels(field.suns.length)) : null;
    return { packed: this.makePacked(field.arrays.sigma_t, data.packed), sunT };
  }

  /** The moving camera's RGBA16F (sigma_t, L_in) texture, or its suns' transmittance (16F, a
   * channel a sun, RGB padded: mipmaps need a format it can render to), with mipmaps where the
   * device can. */
  makePacked(arr, data, channels = 4) {
    const gl = this.gl;
    const [nz, ny, nx] = arr.shape;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_3D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    const [internal, format] = TAU_FORMATS[channels - 1];
    gl.texImage3D(gl.TEXTURE_3D, 0, gl[internal], nx, ny, nz, 0, gl[format], gl.FLOAT, data);
    // Mipmaps (where the device can render to half floats): long steps read a prefiltered
    // field instead of skipping over thin features.
    let mips = false;
    if (gl.getExtension("EXT_color_buffer_float") || gl.getExtension("EXT_color_buffer_half_float")) {
      gl.generateMipmap(gl.TEXTURE_3D);
      mips = gl.getError() === gl.NO_ERROR;
    }
    // (nearest mip: SwiftShader samples LINEAR_MIPMAP_LINEAR at a third of the speed)
    gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, mips ? gl.LINEAR_MIPMAP_NEAREST : gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    for (const w of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T, gl.TEXTURE_WRAP_R]) {
      gl.texParameteri(gl.TEXTURE_3D, w, gl.CLAMP_TO_EDGE);
    }
    return t;
  }

  /**
   * Uploads a decoded field (field.js) and makes it the one drawn; the previous field's
   * textures are freed only once the new ones exist, so a failed upload keeps the old view.
   */
  setField(field) {
    const gl = this.gl;
    const { sigma_t, radiance_ms, majorant } = field.arrays;
    const make = (arr, internal, format, data, filter, type) => this.makeTexture(arr, internal, format, data, filter, type);
    const m = mixOf(field, this.mix);
    const taus = field.suns.map((s) => field.arrays[s.tau]);
    // a channel per sun, at the tau grid's resolution (the field's or twice it: field.js)
    const tauTexture = (group) => {
      if (!group.length) return null;
      const [internal, format] = TAU_FORMATS[group.length - 1];
      const texels = group.map((t) => depthTexels(t, field.tauPower));
      const data = texels.length > 1 ? interleaved(texels) : texels[0];
      return make(group[0], gl[internal], gl[format], data, gl.LINEAR, gl.FLOAT);
    };
    const shaped = shapedSuns(field);
    const layout = { suns: field.suns.length, shaped, env: !!m.env, sunMs: !!field.msLight };
    const phase = movingPhase(field);
    const programs = {
      exact: this.program({ packed: false, ...layout }),
      // an anisotropic field of more suns than the moving textures hold moves with the exact march
      fast: phaseLobes(field.header.phase) && field.suns.length > MOVING_PHASE_SUNS ? null : this.program({ packed: true, ...layout, shaped: [], phase }),
    };
    const textures = {
      dens: make(sigma_t, gl.R16F, gl.RED, halfFloats(sigma_t.data), gl.LINEAR, gl.FLOAT),
      tauA: tauTexture(taus.slice(0, 4)),
      tauB: tauTexture(taus.slice(4)),
      ...this.makeRadiance(field, m),
      maj: make(majorant, gl.R16F, gl.RED, majorant.data, gl.NEAREST),
      ...this.makeMoving(field, m),
      env: m.env ? this.makeBackground(m.env) : null,
    };
    // a shaped sun's view terms summed toward the camera, made when it moves (draw)
    const views = shaped.map((k) => viewGrid(field.arrays[field.suns[k].shape.array], field.unitToWorld));
    shaped.forEach((k, j) => {
      textures[`view${k}`] = make(field.arrays[field.suns[k].shape.array], gl.R16F, gl.RED, new Float32Array(views[j].points.length / 3), gl.LINEAR, gl.FLOAT);
    });
    const err = gl.getError();
    if (err !== gl.NO_ERROR && !gl.isContextLost()) {
      Object.values(textures).forEach((t) => t && gl.deleteTexture(t));
      throw new Error(`the field could not be uploaded to the GPU (WebGL error 0x${err.toString(16)})`);
    }
    if (this.textures) Object.values(this.textures).forEach((t) => t && gl.deleteTexture(t));
    this.textures = textures;
    // a v1.1 field's arrays stay for re-mixes (setMix); a v1 field's can be collected
    this.unitField = field.unit ? field : null;
    const [nz, ny, nx] = sigma_t.shape;
    const [bz, by, bx] = majorant.shape;
    const B = majorant.block;
    const toLight = field.suns.map((s) => normalize(s.direction.map((c) => -c)));
    // Keep the numbers the shader needs, not the arrays: the body can be garbage collected.
    this.field = {
      programs,
      suns: field.suns.length,
      worldToUnit: field.worldToUnit,
      step: field.step,
      maxDtau: field.maxDtau,
      edge: field.edge,
      lightUnit: field.suns.map((s) => towardLight(field.worldToUnit, s.direction)),
      sigmaScale: Number(sigma_t.scale),
      tauPower: field.tauPower,
      // L_ms = texel * uRadScale * exp(-min(uMsPower tau_light of sun 1, uMsRange)); power 0: 1
      msPower: field.msLight ? field.msLight.power : [0, 0, 0],
      msRange: field.msLight ? field.msLight.range : 0,
      majScale: Number(majorant.scale),
      ...m.uniforms,
      albedo: field.albedo,
      blockCells: [nx / B, ny / B, nz / B],
      blocks: [bx, by, bz],
      grid: [nx, ny, nz],
      radianceGrid: radiance_ms.shape.slice(0, 3).reverse(),
      textureBytes: GLView.textureBytes(field),
      radianceKey: field.header.radiance_key,
      phase: phaseLobes(field.header.phase),
      forward: field.forward,
      // per shaped sun: its view terms (as floats: viewGrid), frame, the grey power of the light
      // factor they are kept over and its texture's shape; viewEye: the eye they were last
      // summed toward
      shapes: shaped.map((k, j) => ({
        sun: k,
        grid: views[j],
        frame: field.suns[k].shape.frame,
        lightPower: field.suns[k].shape.lightPower,
        shape: field.arrays[field.suns[k].shape.array].shape.slice(0, 3),
      })),
      viewEye: null,
      toLight,
    };
    this.warmUp(field.worldBbox);
  }

  /** Draws a few pixels with each of the field's programs, off screen, through the medium's
   * box (``bbox``: [lo, hi], world) and past it: a driver that compiles a program, or its
   * texture reads, on first use (SwiftShader takes seconds) does so now, while the field
   * arrives, not on the first frames of a move. */
  warmUp(bbox) {
    const gl = this.gl;
    const [lo, hi] = bbox;
    const target = lo.map((v, i) => (v + hi[i]) / 2);
    const r = Math.hypot(...hi.map((v, i) => v - lo[i]));
    const cam = { eye: [target[0], target[1], target[2] - 2 * r], target, up: [0, 1, 0], fov: 40 };
    this.offscreen(4, 4, gl.RGBA8, () => {
      for (const fast of [false, true]) this.draw(cam, 4, 4, { fast, stepScale: fast ? 2 : 1 });
      gl.readPixels(0, 0, 4, 4, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(64));
    });
  }

  /** Runs ``fn`` with a width x height texture of ``format`` bound as the framebuffer, then
   * frees both. */
  offscreen(width, height, format, fn) {
    const gl = this.gl;
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, format, width, height);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    try {
      fn();
    } finally {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.deleteFramebuffer(fbo);
      gl.deleteTexture(tex);
    }
  }

  /**
   * Draws the field as seen by scene-spec camera ``cam`` into the current framebuffer at
   * width x height. exposure: stops; stepScale >= 1 lengthens the march step (while moving).
   */
  draw(cam, width, height, { exposure = 0, stepScale = 1, fast = false, seed = 0, offset = [0.5, 0.5], linear = false } = {}) {
    const gl = this.gl;
    const f = this.field;
    if (!f) return;
    // The moving camera's texture of an anisotropic field holds each sun's transmittance apart
    // (weighted by E p per ray) and L_ms without its view terms; beyond MOVING_PHASE_SUNS suns
    // every frame takes the exact march
    fast = fast && !!f.programs.fast;
    const { program, loc: L } = fast ? f.programs.fast : f.programs.exact;
    const { forward, right, up } = cameraBasis(cam);
    const tanX = Math.tan((cam.fov * Math.PI) / 360);
    // a uniform the shader optimised away has no location
    const set = (fn, name, ...v) => L[name] && gl[fn](L[name], ...v);
    gl.viewport(0, 0, width, height);
    gl.useProgram(program);
    set("uniform3fv", "uEye", cam.eye);
    set("uniform3fv", "uForward", forward);
    set("uniform3fv", "uRight", right);
    set("uniform3fv", "uUp", up);
    set("uniform2f", "uTan", tanX, (tanX * height) / width);
    set("uniform2f", "uSize", width, height);
    set("uniformMatrix4fv", "uWorldToUnit", true, f.worldToUnit);
    set("uniform1f", "uStep", f.step * stepScale);
    set("uniform1f", "uSigmaScale", f.sigmaScale);
    set("uniform1f", "uTauPower", f.tauPower);
    set("uniform3fv", "uRadScale", f.radScale);
    if (f.sunRadScale.length) set("uniform3fv", "uSunRadScale[0]", f.sunRadScale.flat());
    set("uniform3fv", "uMsPower", f.msPower);
    set("uniform1f", "uMsRange", f.msRange);
    set("uniform3fv", "uSky", f.background);
    set("uniform3fv", "uEnvScale", f.envScale);
    if (f.suns) {
      set("uniform3fv", "uDirect[0]", f.direct.flat());
      set("uniform3fv", "uToLight[0]", f.toLight.flat());
      set("uniform3fv", "uLightUnit[0]", f.lightUnit.flat());
    }
    set("uniform1i", "uAnisotropic", f.phase ? 1 : 0);
    set("uniform3fv", "uPhase", f.phase || [0, 0, 1]);
    set("uniform1i", "uBeamOrders", f.phase ? f.forward : 0);
    if (!fast) {
      for (const { sun, lightPower } of f.shapes) set("uniform1f", `uShapePower${sun}`, lightPower);
      this.sumViews(cam.eye);
    }
    set("uniform3fv", "uAlbedo", f.albedo);
    set("uniform1f", "uGain", 2 ** exposure);
    set("uniform3fv", "uBlockCells", f.blockCells);
    set("uniform3iv", "uBlocks", f.blocks);
    set("uniform1ui", "uSeed", seed);
    set("uniform2fv", "uPixelOffset", offset);
    set("uniform1i", "uLinearOut", linear ? 1 : 0);
    set("uniform1f", "uLod", Math.max(0, Math.log2(stepScale / 2)));
    set("uniform1f", "uMajScale", f.majScale);
    set("uniform1f", "uMaxDtau", f.maxDtau);
    set("uniform1f", "uEdge", f.edge);
    const t = this.textures;
    const units = [
      ["uDens", fast ? t.packed : t.dens],
      ["uRad", t.rad],
      ...(fast ? [] : f.sunRadScale.map((_, k) => [`uSunRad${k}`, t[`sunRad${k}`]])),
      ["uMaj", t.maj],
      ["uTauA", t.tauA],
      ["uSunT", t.sunT],
      ["uTauB", t.tauB],
      ...(fast ? [] : f.shapes.map(({ sun }) => [`uView${sun}`, t[`view${sun}`]])),
    ];
    let unit = 0;
    for (const [name, tex] of [...units, ["uEnv", t.env]]) {
      if (!L[name] || !tex) continue; // optimised away, or not this field's
      gl.activeTexture(gl.TEXTURE0 + unit);
      gl.bindTexture(name === "uEnv" ? gl.TEXTURE_2D : gl.TEXTURE_3D, tex);
      gl.uniform1i(L[name], unit++);
    }
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  /** The shaped suns' view terms summed toward a camera at ``eye`` (fieldtex.js viewSums) into
   * their textures, where the eye moved since they were last (the exact march reads them). */
  sumViews(eye) {
    const gl = this.gl;
    const f = this.field;
    if (!f.shapes.length || (f.viewEye && f.viewEye.every((v, i) => v === eye[i]))) return;
    for (const { sun, grid, frame, shape } of f.shapes) {
      const [nz, ny, nx] = shape;
      gl.bindTexture(gl.TEXTURE_3D, this.textures[`view${sun}`]);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
      gl.texSubImage3D(gl.TEXTURE_3D, 0, 0, 0, 0, nx, ny, nz, gl.RED, gl.FLOAT, viewSums(grid, frame, eye));
    }
    f.viewEye = eye.slice();
  }

  /** Draws onto the canvas, resizing its drawing buffer to width x height first. */
  drawToCanvas(cam, width, height, options) {
    if (this.canvas.width !== width || this.canvas.height !== height) {
      this.canvas.width = width;
      this.canvas.height = height;
    }
    this.gl.bindFramebuffer(this.gl.FRAMEBUFFER, null);
    this.draw(cam, width, height, options);
  }

  /**
   * The field seen by ``cam`` at its width x height with the exact march, as top-down sRGB
   * ImageData. ``samples`` = n^2 > 1 averages n x n stratified ray origins inside each pixel
   * (a box filter, as the server's multi-sample renders), in linear radiance where the device
   * can render to float textures.
   */
  readImage(cam, { exposure = 0, samples = 1, fast = false } = {}) {
    const gl = this.gl;
    const { width, height } = cam;
    const n = Math.max(1, Math.round(Math.sqrt(samples)));
    const float = n > 1 && !!gl.getExtension("EXT_color_buffer_float");
    const sum = new Float32Array(width * height * 4);
    this.offscreen(width, height, float ? gl.RGBA32F : gl.RGBA8, () => {
      for (let k = 0; k < n * n; k++) {
        const offset = n > 1 ? [((k % n) + 0.5) / n, (Math.floor(k / n) + 0.5) / n] : [0.5, 0.5];
        this.draw(cam, width, height, { exposure, fast, seed: k, offset, linear: float });
        if (float) {
          const px = new Float32Array(width * height * 4);
          gl.readPixels(0, 0, width, height, gl.RGBA, gl.FLOAT, px);
          for (let i = 0; i < px.length; i++) sum[i] += px[i];
        } else {
          const px = new Uint8Array(width * height * 4);
          gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, px);
          for (let i = 0; i < px.length; i++) sum[i] += srgbToLinear(px[i]);
        }
      }
    });
    // mean, clamped, to sRGB bytes, rows flipped to top-down
    const out = new ImageData(width, height);
    const inv = 1 / (n * n);
    for (let r = 0; r < height; r++) {
      for (let c = 0; c < width; c++) {
        const src = 4 * ((height - 1 - r) * width + c);
        const dst = 4 * (r * width + c);
        for (let ch = 0; ch < 3; ch++) {
          const x = Math.min(1, Math.max(0, sum[src + ch] * inv));
          out.data[dst + ch] = linearToSrgb8(x);
        }
        out.data[dst + 3] = 255;
      }
    }
    return out;
  }
}

/**
 * The field header's phase (api.md: absent for the isotropic phase) as the shader's lobes
 * [g1, g2, weight of the first], or null for the isotropic phase.
 */
export function phaseLobes(phase) {
  if (!phase || phase.type === "isotropic") return null;
  if (phase.type === "hg") return phase.g === 0 ? null : [phase.g, 0, 1];
  if (phase.type === "hg2") return [phase.g[0], phase.g[1], phase.weight];
  throw new Error(`the field's header has an unknown phase ${JSON.stringify(phase.type)}`);
}

/** Whether the moving camera's texture of a field holds its suns' transmittance apart: an
 * anisotropic phase's field of at most MOVING_PHASE_SUNS suns (fieldtex.js). */
function movingPhase(field) {
  return !!phaseLobes(field.header.phase) && field.suns.length > 0 && field.suns.length <= MOVING_PHASE_SUNS;
}

/** Whether a field has an environment map's background to draw. */
function hasEnv(field) {
  return field.components.some((c) => c.background);
}

/** The indices of a field's directional lights whose view terms it holds. */
function shapedSuns(field) {
  return field.suns.flatMap((s, k) => (s.shape ? [k] : []));
}

/** The direction toward the light (against ``direction``, which light travels) in the unit cube
 * of a row-major world-to-unit map, per world unit. */
function towardLight(w2u, direction) {
  const l = normalize(direction.map((c) => -c));
  return [0, 1, 2].map((r) => w2u[4 * r] * l[0] + w2u[4 * r + 1] * l[1] + w2u[4 * r + 2] * l[2]);
}
