// The HTTP API: one fetch wrapper that adds the API key and turns every failure into a sentence.

const KEY_STORAGE = "cloudgraph.apiKey";

const MEANING = {
  400: "bad request",
  401: "not authorised",
  403: "forbidden",
  404: "not found",
  409: "not ready",
  410: "gone",
  413: "too large",
  422: "rejected",
  429: "server busy",
};

/** An API or network failure; ``message`` is meant for people. */
export class ApiError extends Error {
  constructor(message, status = 0, detail = "") {
    super(message);
    this.name = "ApiError";
    this.status = status;
    this.detail = detail;
  }
}

export function isAbort(err) {
  return err && (err.name === "AbortError" || err.name === "TimeoutError");
}

/** A sentence for any error: ApiError's own message, else something readable. */
export function describeError(err) {
  if (err instanceof ApiError) return err.message;
  if (err && err.message) return err.message;
  return String(err);
}

function detailText(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    // FastAPI's default validation shape, in case a route answers with it
    return detail
      .map((d) => {
        const loc = (d.loc || []).filter((p) => p !== "body").join(".");
        return loc ? `${loc}: ${d.msg}` : d.msg;
      })
      .join("; ");
  }
  return detail == null ? "" : JSON.stringify(detail);
}

async function errorFrom(response, what) {
  let detail = "";
  try {
    const text = await response.text();
    try {
      detail = detailText(JSON.parse(text).detail);
    } catch {
      detail = text.slice(0, 300);
    }
  } catch {
    // the body could not be read; the status alone has to do
  }
  const s = response.status;
  const meaning = MEANING[s] || (s >= 500 ? "server error" : response.statusText || "error");
  let message = `${what} failed (${s} ${meaning})`;
  if (detail) message += `: ${detail}`;
  if (s === 401) message += ". Enter a valid API key at the top of the page.";
  if (s === 429) {
    const after = response.headers.get("Retry-After");
    if (after) message += ` (retry in ${after} s)`;
  }
  if (s >= 500) message += ". This is a bug in the service; its log says more.";
  return new ApiError(message, s, detail);
}

export class Api {
  constructor(storage = window.localStorage) {
    this.storage = storage;
    this.key = (storage && storage.getItem(KEY_STORAGE)) || "";
  }

  setKey(key) {
    this.key = (key || "").trim();
    if (this.key) this.storage.setItem(KEY_STORAGE, this.key);
    else this.storage.removeItem(KEY_STORAGE);
  }

  headers(extra = {}) {
    const h = { ...extra };
    if (this.key) h.Authorization = `Bearer ${this.key}`;
    return h;
  }

  /**
   * A request that succeeded (2xx), else an ApiError. ``what`` names the action in messages.
   * Options: json (a body to send as JSON), form (FormData), signal, method.
   */
  async request(path, { method = "GET", json, form, signal, what } = {}) {
    const label = what || `${method} ${path}`;
    const init = { method, signal, headers: this.headers() };
    if (json !== undefined) {
      init.body = JSON.stringify(json);
      init.headers["Content-Type"] = "application/json";
    } else if (form !== undefined) {
      init.body = form;
    }
    let response;
    try {
      response = await fetch(path, init);
    } catch (err) {
      if (isAbort(err)) throw err;
      throw new ApiError(`${label} failed: the server cannot be reached (${err.message || err})`);
    }
    if (!response.ok) throw await errorFrom(response, label);
    return response;
  }

  async json(path, options = {}) {
    const response = await this.request(path, options);
    try {
      return { status: response.status, body: await response.json(), response };
    } catch (err) {
      if (isAbort(err)) throw err;
      throw new ApiError(`${options.what || path} failed: the answer is not JSON`);
    }
  }

  async blob(path, options = {}) {
    const response = await this.request(path, options);
    return { blob: await response.blob(), response };
  }

  /** POSTs ``file`` as the multipart field "file" to ``path``. */
  upload(path, file) {
    const form = new FormData();
    form.append("file", file, file.name);
    return this.json(path, { method: "POST", form, what: `Uploading “${file.name}”` });
  }

  // --- the routes the page uses ---

  listVolumes() {
    return this.json("/v1/volumes", { what: "Listing volumes" }).then((r) => r.body);
  }

  uploadVolume(file) {
    return this.upload("/v1/volumes", file);
  }

  listEnvironments() {
    return this.json("/v1/environments", { what: "Listing environment maps" }).then((r) => r.body);
  }

  uploadEnvironment(file) {
    return this.upload("/v1/environments", file);
  }

  createCache(body, signal) {
    return this.json("/v1/caches", { method: "POST", json: body, signal, what: "Precompute" });
  }

  job(id, signal) {
    return this.json(`/v1/jobs/${encodeURIComponent(id)}`, { signal, what: "Job status" }).then(
      (r) => r.body,
    );
  }

  cancelJob(id) {
    return this.json(`/v1/jobs/${encodeURIComponent(id)}/cancel`, { method: "POST", what: "Cancel" });
  }

  createAnimation(body) {
    return this.json("/v1/animations", { method: "POST", json: body, what: "Animation" });
  }
}
