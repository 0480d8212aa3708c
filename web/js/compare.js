// Compare: the graph integrator and volpath (the reference) for the same camera, side by side
// in a split view, with the mean absolute error of linear values computed here, in the page.

import { isAbort } from "./api.js";
import { $, formatSeconds, readNumber, setText } from "./dom.js";
import { compareImages, heatmap, imageDataOf } from "./imagemath.js";
import { renderImage } from "./render.js";

export class ComparePanel {
  constructor({ api, status, camera, buildRequest }) {
    Object.assign(this, { api, status, camera, buildRequest });
    this.button = $("#compare-run");
    this.cancelButton = $("#compare-cancel");
    this.size = $("#compare-size");
    this.graphSpp = $("#compare-graph-spp");
    this.volpathSpp = $("#compare-volpath-spp");
    this.view = $("#compare-view");
    this.split = $("#compare-split");
    this.canvas = $("#compare-canvas");
    this.result = $("#compare-mae");
    this.state = $("#compare-state");
    this.labels = $("#compare-labels");
    this.images = null;
    this.controller = null;

    this.button.addEventListener("click", () => this.run());
    this.cancelButton.addEventListener("click", () => this.controller && this.controller.abort());
    this.view.addEventListener("change", () => this.draw());
    this.split.addEventListener("input", () => this.draw());
    const drag = (e) => {
      if (!(e.buttons & 1) || !this.images || this.view.value !== "split") return;
      const r = this.canvas.getBoundingClientRect();
      this.split.value = String(Math.round((100 * (e.clientX - r.left)) / r.width));
      this.draw();
    };
    this.canvas.addEventListener("pointerdown", drag);
    this.canvas.addEventListener("pointermove", drag);
  }

  async run() {
    if (this.controller) this.controller.abort();
    const controller = new AbortController();
    this.controller = controller;
    let bodies;
    try {
      const size = Number(this.size.value);
      const cam = this.camera.spec(size, size);
      bodies = [
        this.buildRequest(cam, readNumber(this.graphSpp, { min: 1, max: 4096, integer: true }), "graph"),
        this.buildRequest(cam, readNumber(this.volpathSpp, { min: 1, max: 4096, integer: true }), "volpath"),
      ];
    } catch (err) {
      this.status.error(err, "Compare");
      return;
    }
    this.button.disabled = true;
    this.cancelButton.disabled = false;
    this.canvas.closest(".compare-out").dataset.state = "busy";
    setText(this.state, "rendering graph and volpath…");
    try {
      const done = { graph: false, volpath: false };
      const one = (body) =>
        renderImage(this.api, body, { signal: controller.signal }).then((r) => {
          done[body.integrator] = true;
          setText(this.state, `rendering… ${Object.keys(done).filter((k) => done[k]).join(", ")} done`);
          return r;
        });
      const [g, v] = await Promise.all(bodies.map(one));
      const [gi, vi] = await Promise.all([imageDataOf(g.blob), imageDataOf(v.blob)]);
      if (this.controller !== controller) return;
      const m = compareImages(gi, vi);
      this.images = { graph: gi, volpath: vi, metrics: m };
      this.canvas.hidden = false;
      this.canvas.width = gi.width;
      this.canvas.height = gi.height;
      this.draw();
      this.canvas.dataset.mae = String(m.mae);
      setText(
        this.result,
        `MAE ${m.mae.toExponential(3)} · ${(100 * m.relative).toFixed(1)} % of the volpath mean ` +
          `(${m.refMean.toFixed(4)}; graph mean ${m.testMean.toFixed(4)}, ratio ${(m.testMean / m.refMean).toFixed(3)})`,
      );
      setText(
        this.state,
        `${gi.width}×${gi.height} px · graph ${bodies[0].scene.render.spp} spp in ${formatSeconds(g.renderSeconds)} · ` +
          `volpath ${bodies[1].scene.render.spp} spp in ${formatSeconds(v.renderSeconds)}`,
      );
      this.canvas.closest(".compare-out").dataset.state = "done";
    } catch (err) {
      if (this.controller !== controller) return;
      this.canvas.closest(".compare-out").dataset.state = "failed";
      if (isAbort(err)) {
        setText(this.state, "cancelled");
        return;
      }
      setText(this.state, "failed");
      this.status.error(err, "Compare");
    } finally {
      if (this.controller === controller) {
        this.controller = null;
        this.button.disabled = false;
        this.cancelButton.disabled = true;
      }
    }
  }

  draw() {
    if (!this.images) return;
    const { graph, volpath, metrics } = this.images;
    const ctx = this.canvas.getContext("2d");
    const w = graph.width;
    const hgt = graph.height;
    const mode = this.view.value;
    this.split.disabled = mode !== "split";
    if (mode === "graph") ctx.putImageData(graph, 0, 0);
    else if (mode === "volpath") ctx.putImageData(volpath, 0, 0);
    else if (mode === "diff") ctx.putImageData(heatmap(metrics.diff, w, hgt, metrics.fgMean || 1), 0, 0);
    else {
      const x = Math.round((Number(this.split.value) / 100) * w);
      ctx.putImageData(graph, 0, 0);
      ctx.putImageData(volpath, 0, 0, x, 0, w - x, hgt);
      ctx.fillStyle = "rgba(255,255,255,0.8)";
      ctx.fillRect(Math.min(w - 1, x), 0, 1, hgt);
    }
    const names = { split: ["graph", "volpath"], graph: ["graph", ""], volpath: ["", "volpath"], diff: ["|graph − volpath|", "yellow: the smoke's mean value"] };
    const [left, right] = names[mode] || ["", ""];
    setText(this.labels.children[0], left);
    setText(this.labels.children[1], right);
  }
}
