// The precompute panel: starts or finds the radiance cache of the scene panel's settings,
// follows its job (stage and progress bar) and shows its stats when it is ready.

import { isAbort } from "./api.js";
import { $, formatBytes, formatSeconds, h, setText } from "./dom.js";
import { followJob, jobFailure, jobIdOf } from "./jobs.js";

const STATUS_WORDS = {
  queued: "queued",
  waiting: "waiting",
  running: "running",
  finished: "ready",
  failed: "failed",
  canceled: "cancelled",
};

export class CachePanel {
  /** request() -> { key, body } for POST /v1/caches (throws in words); onReady(key) when one is
   * ready; onFailed(key) when its precompute failed or was cancelled. */
  constructor({ api, status, request, onReady, onFailed = () => {} }) {
    Object.assign(this, { api, status, request, onReady, onFailed });
    this.button = $("#precompute");
    this.cancelButton = $("#precompute-cancel");
    this.bar = $("#cache-progress");
    this.stage = $("#cache-stage");
    this.state = $("#cache-state");
    this.stats = $("#cache-stats");
    this.ready = new Map(); // key -> stats
    this.ids = new Map(); // key -> cache id (for GET /v1/caches/{id}/field)
    this.running = null; // { key, jobId, controller }
    this.button.addEventListener("click", () => this.precompute());
    this.cancelButton.addEventListener("click", () => this.cancel());
  }

  isReadyFor(key) {
    return key != null && this.ready.has(key);
  }

  /** The cache id of a ready cache, else undefined. */
  idFor(key) {
    return this.ids.get(key);
  }

  /** The key being precomputed now, or null. */
  runningKey() {
    return this.running ? this.running.key : null;
  }

  /** The scene changed: says whether the cache of the new settings is ready. */
  sceneChanged(key) {
    if (this.running) return;
    if (this.isReadyFor(key)) {
      this.setState("ready", "ready");
      this.showStats(this.ready.get(key));
    } else {
      this.setState("none", key ? "not built for these settings" : "–");
      this.stats.replaceChildren();
      this.bar.value = 0;
      setText(this.stage, "");
    }
  }

  setState(name, text) {
    this.state.dataset.state = name;
    setText(this.state, text);
  }

  showProgress(job) {
    const f = Math.max(0, Math.min(1, Number(job.fraction) || 0));
    this.bar.value = f;
    const words = STATUS_WORDS[job.status] || job.status;
    const stage = job.stage && job.stage !== job.status ? ` · ${job.stage}` : "";
    setText(this.stage, `${words}${stage} · ${Math.round(f * 100)} %`);
  }

  async precompute() {
    let req;
    try {
      req = this.request();
    } catch (err) {
      this.status.error(err, "Precompute");
      return;
    }
    if (this.running) {
      if (this.running.key === req.key) return; // already following it
      this.running.controller.abort();
    }
    const run = { key: req.key, jobId: null, controller: new AbortController() };
    this.running = run;
    this.button.disabled = true;
    this.cancelButton.disabled = false;
    this.stats.replaceChildren();
    this.bar.value = 0;
    setText(this.stage, "starting…");
    this.setState("running", "building");
    let found = false;
    try {
      const { status, body } = await this.api.createCache(req.body, run.controller.signal);
      let stats = body.stats;
      run.id = body.id;
      found = status === 200;
      if (!found) {
        run.jobId = jobIdOf(body.job);
        this.showProgress(body);
        const job = await followJob(this.api, run.jobId, {
          signal: run.controller.signal,
          onProgress: (j) => this.showProgress(j),
        });
        if (job.status !== "finished") throw jobFailure(job, "Precompute");
        stats = job.result && job.result.stats;
      }
      this.ready.set(run.key, stats || {});
      this.ids.set(run.key, run.id);
    } catch (err) {
      if (isAbort(err)) return;
      if (/cancelled/.test(err.message)) {
        this.setState("none", "cancelled");
        setText(this.stage, "cancelled");
        this.status.info(err.message);
      } else {
        this.setState("failed", "failed");
        this.status.error(err);
      }
    } finally {
      if (this.running === run) {
        this.running = null;
        this.button.disabled = false;
        this.cancelButton.disabled = true;
      }
    }
    if (!this.ready.has(run.key)) {
      if (!run.controller.signal.aborted) this.onFailed(run.key);
      return;
    }
    this.bar.value = 1;
    setText(this.stage, found ? "ready (found on the server) · 100 %" : "done · 100 %");
    this.setState("ready", "ready");
    this.showStats(this.ready.get(run.key));
    this.status.info("The radiance cache is ready.");
    this.onReady(run.key);
  }

  async cancel() {
    const run = this.running;
    if (!run || !run.jobId) return;
    try {
      await this.api.cancelJob(run.jobId);
      setText(this.stage, "cancelling…");
    } catch (err) {
      this.status.error(err);
    }
  }

  showStats(s) {
    if (!s) return;
    const bytes = (s.graph_bytes || 0) + (s.radiance_bytes || 0);
    const rows = [
      ["nodes", s.nodes != null ? s.nodes.toLocaleString("en") : "–"],
      ["edges", s.edges != null ? s.edges.toLocaleString("en") : "–"],
      ["graph build", s.graph_reused ? "reused" : formatSeconds(s.build_s)],
      ["lighting", s.radiance_reused ? "reused" : formatSeconds(s.lighting_s)],
      ["transport", s.radiance_reused ? "reused" : formatSeconds(s.transport_s)],
      ["field bake", s.field_reused ? "reused" : formatSeconds(s.field_s)],
      // a cache of several lights: each light's own, those found reused (a relight)
      ...(s.light_components > 1 ? [["lights", `${s.light_components} (${s.components_reused || 0} reused)`]] : []),
      ["field", s.field_bytes != null ? formatBytes(s.field_bytes) : "–"],
      ["bytes", `${formatBytes(bytes)} (graph ${formatBytes(s.graph_bytes)}, radiance ${formatBytes(s.radiance_bytes)})`],
      ["node radius", s.radius != null ? Number(s.radius).toPrecision(3) : "–"],
    ];
    this.stats.replaceChildren(
      ...rows.flatMap(([k, v]) => [h("dt", {}, k), h("dd", { dataset: { stat: k } }, v)]),
    );
  }
}
