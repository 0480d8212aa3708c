// One image from POST /v1/renders: the PNG itself (200) or, for a 202, the job followed to its
// image. Resolves with { blob, renderSeconds, roundTrip, jobId }.

import { followJob, jobFailure } from "./jobs.js";

export async function renderImage(api, body, { signal, onProgress } = {}) {
  const t0 = performance.now();
  const what = `Render (${body.integrator}, ${body.scene.camera.width}×${body.scene.camera.height})`;
  const response = await api.request("/v1/renders", { method: "POST", json: body, signal, what });
  if (response.status === 200) {
    const blob = await response.blob();
    return {
      blob,
      renderSeconds: parseFloat(response.headers.get("X-Render-Seconds")),
      roundTrip: (performance.now() - t0) / 1000,
      jobId: response.headers.get("X-Job-Id"),
    };
  }
  const job = await response.json();
  const final = await followJob(api, job.id, { signal, onProgress });
  if (final.status !== "finished") throw jobFailure(final, what);
  const { blob } = await api.blob(final.result_url, { signal, what: `${what}: fetching the image` });
  return {
    blob,
    renderSeconds: final.result ? final.result.render_s : NaN,
    roundTrip: (performance.now() - t0) / 1000,
    jobId: final.id,
  };
}
