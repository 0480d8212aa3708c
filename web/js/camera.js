// An orbit camera around a target: the state behind the viewport and the scene's camera.
// Angles are taken in a frame of three world axes (AXES): ``up``, ``right`` and ``front`` (the
// side a front view looks from). yaw is measured from front towards right (yaw 0: the eye on
// the front side of the target), pitch towards up.

const DEG = Math.PI / 180;
const MAX_PITCH = 89 * DEG;

export const add = (a, b) => a.map((v, i) => v + b[i]);
export const sub = (a, b) => a.map((v, i) => v - b[i]);
export const scale = (a, s) => a.map((v) => v * s);
export const dot = (a, b) => a.reduce((s, v, i) => s + v * b[i], 0);
export const norm = (a) => Math.sqrt(dot(a, a));
export const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
export const normalize = (a) => scale(a, 1 / (norm(a) || 1));

const round = (v) => Math.round(v * 1e4) / 1e4;

/** World frames: y up (OpenVDB, Mitsuba, Houdini) or z up (Blender, front view from -y). */
export const AXES = {
  y: { right: [1, 0, 0], up: [0, 1, 0], front: [0, 0, 1] },
  z: { right: [1, 0, 0], up: [0, 0, 1], front: [0, -1, 0] },
};

/** a * right + b * up + c * front */
export function fromFrame(axes, [a, b, c]) {
  return axes.right.map((_, i) => a * axes.right[i] + b * axes.up[i] + c * axes.front[i]);
}

export class OrbitCamera {
  constructor() {
    this.target = [0, 0, 0];
    this.yaw = 0;
    this.pitch = 0;
    this.distance = 10;
    this.fov = 40;
    this.minDistance = 1e-3;
    this.axes = AXES.y;
  }

  /** Unit vector from the target to the eye. */
  offsetDir() {
    const cp = Math.cos(this.pitch);
    return fromFrame(this.axes, [cp * Math.sin(this.yaw), Math.sin(this.pitch), cp * Math.cos(this.yaw)]);
  }

  eye() {
    return add(this.target, scale(this.offsetDir(), this.distance));
  }

  /** forward (eye to target), right and up of the view, unit vectors. */
  basis() {
    const forward = scale(this.offsetDir(), -1);
    const right = normalize(cross(forward, this.axes.up));
    const up = cross(right, forward);
    return { forward, right, up };
  }

  /** Rotates around the target, in radians. */
  orbit(dYaw, dPitch) {
    this.yaw = (this.yaw + dYaw) % (2 * Math.PI);
    this.pitch = Math.max(-MAX_PITCH, Math.min(MAX_PITCH, this.pitch + dPitch));
  }

  /** Moves towards (factor < 1) or away from (> 1) the target. */
  zoom(factor) {
    this.distance = Math.max(this.minDistance, this.distance * factor);
  }

  /** Moves the target in the view plane; dx, dy in fractions of the view's width/height. */
  pan(dx, dy) {
    const { right, up } = this.basis();
    const span = 2 * this.distance * Math.tan((this.fov * DEG) / 2);
    this.target = add(this.target, add(scale(right, -dx * span), scale(up, dy * span)));
  }

  /** Moves eye and target together along the view's forward, right and world up, in world units. */
  fly(forward, right, up) {
    const b = this.basis();
    const move = add(add(scale(b.forward, forward), scale(b.right, right)), scale(this.axes.up, up));
    this.target = add(this.target, move);
  }

  /** Frames a world bounding box [[x0,y0,z0],[x1,y1,z1]] from the front, slightly above: the
   * nearest distance at which all eight corners are in view, plus a margin. */
  frame(bbox) {
    const [lo, hi] = bbox;
    this.target = scale(add(lo, hi), 0.5);
    this.yaw = 0;
    this.pitch = 10 * DEG;
    const { forward, right, up } = this.basis();
    const t = Math.tan((this.fov * DEG) / 2);
    let d = 0;
    for (let i = 0; i < 8; i++) {
      const c = sub([i & 1 ? hi[0] : lo[0], i & 2 ? hi[1] : lo[1], i & 4 ? hi[2] : lo[2]], this.target);
      const z = dot(c, forward);
      d = Math.max(d, Math.abs(dot(c, right)) / t - z, Math.abs(dot(c, up)) / t - z);
    }
    const radius = norm(sub(hi, lo)) / 2 || 1;
    this.distance = Math.max(d * 1.08, radius * 0.1);
    this.minDistance = radius * 1e-3;
    this.home = this.save();
  }

  save() {
    return {
      target: [...this.target],
      yaw: this.yaw,
      pitch: this.pitch,
      distance: this.distance,
      fov: this.fov,
      axes: this.axes,
    };
  }

  restore(s) {
    Object.assign(this, { ...s, target: [...s.target] });
  }

  /** The scene spec's camera at a resolution. */
  spec(width, height = width) {
    return {
      eye: this.eye().map(round),
      target: this.target.map(round),
      up: [...this.axes.up],
      fov: this.fov,
      width,
      height,
    };
  }

  /** Yaw and pitch in degrees, for people. */
  describe() {
    const e = this.eye();
    return `eye (${e.map((v) => v.toFixed(1)).join(", ")}) · yaw ${(this.yaw / DEG).toFixed(0)}° · pitch ${(this.pitch / DEG).toFixed(0)}°`;
  }
}
