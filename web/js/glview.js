// The WebGL2 renderer of a radiance field: 3D textures on the GPU, one draw per frame, and a
// read-back of an image at a given size for comparisons. Knows nothing of the DOM around it.

import { fragmentShader, VERTEX } from "./shaders.js";
import { channelGroup, interleaved, packedField } from "./fieldtex.js";
import { SHAPE_TERMS } from "./field.js";
import { linearToSrgb8, srgbToLinear } from "./imagemath.js";
import { cross, normalize, sub } from "./camera.js";

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

/** A v1.1 field's sky radiance array beside a sun's radiance_ms, or null. */
function skyArray(field) {
  const l = field.lights;
  return l && l.sun && l.sky ? field.arrays[l.sky] : null;
}

/**
 * A field in a light: the shader's uniforms { direct (E / 4pi), radScale (radiance_ms's scale
 * times its component's intensity), skyRadScale, background (the sky behind the medium) } and
 * packedField's mix. A v1 field is in its own light; a v1.1 one (unit components) in ``mix``
 * ({ sun, sky }: RGB intensities; none given: 1 and 0).
 */
function mixOf(field, mix) {
  const scale = field.arrays.radiance_ms.scale;
  const l = field.lights;
  if (!l) {
    const direct = field.light.irradiance.map((e) => e / (4 * Math.PI));
    const uniforms = { direct, radScale: scale, skyRadScale: [0, 0, 0], background: [0, 0, 0] };
    return { uniforms, packed: { direct, radScale: scale, sky: null } };
  }
  const sun = l.sun ? (mix && mix.sun) || [1, 1, 1] : [0, 0, 0];
  const skyE = l.sky ? (mix && mix.sky) || [0, 0, 0] : [0, 0, 0];
  const first = l.sun ? sun : skyE; // the first component's intensity (radiance_ms)
  const sky = skyArray(field);
  const uniforms = {
    direct: sun.map((e) => e / (4 * Math.PI)),
    radScale: scale.map((s, c) => s * first[c]),
    skyRadScale: sky ? sky.scale.map((s, c) => s * skyE[c]) : [0, 0, 0],
    background: skyE,
  };
  const packed = { direct: uniforms.direct, radScale: uniforms.radScale, sky: sky && { data: sky.data, scale: uniforms.skyRadScale } };
  return { uniforms, packed };
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
    this.programs = { exact: this.link(false), fast: this.link(true) };
    this.vao = gl.createVertexArray();
    this.textures = null;
    this.field = null;
    this.mix = null; // the lights' intensities for a v1.1 field (setMix)
    this.maxSize = gl.getParameter(gl.MAX_3D_TEXTURE_SIZE);
  }

  /** The ray-march program and its uniform locations. */
  link(packed) {
    const gl = this.gl;
    const program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, fragmentShader({ packed })));
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
    const bytes = GLView.textureBytes(field);
    if (bytes > maxBytes) return `the field needs ${(bytes / 2 ** 20).toFixed(0)} MiB of textures`;
    return "";
  }

  /**
   * GPU bytes of a field's textures: RG16F density + tau, RGBA16F-padded radiance, R16F
   * majorant, and the RGBA16F (sigma_t, L_in) texture of the moving camera with its mipmaps.
   */
  static textureBytes(field) {
    const count = (a) => a.shape[0] * a.shape[1] * a.shape[2];
    const { sigma_t, radiance_ms, majorant } = field.arrays;
    const skies = skyArray(field) ? 2 : 1; // a v1.1 field's sky: a second radiance texture
    // an anisotropic phase's view terms: RGBA16F textures of four channels each
    const shape = field.shape ? 8 * Math.ceil(SHAPE_TERMS / 4) * count(field.arrays[field.shape.array]) : 0;
    return Math.round((4 + (8 * 8) / 7) * count(sigma_t) + 8 * skies * count(radiance_ms) + 2 * count(majorant) + shape);
  }

  /**
   * The lights' intensities for a v1.1 field (held at unit intensity): { sun: [3] irradiance,
   * sky: [3] radiance }. Re-draws need no request: uniforms, and the moving camera's texture
   * made again. A v1 field keeps its own light.
   */
  setMix(mix) {
    this.mix = mix;
    if (!this.unitField || !this.textures) return;
    const m = mixOf(this.unitField, mix);
    Object.assign(this.field, m.uniforms);
    const packed = this.makePacked(this.unitField.arrays.sigma_t, packedField(this.unitField, m.packed));
    this.gl.deleteTexture(this.textures.packed);
    this.textures.packed = packed;
  }

  /** The moving camera's RGBA16F (sigma_t, L_in) texture, with mipmaps where the device can. */
  makePacked(arr, data) {
    const gl = this.gl;
    const [nz, ny, nx] = arr.shape;
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_3D, t);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 4);
    gl.texImage3D(gl.TEXTURE_3D, 0, gl.RGBA16F, nx, ny, nz, 0, gl.RGBA, gl.FLOAT, data);
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
    const { sigma_t, tau_light, radiance_ms, majorant } = field.arrays;
    const make = (arr, internal, format, data, filter) => {
      const [nz, ny, nx] = arr.shape;
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_3D, t);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
      gl.texImage3D(gl.TEXTURE_3D, 0, internal, nx, ny, nz, 0, format, gl.HALF_FLOAT, data);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MIN_FILTER, filter);
      gl.texParameteri(gl.TEXTURE_3D, gl.TEXTURE_MAG_FILTER, filter);
      for (const w of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T, gl.TEXTURE_WRAP_R]) {
        gl.texParameteri(gl.TEXTURE_3D, w, gl.CLAMP_TO_EDGE);
      }
      return t;
    };
    const m = mixOf(field, this.mix);
    const sky = skyArray(field);
    const shape = field.shape ? field.arrays[field.shape.array] : null;
    const groups = shape ? Array.from({ length: Math.ceil(SHAPE_TERMS / 4) }, (_, g) => 4 * g) : [];
    const textures = {
      ...Object.fromEntries(
        groups.map((from) => [`shape${from / 4}`, make(shape, gl.RGBA16F, gl.RGBA, channelGroup(shape.data, SHAPE_TERMS, from), gl.LINEAR)]),
      ),
      densTau: make(sigma_t, gl.RG16F, gl.RG, interleaved(sigma_t.data, tau_light.data), gl.LINEAR),
      rad: make(radiance_ms, gl.RGB16F, gl.RGB, radiance_ms.data, gl.LINEAR),
      sky: sky ? make(sky, gl.RGB16F, gl.RGB, sky.data, gl.LINEAR) : null,
      maj: make(majorant, gl.R16F, gl.RED, majorant.data, gl.NEAREST),
      packed: this.makePacked(sigma_t, packedField(field, m.packed)),
    };
    const err = gl.getError();
    if (err !== gl.NO_ERROR && !gl.isContextLost()) {
      Object.values(textures).forEach((t) => t && gl.deleteTexture(t));
      throw new Error(`the field could not be uploaded to the GPU (WebGL error 0x${err.toString(16)})`);
    }
    if (this.textures) Object.values(this.textures).forEach((t) => t && gl.deleteTexture(t));
    this.textures = textures;
    // a v1.1 field's arrays stay for re-mixes (setMix); a v1 field's can be collected
    this.unitField = field.lights ? field : null;
    const [nz, ny, nx] = sigma_t.shape;
    const [bz, by, bx] = majorant.shape;
    const B = majorant.block;
    // Keep the numbers the shader needs, not the arrays: the body can be garbage collected.
    this.field = {
      worldToUnit: field.worldToUnit,
      step: field.step,
      maxDtau: field.maxDtau,
      edge: field.edge,
      lightUnit: towardLight(field.worldToUnit, field.light.direction),
      sigmaScale: Number(sigma_t.scale),
      tauScale: Number(tau_light.scale),
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
      // the view terms' scales, four a texture (zero past the last), and their frame
      shapeScale: shape ? groups.flatMap((from) => [0, 1, 2, 3].map((c) => (from + c < SHAPE_TERMS ? shape.scale[from + c] : 0))) : null,
      shapeFrame: field.shape ? field.shape.frame : null,
      toLight: normalize(field.light.direction.map((c) => -c)),
    };
  }

  /**
   * Draws the field as seen by scene-spec camera ``cam`` into the current framebuffer at
   * width x height. exposure: stops; stepScale >= 1 lengthens the march step (while moving).
   */
  draw(cam, width, height, { exposure = 0, stepScale = 1, fast = false, seed = 0, offset = [0.5, 0.5], linear = false } = {}) {
    const gl = this.gl;
    const f = this.field;
    if (!f) return;
    // The moving camera's texture holds isotropic single scattering (fieldtex.js): with a
    // Henyey-Greenstein phase every frame takes the exact march, whose phase factor is per ray
    fast = fast && !f.phase;
    const { program, loc: L } = fast ? this.programs.fast : this.programs.exact;
    const { forward, right, up } = cameraBasis(cam);
    const tanX = Math.tan((cam.fov * Math.PI) / 360);
    gl.viewport(0, 0, width, height);
    gl.useProgram(program);
    gl.uniform3fv(L.uEye, cam.eye);
    gl.uniform3fv(L.uForward, forward);
    gl.uniform3fv(L.uRight, right);
    gl.uniform3fv(L.uUp, up);
    gl.uniform2f(L.uTan, tanX, (tanX * height) / width);
    gl.uniform2f(L.uSize, width, height);
    gl.uniformMatrix4fv(L.uWorldToUnit, true, f.worldToUnit);
    gl.uniform1f(L.uStep, f.step * stepScale);
    gl.uniform1f(L.uSigmaScale, f.sigmaScale);
    gl.uniform1f(L.uTauScale, f.tauScale);
    gl.uniform3fv(L.uRadScale, f.radScale);
    gl.uniform3fv(L.uDirect, f.direct);
    if (L.uSkyRadScale) gl.uniform3fv(L.uSkyRadScale, f.skyRadScale);
    if (L.uHasSky) gl.uniform1i(L.uHasSky, this.textures.sky ? 1 : 0);
    if (L.uSky) gl.uniform3fv(L.uSky, f.background);
    if (L.uAnisotropic) gl.uniform1i(L.uAnisotropic, f.phase ? 1 : 0);
    if (L.uPhase) gl.uniform3fv(L.uPhase, f.phase || [0, 0, 1]);
    if (L.uToLight) gl.uniform3fv(L.uToLight, f.toLight);
    if (L.uHasShape) gl.uniform1i(L.uHasShape, f.shapeScale ? 1 : 0);
    if (f.shapeScale && L["uShapeScale[0]"]) {
      gl.uniform4fv(L["uShapeScale[0]"], f.shapeScale);
      gl.uniformMatrix3fv(L.uShapeFrame, true, f.shapeFrame);
    }
    gl.uniform3fv(L.uAlbedo, f.albedo);
    gl.uniform1f(L.uGain, 2 ** exposure);
    gl.uniform3fv(L.uBlockCells, f.blockCells);
    gl.uniform3iv(L.uBlocks, f.blocks);
    gl.uniform1ui(L.uSeed, seed);
    gl.uniform2fv(L.uPixelOffset, offset);
    gl.uniform1i(L.uLinearOut, linear ? 1 : 0);
    gl.uniform1f(L.uLod, Math.max(0, Math.log2(stepScale / 2)));
    gl.uniform1f(L.uMajScale, f.majScale);
    gl.uniform1f(L.uMaxDtau, f.maxDtau);
    gl.uniform3fv(L.uLightUnit, f.lightUnit);
    gl.uniform1f(L.uEdge, f.edge);
    const units = [
      ["uDensTau", fast ? this.textures.packed : this.textures.densTau],
      ["uRad", this.textures.rad],
      ["uMaj", this.textures.maj],
      ["uRadSky", this.textures.sky || this.textures.rad],
      ...[0, 1, 2, 3].map((g) => [`uShape${g}`, this.textures[`shape${g}`] || this.textures.rad]),
    ];
    units.forEach(([name, tex], i) => {
      if (!L[name]) return; // optimised away
      gl.activeTexture(gl.TEXTURE0 + i);
      gl.bindTexture(gl.TEXTURE_3D, tex);
      gl.uniform1i(L[name], i);
    });
    gl.bindVertexArray(this.vao);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
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
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, float ? gl.RGBA32F : gl.RGBA8, width, height);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    const sum = new Float32Array(width * height * 4);
    try {
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
    } finally {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.deleteFramebuffer(fbo);
      gl.deleteTexture(tex);
    }
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

/** The direction toward the light (against ``direction``, which light travels) in the unit cube
 * of a row-major world-to-unit map, per world unit. */
function towardLight(w2u, direction) {
  const l = normalize(direction.map((c) => -c));
  return [0, 1, 2].map((r) => w2u[4 * r] * l[0] + w2u[4 * r + 1] * l[1] + w2u[4 * r + 2] * l[2]);
}
