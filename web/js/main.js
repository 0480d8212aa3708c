// Wiring: the panels, the viewport and the API key, and the one rule that decides whether the
// viewport may render (a volume, valid inputs, and a ready cache for the graph integrator).

import { Api } from "./api.js";
import { AnimationPanel } from "./animation.js";
import { CachePanel } from "./cache.js";
import { OrbitCamera } from "./camera.js";
import { ComparePanel } from "./compare.js";
import { Controls } from "./controls.js";
import { $, readNumber, setText } from "./dom.js";
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
      light: v.light,
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
      body: { volume: v.volume, medium: v.medium, light: v.light, max_depth: -1, quality: v.quality },
    };
  },
  onReady: () => sceneChanged(),
});

new ComparePanel({ api, status, camera, buildRequest });

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

function showCamera() {
  const info = $("#camera-info");
  setText(info, camera.describe());
  info.dataset.eye = JSON.stringify(camera.eye());
  info.dataset.target = JSON.stringify(camera.target);
  scene.light.setCamera(camera.yaw);
}

function cameraMoved() {
  showCamera();
  viewer.cameraMoved();
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

/** Anything but the camera changed: the cache's state, the viewport's permission to render. */
function sceneChanged() {
  const key = scene.key();
  cache.sceneChanged(key);
  showCamera();
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
