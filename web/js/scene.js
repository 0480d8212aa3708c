// The scene panel: volumes (list, upload), the up axis, medium (with its phase function), the
// lights (suns, a sky) and the quality preset.
// values() is the scene without its camera; onVolume(info) when another volume (or up axis) is
// chosen, onChange() when anything else that the cache depends on changes.

import { $, $$, formatBytes, h, readNumber, setText } from "./dom.js";
import { AXES } from "./camera.js";
import { LightWidget, lightDirection, towardsLight } from "./lightwidget.js";

/** density_scale that gives the densest voxel an optical depth of 1. */
export function defaultDensityScale(info) {
  const vmax = info.value_range ? info.value_range[1] : 0;
  const vs = info.voxel_size || [1, 1, 1];
  const voxel = (vs[0] + vs[1] + vs[2]) / 3;
  if (!(vmax > 0) || !(voxel > 0)) return 1;
  return Number((1 / (vmax * voxel)).toPrecision(3));
}

/**
 * The grid the page's scenes read: the volume's default, else (several float grids, none named
 * "density": api.md) the first float grid, the one the volume's boxes and values describe.
 */
export function densityGrid(info) {
  if (info.grid != null) return info.grid;
  const first = info.grids.find((g) => g.type === "float" || g.type === "half");
  return first ? first.name : null;
}

/** Largest |g| of a Henyey–Greenstein lobe (scene spec v1.1, cloudgraph/scene.py). */
export const MAX_G = 0.95;

/**
 * The scene spec's medium.phase from the panel's controls (type, g, g2, weight), or null for
 * the isotropic phase (left out of the medium: a v1 scene, the same cache). Throws an Error
 * naming the field.
 */
export function readPhase({ type, g, g2, weight }) {
  if (type.value === "hg") return { type: "hg", g: readNumber(g, { min: -MAX_G, max: MAX_G }) };
  if (type.value === "hg2") {
    return {
      type: "hg2",
      g: [readNumber(g, { min: -MAX_G, max: MAX_G }), readNumber(g2, { min: -MAX_G, max: MAX_G })],
      weight: readNumber(weight, { min: 0, max: 1 }),
    };
  }
  return null;
}

/** The most lights a scene has (scene spec v1.1, ``lights``). */
export const MAX_LIGHTS = 8;

/** An RGB intensity: ``scale`` times an <input type=color> value's linear colour. */
export function tinted(hex, scale) {
  const c = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
  const linear = c.map((v) => (v <= 0.04045 ? v / 12.92 : ((v + 0.055) / 1.055) ** 2.4));
  return linear.map((v) => Number((scale * v).toPrecision(4)));
}

/** The light components a scene light makes: a sunsky two (its sun and its sky), others one. */
export function componentCount(lights) {
  return lights.reduce((n, l) => n + (l.type === "sunsky" ? 2 : 1), 0);
}

/** A directional light of the spec from azimuth and elevation (degrees), an irradiance input
 * and a colour input: a scalar irradiance for white, else RGB. ``n``: its number in words. */
function sunSpec(az, el, irradianceInput, colourInput, axes, n = 1) {
  const e = readNumber(irradianceInput, { min: 0 });
  const white = colourInput.value.toLowerCase() === "#ffffff";
  if (!white && !/^#[0-9a-f]{6}$/i.test(colourInput.value)) throw new Error(`sun ${n} colour: pick a colour`);
  return { type: "directional", direction: lightDirection(az, el, axes), irradiance: white ? e : tinted(colourInput.value, e) };
}

function describeVolume(info) {
  const [lo, hi] = info.index_bbox || [[0, 0, 0], [0, 0, 0]];
  const dims = hi.map((v, i) => v - lo[i] + 1).join("×");
  return `${info.filename || "volume"} · ${dims} voxels · ${formatBytes(info.bytes)}`;
}

export class ScenePanel {
  constructor({ api, status, onVolume, onChange }) {
    Object.assign(this, { api, status, onVolume, onChange });
    this.volumes = new Map();
    this.select = $("#volume-select");
    this.file = $("#volume-file");
    this.uploadState = $("#upload-state");
    this.volumeInfo = $("#volume-info");
    this.density = $("#density");
    this.albedo = $("#albedo");
    this.phase = { type: $("#phase-type"), g: $("#phase-g"), g2: $("#phase-g2"), weight: $("#phase-weight") };
    this.phaseRows = { g: $("#phase-g-row"), hg2: $("#phase-hg2-row") };
    this.az = $("#light-az");
    this.el = $("#light-el");
    this.irradiance = $("#irradiance");
    this.sunColour = $("#sun-colour");
    this.sky = $("#sky");
    this.skyColour = $("#sky-colour");
    this.sunsky = $("#sunsky");
    this.turbidity = $("#turbidity");
    this.skyScale = $("#sky-scale");
    this.envSelect = $("#env-select");
    this.envScale = $("#env-scale");
    this.envFile = $("#env-file");
    this.envState = $("#env-state");
    this.envSelect.addEventListener("change", () => this.onChange());
    this.envScale.addEventListener("change", () => this.onChange());
    this.envFile.addEventListener("change", () => this.uploadEnvironment());
    this.sunList = $("#sun-list");
    this.sunAdd = $("#sun-add");
    this.sunAdd.addEventListener("click", () => this.addSun());
    this.quality = $("#quality");
    this.upAxis = $("#up-axis");

    this.light = new LightWidget(
      $("#light-canvas"),
      (az, el) => {
        this.az.value = az;
        this.el.value = el;
      },
      () => this.onChange(),
    );
    this.light.set(Number(this.az.value), Number(this.el.value));
    this.light.setAxes(this.axes());
    this.upAxis.addEventListener("change", () => {
      this.light.setAxes(this.axes());
      this.onVolume(this.volume());
    });

    this.select.addEventListener("change", () => this.chooseVolume(this.select.value));
    $("#volume-refresh").addEventListener("click", () => this.refresh(this.select.value));
    this.file.addEventListener("change", () => this.upload());
    $("#density-auto").addEventListener("click", () => {
      const info = this.volume();
      if (!info) return;
      this.density.value = defaultDensityScale(info);
      this.onChange();
    });
    for (const input of [this.density, this.albedo, this.irradiance, this.quality, this.sky, this.sunsky, this.turbidity, this.skyScale]) {
      input.addEventListener("change", () => this.onChange());
    }
    // colours re-mix the view as they are picked (no request when the cache holds the lights
    // apart)
    for (const input of [this.skyColour, this.sunColour]) input.addEventListener("input", () => this.onChange());
    this.showPhase();
    this.phase.type.addEventListener("change", () => {
      this.showPhase();
      this.onChange();
    });
    for (const input of [this.phase.g, this.phase.g2, this.phase.weight]) {
      input.addEventListener("change", () => this.onChange());
    }
    for (const input of [this.az, this.el]) {
      input.addEventListener("input", () => {
        const az = Number(this.az.value);
        const el = Number(this.el.value);
        if (Number.isFinite(az) && Number.isFinite(el)) this.light.set(az, el);
      });
      input.addEventListener("change", () => this.onChange());
    }
  }

  volume() {
    return this.volumes.get(this.select.value) || null;
  }

  /** Shows the phase's inputs for its type: g for hg and hg2, g2 and the weight for hg2. */
  showPhase() {
    const type = this.phase.type.value;
    this.phaseRows.g.hidden = type === "isotropic";
    this.phaseRows.hg2.hidden = type !== "hg2";
    this.phase.g.dataset.label = type === "hg2" ? "phase g1" : "phase g";
  }

  /** The world frame chosen for "up" (camera orbits and light elevation). */
  axes() {
    return AXES[this.upAxis.value] || AXES.y;
  }

  /** Reloads the environment maps' list; selects ``selectId`` if given, else keeps the choice. */
  async refreshEnvironments(selectId = "") {
    let list;
    try {
      list = await this.api.listEnvironments();
    } catch (err) {
      this.status.error(err);
      return;
    }
    const before = this.envSelect.value;
    const options = list.map((e) => h("option", { value: e.id }, `${e.filename} · ${e.width}×${e.height}`));
    this.envSelect.replaceChildren(h("option", { value: "" }, "none"), ...options);
    const want = [selectId, before].find((id) => id && list.some((e) => e.id === id)) || "";
    this.envSelect.value = want;
    if (want !== before) this.onChange();
  }

  async uploadEnvironment() {
    const file = this.envFile.files && this.envFile.files[0];
    if (!file) return;
    setText(this.envState, `uploading ${file.name}…`);
    this.envState.className = "busy";
    try {
      const { body } = await this.api.uploadEnvironment(file);
      await this.refreshEnvironments(body.id); // (selects it: the scene changes)
      setText(this.envState, `uploaded ${file.name}`);
      this.envState.className = "ok";
    } catch (err) {
      setText(this.envState, `upload of ${file.name} failed`);
      this.envState.className = "failed";
      this.status.error(err);
    } finally {
      this.envFile.value = "";
    }
  }

  /** Reloads the list; selects ``selectId`` if given and present, else keeps or picks the first. */
  async refresh(selectId = "") {
    this.refreshEnvironments();
    let list;
    try {
      list = await this.api.listVolumes();
    } catch (err) {
      this.status.error(err);
      return;
    }
    const before = this.select.value;
    this.volumes = new Map(list.map((v) => [v.id, v]));
    const options = list.map((v) => h("option", { value: v.id }, describeVolume(v)));
    if (!list.length) options.push(h("option", { value: "" }, "no volumes yet: upload one"));
    this.select.replaceChildren(...options);
    const want = [selectId, before].find((id) => id && this.volumes.has(id)) || (list[0] && list[0].id) || "";
    this.select.value = want;
    if (want !== before || selectId) this.chooseVolume(want);
  }

  chooseVolume(id) {
    const info = this.volumes.get(id);
    if (!info) {
      setText(this.volumeInfo, "");
      this.onVolume(null);
      return;
    }
    this.density.value = defaultDensityScale(info);
    const [lo, hi] = info.world_bbox;
    setText(
      this.volumeInfo,
      `grid “${densityGrid(info)}”${info.grid == null ? " (none is named “density”: the first float grid)" : ""} · voxel ${info.voxel_size[0].toPrecision(3)} · values ` +
        `${info.value_range[0].toPrecision(3)}…${info.value_range[1].toPrecision(3)} · world ` +
        `[${lo.map((v) => v.toFixed(1)).join(", ")}] – [${hi.map((v) => v.toFixed(1)).join(", ")}]`,
    );
    this.onVolume(info);
  }

  async upload() {
    const file = this.file.files && this.file.files[0];
    if (!file) return;
    setText(this.uploadState, `uploading ${file.name} (${formatBytes(file.size)})…`);
    this.uploadState.className = "busy";
    try {
      const { status, body } = await this.api.uploadVolume(file);
      setText(this.uploadState, status === 201 ? `uploaded ${file.name}` : `${file.name} was already uploaded`);
      this.uploadState.className = "ok";
      this.status.info(`Volume ${file.name} is ready (${body.id.slice(0, 12)}…)`);
      await this.refresh(body.id);
    } catch (err) {
      setText(this.uploadState, `upload of ${file.name} failed`);
      this.uploadState.className = "failed";
      this.status.error(err);
    } finally {
      this.file.value = "";
    }
  }

  /** The scene without camera and render settings, validated; throws an Error in words. */
  values() {
    const info = this.volume();
    if (!info) throw new Error("no volume selected: upload or select one");
    const az = readNumber(this.az, { min: -360, max: 360 });
    const el = readNumber(this.el, { min: -90, max: 90 });
    const medium = {
      density_scale: readNumber(this.density, { min: 0 }),
      albedo: readNumber(this.albedo, { min: 0, max: 1 }),
    };
    const phase = readPhase(this.phase);
    if (phase) medium.phase = phase;
    // the first sun: a directional light, or with "Sun & sky" the model's sun and sky
    const first = this.sunsky.checked
      ? {
          type: "sunsky",
          sun_direction: towardsLight(az, el, this.axes()).map((v) => Math.round(v * 1e5) / 1e5 + 0),
          up: this.axes().up,
          turbidity: readNumber(this.turbidity, { min: 1, max: 10 }),
          sun_scale: readNumber(this.irradiance, { min: 0 }),
          sky_scale: readNumber(this.skyScale, { min: 0 }),
        }
      : sunSpec(az, el, this.irradiance, this.sunColour, this.axes());
    if (first.type === "sunsky" && el < 0) throw new Error("light elevation: the model's sun must be above the horizon (0° or more)");
    const suns = [first];
    this.extraSuns().forEach((row, i) => {
      const n = i + 2;
      const [azIn, elIn, eIn, colour] = $$("input", row);
      suns.push(sunSpec(readNumber(azIn, { min: -360, max: 360 }), readNumber(elIn, { min: -90, max: 90 }), eIn, colour, this.axes(), n));
    });
    const sky = readNumber(this.sky, { min: 0 });
    const all = sky > 0 ? [...suns, { type: "sky", radiance: tinted(this.skyColour.value, sky) }] : [...suns];
    if (this.envSelect.value) all.push({ type: "envmap", id: this.envSelect.value, scale: readNumber(this.envScale, { min: 0 }) });
    if (componentCount(all) > MAX_LIGHTS) {
      throw new Error(`lights: at most ${MAX_LIGHTS} in all, Sun & sky counting 2 (remove a sun, the sky or the map)`);
    }
    // One sun alone: a v1 scene's one light; more lights (or the model's sun and sky): v1.1's
    // lights (the cache holds them apart, so their intensities are not part of it: key())
    const lightPart = all.length > 1 || first.type === "sunsky" ? { lights: all } : { light: suns[0] };
    const volume = info.grid == null ? { id: info.id, grid: densityGrid(info) } : { id: info.id };
    return { volume, medium, ...lightPart, lightPart, quality: this.quality.value };
  }

  /** The lights' intensities, for the real-time view's mix: { suns: [[3] per sun], sky: [3],
   * envmaps: [[3] scale per map] }, in the order of the field's components (cloudgraph/
   * lights.py): a sunsky is a sun (its sun_scale: the field keeps the model's colour, its
   * ``base``) and a map (its sky_scale), each in its place among its kind. */
  mix() {
    try {
      const v = this.values();
      const lights = v.lights || [v.light];
      const rgb = (e) => (Array.isArray(e) ? e : [e, e, e]);
      const sky = lights.find((l) => l.type === "sky");
      const sunOf = (l) => rgb(l.type === "sunsky" ? l.sun_scale : l.irradiance);
      const mapOf = (l) => rgb(l.type === "sunsky" ? l.sky_scale : l.scale);
      return {
        suns: lights.filter((l) => l.type === "directional" || l.type === "sunsky").map(sunOf),
        sky: sky ? sky.radiance : [0, 0, 0],
        envmaps: lights.filter((l) => l.type === "envmap" || l.type === "sunsky").map(mapOf),
      };
    } catch {
      return null;
    }
  }

  /** The rows of the suns after the first. */
  extraSuns() {
    return $$(".sun-row", this.sunList);
  }

  /** Adds a sun row (azimuth, elevation, irradiance, colour, remove); at most MAX_LIGHTS. */
  addSun({ az = 150, el = 40, irradiance = 0.5, colour = "#ffffff" } = {}) {
    if (this.extraSuns().length + 1 >= MAX_LIGHTS) return;
    const n = this.extraSuns().length + 2;
    const number = (value, label, min, max) =>
      h("input", { type: "number", value, min, max, step: "any", "data-label": `sun ${n} ${label}`, title: `sun ${n}'s ${label}` });
    const inputs = [
      number(az, "azimuth", -360, 360),
      number(el, "elevation", -90, 90),
      number(irradiance, "irradiance", 0, undefined),
      h("input", { type: "color", value: colour, title: `sun ${n}'s colour` }),
    ];
    inputs.forEach((input, i) => input.addEventListener(i === 3 ? "input" : "change", () => this.sunsChanged()));
    const remove = h("button", { type: "button", class: "small", title: `remove sun ${n}` }, "×");
    const row = h("div", { class: "sun-row" }, h("span", {}, `Sun ${n}`), ...inputs, remove);
    remove.addEventListener("click", () => {
      row.remove();
      this.renumberSuns();
      this.sunsChanged();
    });
    this.sunList.append(row);
    this.sunsChanged();
    return row;
  }

  /** Labels the sun rows 2, 3, ... in order after a removal. */
  renumberSuns() {
    this.extraSuns().forEach((row, i) => {
      const n = i + 2;
      $("span", row).textContent = `Sun ${n}`;
      const [azIn, elIn, eIn, colour] = $$("input", row);
      [azIn, elIn, eIn].forEach((input, k) => {
        const what = ["azimuth", "elevation", "irradiance"][k];
        input.dataset.label = `sun ${n} ${what}`;
        input.title = `sun ${n}'s ${what}`;
      });
      colour.title = `sun ${n}'s colour`;
      $("button", row).title = `remove sun ${n}`;
    });
  }

  /** The suns changed: the widget shows the others, the add button stops at MAX_LIGHTS. */
  sunsChanged() {
    const others = this.extraSuns().map((row) => {
      const [azIn, elIn] = $$("input", row);
      return { az: Number(azIn.value), el: Number(elIn.value) };
    });
    this.light.setOthers(others.filter((o) => Number.isFinite(o.az) && Number.isFinite(o.el)));
    this.sunAdd.disabled = others.length + 1 >= MAX_LIGHTS;
    this.onChange();
  }

  /** What a radiance cache depends on, as a string (null when the inputs are invalid): for
   * v1.1 lights their kinds, directions and maps only (new intensities are the same cache). */
  key() {
    try {
      const v = this.values();
      const kind = (l) =>
        l.type === "sunsky"
          ? { type: l.type, sun_direction: l.sun_direction, up: l.up, turbidity: l.turbidity }
          : { type: l.type, direction: l.direction, id: l.id };
      const light = v.lights ? v.lights.map(kind) : v.light;
      return JSON.stringify([v.volume, v.medium, light, v.quality]);
    } catch {
      return null;
    }
  }
}
