// The viewport: shows renders of the current camera, progressively. While the camera moves it
// keeps one small, fast render in flight (a newer camera waits for it, so the queue never
// fills); once the camera has rested it refines: a larger render, then passes at full size
// with new seeds, averaged here, so that no single request is long. A request that the camera
// or the scene outdates is aborted at once.

import { isAbort } from "./api.js";
import { formatSeconds, setText } from "./dom.js";
import { imageDataOf, linearToSrgb8, srgbToLinear } from "./imagemath.js";
import { renderImage } from "./render.js";

export const LEVELS = {
  graph: [
    { size: 64, spp: 4, label: "preview" },
    { size: 128, spp: 8, label: "refining" },
    { size: 256, spp: 8, passes: 4, label: "final" },
  ],
  volpath: [
    { size: 64, spp: 2, label: "preview" },
    { size: 128, spp: 4, label: "refining" },
    { size: 256, spp: 4, passes: 4, label: "final" },
  ],
};
const REST_MS = 250;

/** A running mean of images, in linear values; toBlob() gives the mean as a PNG. */
class Accumulator {
  reset(width, height) {
    this.width = width;
    this.height = height;
    this.sum = new Float32Array(width * height * 3);
    this.count = 0;
  }

  add(imageData) {
    const d = imageData.data;
    for (let p = 0, q = 0; p < d.length; p += 4, q += 3) {
      this.sum[q] += srgbToLinear(d[p]);
      this.sum[q + 1] += srgbToLinear(d[p + 1]);
      this.sum[q + 2] += srgbToLinear(d[p + 2]);
    }
    this.count++;
  }

  toBlob() {
    const out = new ImageData(this.width, this.height);
    const inv = 1 / this.count;
    for (let p = 0, q = 0; q < this.sum.length; p += 4, q += 3) {
      out.data[p] = linearToSrgb8(this.sum[q] * inv);
      out.data[p + 1] = linearToSrgb8(this.sum[q + 1] * inv);
      out.data[p + 2] = linearToSrgb8(this.sum[q + 2] * inv);
      out.data[p + 3] = 255;
    }
    const canvas = document.createElement("canvas");
    canvas.width = this.width;
    canvas.height = this.height;
    canvas.getContext("2d").putImageData(out, 0, 0);
    return new Promise((resolve, reject) =>
      canvas.toBlob((b) => (b ? resolve(b) : reject(new Error("the averaged image could not be encoded"))), "image/png"),
    );
  }
}

export class Viewer {
  /**
   * element: the viewport box; img: its <img>; overlay, info: text elements;
   * buildRequest(cameraSpec, spp, integrator, seed) -> a POST /v1/renders body (throws when
   * the scene panel holds something invalid).
   */
  constructor({ element, img, overlay, info, api, status, camera, buildRequest }) {
    Object.assign(this, { element, img, overlay, info, api, status, camera, buildRequest });
    this.integrator = "graph";
    this.enabled = false;
    this.version = 0; // bumped by every camera or scene change
    this.shown = { version: -1, level: -1, pass: 0, final: false };
    this.inflight = null;
    this.failed = -1; // the version whose render failed: not retried until something changes
    this.lastMove = 0;
    this.restTimer = null;
    this.url = null;
    this.frames = 0;
    this.acc = new Accumulator();
  }

  /** Turns rendering on, or off with a reason shown over the viewport (then sceneChanged()). */
  setEnabled(enabled, reason = "") {
    setText(this.overlay, enabled ? "" : reason);
    this.overlay.hidden = enabled;
    if (enabled === this.enabled) return;
    this.enabled = enabled;
    this.element.dataset.enabled = enabled ? "1" : "0";
    if (!enabled) this.abort();
  }

  /** Something other than the camera changed (volume, medium, light, exposure, integrator). */
  sceneChanged() {
    this.version++;
    this.abort();
    this.next();
  }

  /** The camera moved: outdated refinements stop, a fast render follows the camera. */
  cameraMoved() {
    this.version++;
    this.lastMove = performance.now();
    if (this.inflight && this.inflight.level > 0) this.abort();
    this.next();
  }

  abort() {
    clearTimeout(this.restTimer);
    if (this.inflight) {
      this.inflight.controller.abort();
      this.inflight = null;
      delete this.element.dataset.busy;
    }
  }

  next() {
    clearTimeout(this.restTimer);
    if (!this.enabled || this.inflight || this.failed === this.version) return;
    const levels = LEVELS[this.integrator];
    const s = this.shown;
    if (s.version !== this.version) {
      this.start(0, 0);
      return;
    }
    if (s.final) return;
    const wait = this.lastMove + REST_MS - performance.now();
    if (wait > 0) {
      this.restTimer = setTimeout(() => this.next(), wait + 5);
      return;
    }
    if (s.level < levels.length - 1) this.start(s.level + 1, 0);
    else this.start(s.level, s.pass + 1);
  }

  async start(level, pass) {
    const step = LEVELS[this.integrator][level];
    const version = this.version;
    const integrator = this.integrator;
    const req = { level, pass, version, controller: new AbortController() };
    let body;
    try {
      body = this.buildRequest(this.camera.spec(step.size, step.size), step.spp, integrator, pass);
    } catch (err) {
      this.failed = version;
      this.status.error(err, "Viewport");
      return;
    }
    this.inflight = req;
    this.element.dataset.busy = "1";
    try {
      const r = await renderImage(this.api, body, { signal: req.controller.signal });
      if (this.inflight !== req) return;
      await this.show(r, req, step, integrator);
    } catch (err) {
      if (isAbort(err) || this.inflight !== req) return;
      this.failed = version;
      this.status.error(err, "Viewport");
    } finally {
      if (this.inflight === req) {
        this.inflight = null;
        delete this.element.dataset.busy;
        this.next();
      }
    }
  }

  async show(r, req, step, integrator) {
    const passes = step.passes || 1;
    let blob = r.blob;
    if (passes > 1) {
      let pixels;
      try {
        pixels = await imageDataOf(r.blob);
      } catch {
        throw new Error("the server's answer is not an image that the browser can show");
      }
      if (this.inflight !== req) return;
      if (req.pass === 0) this.acc.reset(pixels.width, pixels.height);
      this.acc.add(pixels);
      blob = await this.acc.toBlob();
    }
    const url = URL.createObjectURL(blob);
    const probe = new Image();
    probe.src = url;
    try {
      await probe.decode();
    } catch {
      URL.revokeObjectURL(url);
      throw new Error("the server's answer is not an image that the browser can show");
    }
    if (this.inflight !== req) {
      URL.revokeObjectURL(url); // outdated while it decoded
      return;
    }
    const old = this.url;
    this.img.src = url;
    this.url = url;
    if (old) URL.revokeObjectURL(old);
    const final = req.level === LEVELS[integrator].length - 1 && req.pass === passes - 1;
    this.shown = { version: req.version, level: req.level, pass: req.pass, final };
    this.frames++;
    this.element.dataset.frames = String(this.frames);
    Object.assign(this.img.dataset, {
      level: String(req.level),
      pass: String(req.pass),
      final: final ? "1" : "0",
      size: String(step.size),
      frame: String(this.frames),
    });
    const spp = step.spp * (req.pass + 1);
    const passText = passes > 1 ? ` · pass ${req.pass + 1}/${passes}` : "";
    setText(
      this.info,
      `${step.size}×${step.size} px · ${spp} spp · ${integrator} · ${final ? "final" : step.label}${passText} · ` +
        `last request: render ${formatSeconds(r.renderSeconds)}, round trip ${formatSeconds(r.roundTrip)}`,
    );
  }
}
