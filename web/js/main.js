// Wiring: the panels, the viewport and the API key, and the rules that decide what the viewport
// shows: the page's own WebGL2 view of the cache's radiance field when it can (graph, WebGL2, a
// field that fits), else the server's progressive renders; and a light change that keeps the
// old field drawn while the server relights the cache (the graph is reused).

import { Api } from "./api.js";
import { AnimationPanel } from "./animation.js";
import { CachePanel } from "./cache.js";
import { OrbitCamera } from "./camera.js";
import { ComparePanel } from "./compare.js";
import { Controls } from "./controls.js";
import { $, formatSeconds, readNumber, setText } from "./dom.js";
import { RealtimeView } from "./realtime.js";
import { RealtimeCompare } from "./rtcompare.js";
import { ScenePanel } from "./scene.js";
import { StatusArea } from "./status.js";
import { Viewer } from "./viewer.js";

const status = new StatusArea($("#status"), $("#errors"));
window.addEventListener("error", (e) => status.error(e.error || e.message, "Unexpected error in the page"));
window.addEventListener("unhandledrejection", (e) => status.error(e.reason, "Unexpected error in the page"));

const api = new Api();
const camera = new OrbitCamera();
const exposure = $("#exposure");

/** A POST /v1/renders body for the scene panel's scene seen by ``cameraSpec``. */
function buildRequest(cameraSpec, spp, integrator, seed = 0) {
  const v = scene.values();
  return {
    scene: {
      volume: v.volume,
      medium: v.medium,
      ...v.lightPart,
      camera: cameraSpec,
      render: { spp, max_depth: -1, seed },
    },
    integrator,
    format: "png",
    quality: v.quality,
    exposure: readNumber(exposure, { min: -20, max: 20 }),
  };
}

const scene = new ScenePanel({
  api,
  status,
  onVolume: (info) => {
    camera.axes = scene.axes();
    if (info) camera.frame(info.world_bbox);
    sceneChanged();
  },
  onChange: () => sceneChanged(),
});

const viewport = $("#viewport");
const overlay = $("#view-overlay");
const modeNote = $("#view-mode");
const relightInfo = $("#relight-info");

// The real-time view, unless this browser has no WebGL2 (then the server renders every frame).
let realtime = null;
let realtimeMissing = "";
try {
  realtime = new RealtimeView({
    element: viewport,
    canvas: $("#view-canvas"),
    img: $("#view-img"),
    info: $("#view-info"),
    api,
    status,
    camera,
    exposure: () => readNumber(exposure, { min: -20, max: 20 }),
    buildRequest,
    onLost: () => {
      realtimeMissing = "the GPU dropped the WebGL context";
      sceneChanged();
    },
  });
} catch (err) {
  realtimeMissing = err.message;
}
const fieldFailed = new Map(); // scene key -> why its field cannot be drawn here
let relight = null; // { key, t0 } while the server relights for a new light

const viewer = new Viewer({
  element: $("#viewport"),
  img: $("#view-img"),
  overlay: $("#view-overlay"),
  info: $("#view-info"),
  api,
  status,
  camera,
  buildRequest,
});

const cache = new CachePanel({
  api,
  status,
  request: () => {
    const v = scene.values();
    return {
      key: scene.key(),
      body: { volume: v.volume, medium: v.medium, ...v.lightPart, max_depth: -1, quality: v.quality },
    };
  },
  onReady: () => sceneChanged(),
  onFailed: (key) => {
    if (!relight || relight.key !== key) return;
    relight = null;
    setText(relightInfo, "The relight did not finish; still drawing the previous light.");
  },
});

new ComparePanel({ api, status, camera, buildRequest });
new RealtimeCompare({ api, status, camera, buildRequest, realtime: () => (usingRealtime() ? realtime : null) });

new AnimationPanel({
  api,
  status,
  camera,
  buildRequest,
  onGoTo: (state) => {
    camera.restore(state);
    cameraMoved();
  },
});

/** The camera's numbers: data attributes at once (tests and tools read them), the text and
 * the light widget's camera dot at most every CAMERA_TEXT_MS (a mouse sends more moves than
 * frames, and each text change costs a layout and a repaint). */
const CAMERA_TEXT_MS = 100;
let cameraTextPending = false;
function showCamera() {
  const info = $("#camera-info");
  info.dataset.eye = JSON.stringify(camera.eye());
  info.dataset.target = JSON.stringify(camera.target);
  if (cameraTextPending) return;
  cameraTextPending = true;
  setTimeout(() => {
    cameraTextPending = false;
    setText(info, camera.describe());
    scene.light.setCamera(camera.yaw);
  }, CAMERA_TEXT_MS);
}

function cameraMoved() {
  showCamera();
  if (usingRealtime()) realtime.cameraMoved();
  else viewer.cameraMoved();
}

new Controls($("#viewport"), camera, cameraMoved);

$("#view-reset").addEventListener("click", () => {
  if (camera.home) camera.restore(camera.home);
  cameraMoved();
});
$("#view-integrator").addEventListener("change", (e) => {
  viewer.integrator = e.target.value;
  sceneChanged();
});
exposure.addEventListener("change", () => sceneChanged());
$("#final-toggle").addEventListener("change", (e) => realtime && realtime.setFinalWanted(e.target.checked));

function usingRealtime() {
  return viewport.dataset.renderer === "webgl";
}

function showOverlay(text) {
  setText(overlay, text);
  overlay.hidden = !text;
}

/**
 * Same volume, density and quality: the same graph, so a new light is only a relight. An
 * anisotropic phase's graph is that of its similarity-scaled medium, which albedo and phase set
 * too (docs/method.md, "Anisotropic scattering").
 */
function sameGraph(a, b) {
  if (a == null || b == null) return false;
  const [va, ma, , qa] = JSON.parse(a);
  const [vb, mb, , qb] = JSON.parse(b);
  const graphOf = (m) => JSON.stringify(m.phase ? [m.density_scale, m.albedo, m.phase] : [m.density_scale]);
  return JSON.stringify(va) === JSON.stringify(vb) && graphOf(ma) === graphOf(mb) && qa === qb;
}

/** Whether the viewport draws the field itself for this scene key; shows why not. */
function chooseRenderer(key) {
  let why = "";
  if (!realtime || realtime.lost) why = `Real-time view unavailable: ${realtimeMissing}.`;
  else if (viewer.integrator !== "graph") why = "volpath frames come from the server.";
  else if (fieldFailed.has(key)) why = `Real-time view unavailable: ${fieldFailed.get(key)}.`;
  const webgl = !why;
  viewport.dataset.renderer = webgl ? "webgl" : "server";
  setText(
    modeNote,
    webgl
      ? "Real-time: this page draws the cache's radiance field (WebGL2); the server renders finals and comparisons."
      : `${why} Showing the server's progressive renders instead.`,
  );
  modeNote.classList.toggle("warn", !webgl && viewer.integrator === "graph");
  return webgl;
}

/** Downloads the field of the ready cache for ``key`` and draws it; falls back on failure. */
function loadField(key) {
  const id = cache.idFor(key);
  if (!id) return;
  showOverlay(realtime.hasField() ? "" : "Downloading the radiance field…");
  realtime.load(id, key).then(
    (seconds) => {
      if (scene.key() !== key) return;
      showOverlay("");
      if (relight && relight.key === key) {
        const took = (performance.now() - relight.t0) / 1000;
        relightInfo.dataset.seconds = String(took);
        setText(relightInfo, `Relit in ${formatSeconds(took)} (field download ${formatSeconds(seconds)}); now drawing the new light.`);
        relight = null;
      }
      realtime.setActive(true);
    },
    (err) => {
      if (err && err.name === "AbortError") return;
      status.error(err, "Real-time view");
      fieldFailed.set(key, err.message);
      if (relight && relight.key === key) relight = null;
      sceneChanged();
    },
  );
}

/** Anything but the camera changed: the cache's state, the viewport's permission to render. */
function sceneChanged() {
  const key = scene.key();
  cache.sceneChanged(key);
  showCamera();
  if (scene.volume() && key != null && chooseRenderer(key)) {
    realtimeSceneChanged(key);
    return;
  }
  if (realtime) realtime.setActive(false);
  $("#view-img").hidden = false;
  if (!scene.volume()) {
    viewer.setEnabled(false, "Upload a volume (.vdb or .vol) or select one to start.");
  } else if (key == null) {
    let reason = "Fix the scene settings.";
    try {
      scene.values();
    } catch (err) {
      reason = `Fix the scene settings: ${err.message}`;
    }
    viewer.setEnabled(false, reason);
  } else if (viewer.integrator === "graph" && !cache.isReadyFor(key)) {
    viewer.setEnabled(
      false,
      "Press Precompute to build the radiance cache for these settings (or switch the viewport to volpath).",
    );
  } else {
    viewer.setEnabled(true);
  }
  viewer.sceneChanged();
}

/** The real-time viewport's share of sceneChanged(). */
function realtimeSceneChanged(key) {
  viewer.setEnabled(false, "");
  realtime.setMix(scene.mix()); // a v1.1 field's lights re-mixed at once, with no request
  if (cache.isReadyFor(key)) {
    if (realtime.fieldKey === key) {
      showOverlay("");
      realtime.setActive(true);
    } else {
      if (realtime.hasField() && sameGraph(key, realtime.fieldKey)) realtime.setActive(true);
      loadField(key);
    }
  } else if (realtime.hasField() && sameGraph(key, realtime.fieldKey)) {
    // A new light (or albedo) on the same graph: keep drawing the old field while the server
    // relights; the new field replaces it when it arrives.
    showOverlay("");
    realtime.setActive(true);
    if (cache.runningKey() !== key) {
      relight = { key, t0: performance.now() };
      delete relightInfo.dataset.seconds;
      setText(relightInfo, "Relighting on the server (the graph is reused); drawing the previous light meanwhile…");
      cache.precompute();
    }
  } else {
    realtime.setActive(false);
    showOverlay("Press Precompute to build the radiance cache for these settings (or switch the viewport to volpath).");
  }
}

// --- the API key ---
const keyInput = $("#api-key");
const keyState = $("#api-key-state");
function showKeyState() {
  setText(keyState, api.key ? "key set" : "no key");
  keyState.dataset.state = api.key ? "set" : "none";
}
keyInput.value = api.key;
showKeyState();
$("#api-key-form").addEventListener("submit", (e) => {
  e.preventDefault();
  api.setKey(keyInput.value);
  showKeyState();
  status.clearErrors();
  status.info(api.key ? "API key saved in this browser." : "API key removed.");
  scene.refresh(scene.select.value);
});
$("#api-key-clear").addEventListener("click", () => {
  keyInput.value = "";
  api.setKey("");
  showKeyState();
  status.info("API key removed.");
});

status.info("Loading volumes…");
scene.refresh().then(() => {
  if (!$("#errors").children.length) status.info("Ready.");
  sceneChanged();
});
