// Animation: camera keyframes (recorded from the viewport) or an orbit, rendered by the
// service into an MP4 that plays here and can be downloaded.

import { isAbort } from "./api.js";
import { OrbitCamera } from "./camera.js";
import { $, h, readNumber, setText } from "./dom.js";
import { followJob, jobFailure } from "./jobs.js";

export class AnimationPanel {
  /** buildRequest(cameraSpec, spp, integrator) -> a render body whose scene and settings are reused. */
  constructor({ api, status, camera, buildRequest, onGoTo }) {
    Object.assign(this, { api, status, camera, buildRequest, onGoTo });
    this.keys = [];
    this.list = $("#anim-keys-list");
    this.button = $("#anim-run");
    this.cancelButton = $("#anim-cancel");
    this.bar = $("#anim-progress");
    this.stage = $("#anim-stage");
    this.video = $("#anim-video");
    this.download = $("#anim-download");
    this.job = null;
    this.url = null;

    $("#anim-add-key").addEventListener("click", () => this.addKey());
    $("#anim-clear-keys").addEventListener("click", () => {
      this.keys = [];
      this.renderKeys();
    });
    this.button.addEventListener("click", () => this.run());
    this.cancelButton.addEventListener("click", () => this.cancel());
    for (const radio of document.querySelectorAll("input[name=anim-path]")) {
      radio.addEventListener("change", () => this.showPathInputs());
    }
    this.video.addEventListener("error", () => {
      if (!this.video.getAttribute("src")) return;
      const e = this.video.error;
      this.status.error(`the browser cannot play the video${e && e.message ? ` (${e.message})` : ""}`, "Animation");
    });
    this.showPathInputs();
    this.renderKeys();
  }

  path() {
    return document.querySelector("input[name=anim-path]:checked").value;
  }

  showPathInputs() {
    const orbit = this.path() === "orbit";
    $("#anim-orbit-inputs").hidden = !orbit;
    $("#anim-keys-inputs").hidden = orbit;
  }

  addKey() {
    this.keys.push(this.camera.save());
    this.renderKeys();
    if (this.path() !== "keyframes") {
      $("#anim-path-keys").checked = true;
      this.showPathInputs();
    }
  }

  renderKeys() {
    const items = this.keys.map((k, i) => {
      const cam = new OrbitCamera();
      cam.restore(k);
      return h(
        "li",
        {},
        h("span", { class: "key-label" }, `${i + 1}. ${cam.describe()}`),
        h("button", { type: "button", class: "small", title: "Show this camera", onclick: () => this.onGoTo(k) }, "view"),
        h(
          "button",
          {
            type: "button",
            class: "small",
            title: "Remove this keyframe",
            onclick: () => {
              this.keys.splice(i, 1);
              this.renderKeys();
            },
          },
          "×",
        ),
      );
    });
    this.list.replaceChildren(...items);
    setText($("#anim-keys-count"), `${this.keys.length} keyframe${this.keys.length === 1 ? "" : "s"}`);
  }

  body() {
    const size = readNumber($("#anim-size"), { min: 8, max: 2048, integer: true });
    const spp = readNumber($("#anim-spp"), { min: 1, max: 4096, integer: true });
    const integrator = $("#anim-integrator").value;
    const base = this.buildRequest(this.camera.spec(size, size), spp, integrator);
    const body = {
      scene: base.scene,
      frames: readNumber($("#anim-frames"), { min: 1, max: 600, integer: true }),
      fps: readNumber($("#anim-fps"), { min: 1, max: 120 }),
      integrator,
      quality: base.quality,
      exposure: base.exposure,
    };
    if (this.path() === "orbit") {
      body.orbit = {
        elevation: readNumber($("#anim-elevation"), { min: -89, max: 89 }),
        turns: readNumber($("#anim-turns"), { min: 0.01, max: 10 }),
      };
    } else {
      if (this.keys.length < 2) throw new Error("add at least 2 keyframes (Add current camera), or choose an orbit");
      body.keyframes = this.keys.map((k) => {
        const cam = new OrbitCamera();
        cam.restore(k);
        return cam.spec(size, size);
      });
      body.scene = { ...body.scene, camera: body.keyframes[0] };
    }
    return body;
  }

  async run() {
    let body;
    try {
      body = this.body();
    } catch (err) {
      this.status.error(err, "Animation");
      return;
    }
    if (this.job) this.job.controller.abort();
    const run = { id: null, controller: new AbortController() };
    this.job = run;
    this.button.disabled = true;
    this.cancelButton.disabled = false;
    this.bar.value = 0;
    setText(this.stage, "submitting…");
    this.clearVideo();
    try {
      const { body: job } = await this.api.createAnimation(body);
      run.id = job.id;
      this.progress(job);
      const final = await followJob(this.api, job.id, {
        signal: run.controller.signal,
        onProgress: (j) => this.progress(j),
      });
      if (final.status !== "finished") throw jobFailure(final, "Animation");
      await this.showVideo(final, run);
      this.status.info(`The animation is ready (${body.frames} frames).`);
    } catch (err) {
      if (isAbort(err) || this.job !== run) return;
      setText(this.stage, /cancelled/.test(err.message) ? "cancelled" : "failed");
      if (/cancelled/.test(err.message)) this.status.info(err.message);
      else this.status.error(err);
    } finally {
      if (this.job === run) {
        this.job = null;
        this.button.disabled = false;
        this.cancelButton.disabled = true;
      }
    }
  }

  progress(job) {
    const f = Math.max(0, Math.min(1, Number(job.fraction) || 0));
    this.bar.value = f;
    const stage = job.stage && job.stage !== job.status ? ` · ${job.stage}` : "";
    setText(this.stage, `${job.status}${stage} · ${Math.round(f * 100)} %`);
  }

  async cancel() {
    if (!this.job || !this.job.id) return;
    try {
      await this.api.cancelJob(this.job.id);
      setText(this.stage, "cancelling…");
    } catch (err) {
      this.status.error(err);
    }
  }

  clearVideo() {
    this.video.removeAttribute("src");
    this.video.load();
    this.download.hidden = true;
    this.download.removeAttribute("href");
    if (this.url) URL.revokeObjectURL(this.url);
    this.url = null;
  }

  /** Without a key the video streams from its URL; with one (a <video> sends no headers) it is fetched. */
  async showVideo(job, run) {
    let src = job.result_url;
    if (this.api.key) {
      const { blob } = await this.api.blob(job.result_url, {
        signal: run.controller.signal,
        what: "Downloading the video",
      });
      this.url = URL.createObjectURL(blob);
      src = this.url;
    }
    this.video.src = src;
    this.video.dataset.resultUrl = job.result_url;
    this.download.href = src;
    this.download.download = `${job.id}.mp4`;
    this.download.hidden = false;
    this.bar.value = 1;
    setText(this.stage, "done · 100 %");
  }
}
