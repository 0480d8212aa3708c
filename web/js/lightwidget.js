// The light's direction as azimuth and elevation of the sun, drawn from above on a small canvas:
// the rim is the horizon, the centre straight overhead, the right axis to the right and the
// front (the default camera's side) at the bottom. Click or drag to set it. The arrow is the
// way the light travels; the blue dot is the camera's side; small dots are the other suns.

import { AXES, dot, fromFrame } from "./camera.js";

const DEG = Math.PI / 180;

/** Unit vector towards the sun: azimuth from front towards right, elevation above the ground. */
export function towardsLight(azDeg, elDeg, axes = AXES.y) {
  const az = azDeg * DEG;
  const el = elDeg * DEG;
  return fromFrame(axes, [Math.cos(el) * Math.sin(az), Math.sin(el), Math.cos(el) * Math.cos(az)]);
}

/** The scene spec's light.direction: the way the light travels (towards the scene). */
export function lightDirection(azDeg, elDeg, axes = AXES.y) {
  return towardsLight(azDeg, elDeg, axes).map((v) => Math.round(-v * 1e5) / 1e5 + 0);
}

/** Azimuth and elevation in degrees of a light.direction vector. */
export function anglesOf(direction, axes = AXES.y) {
  const t = direction.map((v) => -v);
  const r = Math.hypot(...t) || 1;
  return {
    az: Math.atan2(dot(t, axes.right), dot(t, axes.front)) / DEG,
    el: Math.asin(dot(t, axes.up) / r) / DEG,
  };
}

function axisName(v) {
  const i = v.findIndex((c) => c !== 0);
  return `${v[i] > 0 ? "+" : "−"}${"xyz"[i]}`;
}

export class LightWidget {
  constructor(canvas, onInput, onCommit) {
    this.canvas = canvas;
    this.onInput = onInput;
    this.onCommit = onCommit;
    this.az = 0;
    this.el = 45;
    this.cameraYaw = null;
    this.others = []; // the other suns, { az, el }: drawn, not edited here
    this.axes = AXES.y;
    this.dragging = false;
    canvas.addEventListener("pointerdown", (e) => {
      this.dragging = true;
      canvas.setPointerCapture(e.pointerId);
      this.pick(e);
    });
    canvas.addEventListener("pointermove", (e) => this.dragging && this.pick(e));
    const end = (e) => {
      if (!this.dragging) return;
      this.dragging = false;
      if (canvas.hasPointerCapture(e.pointerId)) canvas.releasePointerCapture(e.pointerId);
      this.onCommit(this.az, this.el);
    };
    canvas.addEventListener("pointerup", end);
    canvas.addEventListener("pointercancel", end);
    this.draw();
  }

  geometry() {
    const w = this.canvas.width;
    const h = this.canvas.height;
    return { cx: w / 2, cy: h / 2, R: Math.min(w, h) / 2 - 14 };
  }

  pick(e) {
    const rect = this.canvas.getBoundingClientRect();
    const { cx, cy, R } = this.geometry();
    const x = ((e.clientX - rect.left) / rect.width) * this.canvas.width - cx;
    const y = ((e.clientY - rect.top) / rect.height) * this.canvas.height - cy;
    const r = Math.min(1, Math.hypot(x, y) / R);
    this.az = Math.round(Math.atan2(x, y) / DEG);
    this.el = Math.round(90 * (1 - r));
    this.draw();
    this.onInput(this.az, this.el);
  }

  set(az, el) {
    this.az = az;
    this.el = el;
    this.draw();
  }

  setAxes(axes) {
    this.axes = axes;
    this.draw();
  }

  /** The other suns' { az, el } (degrees), drawn as small dots. */
  setOthers(list) {
    this.others = list;
    this.draw();
  }

  setCamera(yawRad) {
    this.cameraYaw = yawRad;
    this.draw();
  }

  draw() {
    const ctx = this.canvas.getContext("2d");
    const { cx, cy, R } = this.geometry();
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.fillStyle = "#10161f";
    ctx.beginPath();
    ctx.arc(cx, cy, R, 0, 2 * Math.PI);
    ctx.fill();
    ctx.strokeStyle = "#3b4a5e";
    ctx.lineWidth = 1;
    for (const el of [0, 30, 60]) {
      ctx.beginPath();
      ctx.arc(cx, cy, R * (1 - el / 90), 0, 2 * Math.PI);
      ctx.stroke();
    }
    ctx.beginPath();
    ctx.moveTo(cx - R, cy);
    ctx.lineTo(cx + R, cy);
    ctx.moveTo(cx, cy - R);
    ctx.lineTo(cx, cy + R);
    ctx.stroke();
    ctx.fillStyle = "#7f8ea3";
    ctx.font = "10px sans-serif";
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    const { right, front } = this.axes;
    ctx.fillText(axisName(right), cx + R + 8, cy);
    ctx.fillText(axisName(right.map((v) => -v)), cx - R - 8, cy);
    ctx.fillText(axisName(front), cx, cy + R + 8);
    ctx.fillText(axisName(front.map((v) => -v)), cx, cy - R - 8);

    if (this.cameraYaw != null) {
      // the camera's side, on the rim
      const px = cx + R * Math.sin(this.cameraYaw);
      const py = cy + R * Math.cos(this.cameraYaw);
      ctx.fillStyle = "#5aa0ff";
      ctx.beginPath();
      ctx.arc(px, py, 4, 0, 2 * Math.PI);
      ctx.fill();
    }

    ctx.fillStyle = "#c9a14a";
    for (const o of this.others) {
      const ro = R * Math.min(1.15, 1 - o.el / 90);
      ctx.beginPath();
      ctx.arc(cx + ro * Math.sin(o.az * DEG), cy + ro * Math.cos(o.az * DEG), 4, 0, 2 * Math.PI);
      ctx.fill();
    }

    const r = R * Math.min(1.15, 1 - this.el / 90);
    const sx = cx + r * Math.sin(this.az * DEG);
    const sy = cy + r * Math.cos(this.az * DEG);
    // the light travels from the sun towards the centre
    ctx.strokeStyle = "#ffcf5a";
    ctx.fillStyle = "#ffcf5a";
    ctx.lineWidth = 2;
    const len = Math.hypot(cx - sx, cy - sy);
    if (len > 10) {
      const ux = (cx - sx) / len;
      const uy = (cy - sy) / len;
      const ex = cx - ux * 4;
      const ey = cy - uy * 4;
      ctx.beginPath();
      ctx.moveTo(sx + ux * 8, sy + uy * 8);
      ctx.lineTo(ex, ey);
      ctx.stroke();
      ctx.beginPath();
      ctx.moveTo(ex, ey);
      ctx.lineTo(ex - ux * 8 - uy * 4, ey - uy * 8 + ux * 4);
      ctx.lineTo(ex - ux * 8 + uy * 4, ey - uy * 8 - ux * 4);
      ctx.closePath();
      ctx.fill();
    } else {
      ctx.beginPath();
      ctx.arc(cx, cy, 3, 0, 2 * Math.PI);
      ctx.fill();
    }
    ctx.beginPath();
    ctx.arc(sx, sy, 6, 0, 2 * Math.PI);
    ctx.fill();
  }
}
