// Compare the real-time view: the page's WebGL2 image of the current camera against the
// server's `field` render of the same camera and size (they march the same field, so they
// should agree to a few percent) and against volpath (the reference). Writes the relative MAE
// to data-rel-mae (field) and data-rel-mae-volpath on the result element. Both sides average
// SAMPLES ray origins over each pixel (the server's box filter): one sample per pixel at a
// random place in it, as the server draws at 1 spp, would make the comparison measure that
// placement's noise (about 2.5 % at 128 px on a wispy smoke) rather than the two marches.

import { isAbort } from "./api.js";
import { $, formatSeconds, readNumber, setText } from "./dom.js";
import { compareImages, imageDataOf } from "./imagemath.js";
import { renderImage } from "./render.js";

const SAMPLES = 16;

export class RealtimeCompare {
  /** realtime(): the RealtimeView drawing now, or null when the page draws no field. */
  constructor({ api, status, camera, buildRequest, realtime }) {
    Object.assign(this, { api, status, camera, buildRequest, realtime });
    this.button = $("#compare-realtime");
    this.result = $("#compare-result");
    this.size = $("#compare-size");
    this.volpathSpp = $("#compare-volpath-spp");
    this.button.addEventListener("click", () => this.run());
  }

  async run() {
    const view = this.realtime();
    if (!view || !view.hasField()) {
      this.status.error("the real-time view is not drawing a field (no WebGL2, or no cache ready)", "Compare");
      return;
    }
    let fieldBody;
    let volpathBody;
    let mine;
    const size = Number(this.size.value);
    try {
      const cam = this.camera.spec(size, size);
      fieldBody = this.buildRequest(cam, SAMPLES, "graph");
      fieldBody.estimator = "field";
      volpathBody = this.buildRequest(cam, readNumber(this.volpathSpp, { min: 1, max: 4096, integer: true }), "volpath");
      mine = view.snapshot(size, size, SAMPLES); // now, before the camera can move
    } catch (err) {
      this.status.error(err, "Compare");
      return;
    }
    this.button.disabled = true;
    const el = this.result;
    el.dataset.state = "busy";
    delete el.dataset.relMae;
    delete el.dataset.relMaeVolpath;
    setText(el, `rendering ${size}×${size} px on the server (field, then volpath)…`);
    try {
      const f = await renderImage(this.api, fieldBody);
      const fm = compareImages(mine, await imageDataOf(f.blob));
      el.dataset.relMae = String(fm.relative);
      const line1 =
        `real-time vs server field: relMAE ${(100 * fm.relative).toFixed(2)} % ` +
        `(mean ratio ${(fm.testMean / fm.refMean).toFixed(3)}; server ${formatSeconds(f.renderSeconds)})`;
      setText(el, `${line1}\nvolpath ${volpathBody.scene.render.spp} spp…`);
      const v = await renderImage(this.api, volpathBody);
      const vm = compareImages(mine, await imageDataOf(v.blob));
      el.dataset.relMaeVolpath = String(vm.relative);
      setText(
        el,
        `${line1}\nreal-time vs volpath ${volpathBody.scene.render.spp} spp: relMAE ` +
          `${(100 * vm.relative).toFixed(2)} % (mean ratio ${(vm.testMean / vm.refMean).toFixed(3)}; ` +
          `volpath ${formatSeconds(v.renderSeconds)}, its own noise included)`,
      );
      el.dataset.state = "done";
    } catch (err) {
      el.dataset.state = "failed";
      if (isAbort(err)) return;
      setText(el, `${el.textContent.split("\n")[0]}\nfailed`);
      this.status.error(err, "Compare real-time");
    } finally {
      this.button.disabled = false;
    }
  }
}
