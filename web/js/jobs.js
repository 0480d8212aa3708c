// Following a job to its end: server-sent events when possible, else polling GET /v1/jobs/{id}.
// EventSource cannot send an Authorization header, so with an API key set the page polls.

import { ApiError } from "./api.js";

export const TERMINAL = new Set(["finished", "failed", "canceled"]);
const POLL_MS = 400;

function abortError() {
  return new DOMException("aborted", "AbortError");
}

/** The job id in a path such as "/v1/jobs/cache-1234". */
export function jobIdOf(path) {
  return String(path).split("/").filter(Boolean).pop();
}

/** Resolves with the job's final JSON; ``onProgress(job)`` on every change. Rejects on abort. */
export function followJob(api, id, { onProgress = () => {}, signal } = {}) {
  if (signal && signal.aborted) return Promise.reject(abortError());
  if (!api.key && typeof EventSource === "function") {
    return followEvents(api, id, onProgress, signal);
  }
  return pollJob(api, id, onProgress, signal);
}

function followEvents(api, id, onProgress, signal) {
  return new Promise((resolve, reject) => {
    const es = new EventSource(`/v1/jobs/${encodeURIComponent(id)}/events`);
    let done = false;
    const finish = () => {
      done = true;
      es.close();
      if (signal) signal.removeEventListener("abort", onAbort);
    };
    const onAbort = () => {
      if (done) return;
      finish();
      reject(abortError());
    };
    if (signal) signal.addEventListener("abort", onAbort);
    const parse = (e) => {
      try {
        return JSON.parse(e.data);
      } catch {
        return null;
      }
    };
    es.addEventListener("progress", (e) => {
      const job = parse(e);
      if (job && !done) onProgress(job);
    });
    es.addEventListener("end", (e) => {
      const job = parse(e);
      if (done) return;
      finish();
      if (job) {
        onProgress(job);
        resolve(job);
      } else {
        pollJob(api, id, onProgress, signal).then(resolve, reject);
      }
    });
    es.onerror = () => {
      // The stream broke or never opened (404, proxy, server restart): polling carries on and
      // reports any real error (an unknown job, a missing key) in words.
      if (done) return;
      finish();
      pollJob(api, id, onProgress, signal).then(resolve, reject);
    };
  });
}

function pollJob(api, id, onProgress, signal) {
  return new Promise((resolve, reject) => {
    let timer = null;
    let last = "";
    const onAbort = () => {
      clearTimeout(timer);
      reject(abortError());
    };
    if (signal) signal.addEventListener("abort", onAbort, { once: true });
    const tick = async () => {
      try {
        const job = await api.job(id, signal);
        const state = `${job.status}|${job.stage}|${job.fraction}`;
        if (state !== last) {
          last = state;
          onProgress(job);
        }
        if (TERMINAL.has(job.status)) {
          if (signal) signal.removeEventListener("abort", onAbort);
          resolve(job);
          return;
        }
        timer = setTimeout(tick, POLL_MS);
      } catch (err) {
        if (signal) signal.removeEventListener("abort", onAbort);
        reject(err);
      }
    };
    tick();
  });
}

/** A job that did not finish, as an error in words. */
export function jobFailure(job, what) {
  if (job.status === "canceled") return new ApiError(`${what} was cancelled`);
  return new ApiError(`${what} failed: ${job.error || "the job failed without a message"}`);
}
