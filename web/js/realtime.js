// The real-time viewport: the page draws the cache's radiance field itself (glview.js). While
// the camera moves it draws small, fast frames (quality.js holds the frame budget); once the
// camera rests it redraws at full size with the field's own step, in strips of about two
// frames' work each so that a slow GPU never stalls the next move; then, if asked, the server
// renders a `gather` final frame that is shown over it. Hooks on the viewport element:
// data-renderer="webgl", data-frames (frames drawn), data-internal (size of the last frame),
// data-state (moving, refining, rest).

import { isAbort } from "./api.js";
import { formatBytes, formatSeconds, setText } from "./dom.js";
import { fetchField } from "./field.js";
import { GLView } from "./glview.js";
import { QualityController } from "./quality.js";
import { renderImage } from "./render.js";

const REST_MS = 200;
const MAX_FULL = 1024;
const FINAL = { spp: 32, maxSize: 256 };
const EXACT_COST = 1.6; // the exact march (two fetches a step) against the moving one (one)

export class RealtimeView {
  /**
   * element: the viewport box; canvas: its <canvas>; img: its <img> (the final frame);
   * info: a text element; exposure(): stops; buildRequest(cameraSpec, spp, integrator) -> a
   * POST /v1/renders body; onLost(): the GPU dropped the context (the caller falls back).
   * Throws when WebGL2 is missing (the caller falls back).
   */
  constructor({ element, canvas, img, info, api, status, camera, exposure, buildRequest, onLost }) {
    Object.assign(this, { element, canvas, img, info, api, status, camera, exposure, buildRequest, onLost });
    this.gl = new GLView(canvas);
    this.quality = new QualityController(this.fullSize());
    this.active = false;
    this.fieldKey = null; // the scene key of the field drawn
    this.fieldInfo = null;
    this.loading = null; // { key, controller }
    this.frames = 0;
    this.raf = 0;
    this.restTimer = null;
    this.lastMove = -Infinity;
    this.lastDraw = null; // { at, cost } of the previous tick, if it drew
    this.drawnVersion = -1; // the camera version of the last moving frame
    this.refine = null; // { cam, size, y, fbo, tex, t0 } while the full-size frame is drawn
    this.restShown = null; // { t0, size } from its completion to the next frame
    this.finalWanted = false;
    this.finalReq = null;
    this.version = 0;
    this.fps = { count: 0, since: performance.now(), value: NaN };
    canvas.addEventListener("webglcontextlost", (e) => {
      e.preventDefault();
      this.lost = true;
      this.stop();
      this.status.error("the GPU dropped the real-time view (WebGL context lost); reload the page to draw it again");
      if (this.onLost) this.onLost();
    });
  }

  /** The viewport's size in device pixels (square). */
  fullSize() {
    const css = this.element.clientWidth || 256;
    return Math.max(64, Math.min(MAX_FULL, Math.round(css * (window.devicePixelRatio || 1))));
  }

  hasField() {
    return this.fieldKey != null;
  }

  /** The lights' intensities ({ sun, sky }) that a v1.1 field is drawn in; re-draws. */
  setMix(mix) {
    if (mix && JSON.stringify(mix) === JSON.stringify(this.gl.mix)) return;
    this.gl.setMix(mix);
    if (this.hasField()) this.redraw();
  }

  /** Shows or hides the real-time view (the server viewer takes over when hidden). */
  setActive(active) {
    this.active = active;
    this.canvas.hidden = !active;
    if (active) {
      this.element.dataset.renderer = "webgl";
      this.img.hidden = true;
      this.element.dataset.frames = String(this.frames);
      this.redraw();
    } else {
      this.stop();
    }
  }

  stop() {
    cancelAnimationFrame(this.raf);
    this.raf = 0;
    clearTimeout(this.restTimer);
    this.endRefine();
    this.cancelFinal();
  }

  /**
   * Loads the field of cache ``cacheId`` for scene key ``key`` (keeps drawing the old one
   * meanwhile). Resolves with the seconds it took, or rejects (FieldError, ApiError, or an
   * Error saying the field is too large for this device).
   */
  async load(cacheId, key) {
    if (this.loading) {
      if (this.loading.key === key) return this.loading.promise;
      this.loading.controller.abort();
    }
    const controller = new AbortController();
    const t0 = performance.now();
    const run = { key, controller };
    run.promise = (async () => {
      const field = await fetchField(this.api, cacheId, { signal: controller.signal });
      if (this.loading !== run) throw new DOMException("superseded", "AbortError");
      const tooLarge = this.gl.tooLarge(field);
      if (tooLarge) throw new Error(`the real-time view cannot show this cache: ${tooLarge}`);
      this.gl.setField(field);
      this.fieldKey = key;
      const [nx, ny, nz] = this.gl.field.grid;
      this.fieldInfo = `field ${nx}×${ny}×${nz} · ${formatBytes(field.bytes)} · GPU ${formatBytes(this.gl.field.textureBytes)}`;
      this.element.dataset.fieldKey = this.gl.field.radianceKey || "";
      this.element.dataset.textureBytes = String(this.gl.field.textureBytes);
      this.redraw();
      return (performance.now() - t0) / 1000;
    })();
    this.loading = run;
    try {
      return await run.promise;
    } finally {
      if (this.loading === run) this.loading = null;
    }
  }

  /** The camera moved: fast frames follow it, refinement and the final frame stop. */
  cameraMoved() {
    this.lastMove = performance.now();
    this.redraw();
  }

  /** Exposure or the field changed: the resting view is drawn again. */
  redraw() {
    this.restShown = null;
    this.endRefine();
    this.cancelFinal();
    this.img.hidden = true;
    delete this.element.dataset.final;
    this.version++;
    this.schedule();
  }

  setFinalWanted(on) {
    this.finalWanted = on;
    if (!on) {
      this.cancelFinal();
      this.img.hidden = true;
      delete this.element.dataset.final;
    } else if (this.element.dataset.state === "rest") {
      this.requestFinal();
    }
  }

  schedule() {
    if (!this.active || this.raf || this.lost) return;
    this.raf = requestAnimationFrame((t) => this.tick(t));
  }

  tick(now) {
    this.raf = 0;
    // The time since the last tick that drew is what that frame cost (the browser holds
    // animation frames back while the GPU is busy).
    if (this.lastDraw) this.quality.report(now - this.lastDraw.at, this.lastDraw.cost);
    this.lastDraw = null;
    if (!this.active || !this.gl.field) return;
    if (this.restShown) {
      // the full-size frame has been drawn and presented: the view is at rest
      const { t0, size } = this.restShown;
      this.restShown = null;
      this.element.dataset.restMs = String(Math.round(now - t0));
      this.frameDrawn(size, 1, "rest");
      if (this.finalWanted) this.requestFinal();
      return;
    }
    if (now - this.lastMove < REST_MS) {
      if (this.drawnVersion === this.version) {
        this.restSoon(); // nothing new to draw: wait for the next move, or for the rest
        return;
      }
      const level = this.quality.current();
      const spec = { ...this.camera.spec(1, 1), width: level.size, height: level.size };
      this.gl.drawToCanvas(spec, level.size, level.size, {
        exposure: this.exposure(),
        stepScale: level.stepScale,
        fast: true,
      });
      this.drawnVersion = this.version;
      this.lastDraw = { at: now, cost: level.cost };
      this.frameDrawn(level.size, level.stepScale, "moving");
      this.schedule();
      return;
    }
    if (!this.refine) {
      if (this.element.dataset.state === "rest" && this.restVersion === this.version) return;
      this.startRefine(this.camera.spec(1, 1));
    }
    this.stepRefine(now);
  }

  restSoon() {
    clearTimeout(this.restTimer);
    this.restTimer = setTimeout(() => this.schedule(), REST_MS + 5);
  }

  frameDrawn(size, stepScale, state) {
    this.frames++;
    this.fps.count++;
    const now = performance.now();
    if (now - this.fps.since > 500) {
      this.fps.value = (1000 * this.fps.count) / (now - this.fps.since);
      this.fps = { count: 0, since: now, value: this.fps.value };
    }
    Object.assign(this.element.dataset, {
      frames: String(this.frames),
      internal: String(size),
      stepScale: String(stepScale),
      state,
    });
    // while moving, the text only when the frame rate is recounted (a text change costs a
    // layout and a repaint of its own, every frame)
    if (state === "moving" && this.info.dataset.state === "moving" && this.fps.since !== now) return;
    this.info.dataset.state = state;
    const fps = state === "moving" && Number.isFinite(this.fps.value) ? ` · ${this.fps.value.toFixed(0)} fps` : "";
    const step = stepScale !== 1 ? ` · step ×${stepScale}` : "";
    const took = state === "rest" ? ` in ${formatSeconds(Number(this.element.dataset.restMs) / 1000)}` : "";
    setText(this.info, `WebGL2 · ${size}×${size} px${step}${fps} · ${state}${took} · ${this.fieldInfo || ""}`);
  }

  // --- refinement at rest: the full-size image in strips, shown when complete ---

  startRefine(cam) {
    const gl = this.gl.gl;
    const size = this.fullSize();
    if (size !== this.quality.levels[0].size) this.quality.resize(size);
    const tex = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, tex);
    gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, size, size);
    const fbo = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.refine = { cam: { ...cam, width: size, height: size }, size, y: 0, fbo, tex, t0: performance.now() };
    this.element.dataset.state = "refining";
  }

  stepRefine(now) {
    const r = this.refine;
    const gl = this.gl.gl;
    // one strip a frame, as many rows as the budget holds, but at most 8 strips: where a frame
    // costs mostly its fixed overhead (a software renderer), tiny strips would add up to seconds
    const rows = Math.min(r.size - r.y, Math.max(Math.ceil(r.size / 8), this.quality.rowsFor(r.size, EXACT_COST)));
    this.lastDraw = { at: now, cost: (rows * r.size * EXACT_COST) };
    gl.bindFramebuffer(gl.FRAMEBUFFER, r.fbo);
    gl.enable(gl.SCISSOR_TEST);
    gl.scissor(0, r.size - r.y - rows, r.size, rows); // strips from the top
    this.gl.draw(r.cam, r.size, r.size, { exposure: this.exposure(), stepScale: 1 });
    gl.disable(gl.SCISSOR_TEST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    r.y += rows;
    if (r.y < r.size) {
      setText(this.info, `WebGL2 · refining ${r.size}×${r.size} px · ${Math.round((100 * r.y) / r.size)} % · ${this.fieldInfo || ""}`);
      this.schedule();
      return;
    }
    // complete: copy to the canvas in one go
    if (this.canvas.width !== r.size || this.canvas.height !== r.size) {
      this.canvas.width = r.size;
      this.canvas.height = r.size;
    }
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, r.fbo);
    gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
    gl.blitFramebuffer(0, 0, r.size, r.size, 0, 0, r.size, r.size, gl.COLOR_BUFFER_BIT, gl.NEAREST);
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
    this.endRefine();
    this.restVersion = this.version;
    this.restShown = { t0: r.t0, size: r.size }; // "rest" once the next frame begins
    this.schedule();
  }

  endRefine() {
    const r = this.refine;
    if (!r) return;
    const gl = this.gl.gl;
    gl.deleteFramebuffer(r.fbo);
    gl.deleteTexture(r.tex);
    this.refine = null;
  }

  // --- the server's final frame (gather) at rest ---

  cancelFinal() {
    if (this.finalReq) {
      this.finalReq.controller.abort();
      this.finalReq = null;
      delete this.element.dataset.busy;
    }
  }

  async requestFinal() {
    this.cancelFinal();
    const size = Math.min(FINAL.maxSize, this.fullSize());
    let body;
    try {
      body = this.buildRequest(this.camera.spec(size, size), FINAL.spp, "graph");
    } catch (err) {
      this.status.error(err, "Final render");
      return;
    }
    body.estimator = "gather";
    const req = { controller: new AbortController(), version: this.version };
    this.finalReq = req;
    this.element.dataset.busy = "1";
    try {
      const r = await renderImage(this.api, body, { signal: req.controller.signal });
      const url = URL.createObjectURL(r.blob);
      try {
        const probe = new Image();
        probe.src = url;
        await probe.decode();
      } catch {
        URL.revokeObjectURL(url);
        throw new Error("the server's answer is not an image that the browser can show");
      }
      if (this.finalReq !== req) {
        URL.revokeObjectURL(url);
        return;
      }
      if (this.finalUrl) URL.revokeObjectURL(this.finalUrl);
      this.finalUrl = url;
      this.img.src = url;
      this.img.hidden = false;
      this.element.dataset.final = "1";
      setText(
        this.info,
        `final: server gather ${size}×${size} px · ${FINAL.spp} spp · render ${formatSeconds(r.renderSeconds)} · ${this.fieldInfo || ""}`,
      );
    } catch (err) {
      if (isAbort(err) || this.finalReq !== req) return;
      this.status.error(err, "Final render");
    } finally {
      if (this.finalReq === req) {
        this.finalReq = null;
        delete this.element.dataset.busy;
      }
    }
  }

  /** The real-time view of the scene camera at width x height, full quality, as ImageData;
   * ``samples`` > 1 averages ray origins over each pixel (as a multi-sample server render). */
  snapshot(width, height, samples = 1) {
    return this.gl.readImage(this.camera.spec(width, height), { exposure: this.exposure(), samples });
  }
}
