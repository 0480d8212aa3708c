// Mouse and keyboard on the viewport: left-drag orbits, right-drag or shift-drag pans, the wheel
// zooms, WASD / arrow keys fly (Q/E or PageDown/PageUp down and up). Calls onChange() on
// every camera change.

const ORBIT_RAD_PER_PX = 0.008;
const FLY_KEYS = {
  KeyW: [1, 0, 0],
  ArrowUp: [1, 0, 0],
  KeyS: [-1, 0, 0],
  ArrowDown: [-1, 0, 0],
  KeyA: [0, -1, 0],
  ArrowLeft: [0, -1, 0],
  KeyD: [0, 1, 0],
  ArrowRight: [0, 1, 0],
  KeyE: [0, 0, 1],
  PageUp: [0, 0, 1],
  KeyQ: [0, 0, -1],
  PageDown: [0, 0, -1],
};

export class Controls {
  constructor(element, camera, onChange) {
    this.el = element;
    this.camera = camera;
    this.onChange = onChange;
    this.drag = null;
    this.keys = new Set();
    this.lastFrame = 0;
    this.enabled = true;

    element.addEventListener("pointerdown", (e) => this.down(e));
    element.addEventListener("pointermove", (e) => this.move(e));
    element.addEventListener("pointerup", (e) => this.up(e));
    element.addEventListener("pointercancel", (e) => this.up(e));
    element.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
    element.addEventListener("contextmenu", (e) => e.preventDefault());
    element.addEventListener("keydown", (e) => this.keydown(e));
    element.addEventListener("keyup", (e) => this.keys.delete(e.code));
    element.addEventListener("blur", () => this.keys.clear());
  }

  down(e) {
    if (!this.enabled) return;
    this.el.focus({ preventScroll: true });
    const pan = e.button === 2 || e.button === 1 || e.shiftKey;
    if (e.button !== 0 && !pan) return;
    this.drag = { x: e.clientX, y: e.clientY, pan, id: e.pointerId };
    this.el.setPointerCapture(e.pointerId);
    this.el.classList.add(pan ? "panning" : "orbiting");
    e.preventDefault();
  }

  move(e) {
    if (!this.drag || e.pointerId !== this.drag.id) return;
    const dx = e.clientX - this.drag.x;
    const dy = e.clientY - this.drag.y;
    if (!dx && !dy) return;
    this.drag.x = e.clientX;
    this.drag.y = e.clientY;
    if (this.drag.pan) {
      const r = this.el.getBoundingClientRect();
      this.camera.pan(dx / r.width, dy / r.height);
    } else {
      this.camera.orbit(-dx * ORBIT_RAD_PER_PX, dy * ORBIT_RAD_PER_PX);
    }
    this.onChange();
  }

  up(e) {
    if (!this.drag || e.pointerId !== this.drag.id) return;
    this.drag = null;
    this.el.classList.remove("panning", "orbiting");
    if (this.el.hasPointerCapture(e.pointerId)) this.el.releasePointerCapture(e.pointerId);
  }

  wheel(e) {
    if (!this.enabled) return;
    e.preventDefault();
    const lines = e.deltaMode === 1 ? e.deltaY * 30 : e.deltaMode === 2 ? e.deltaY * 300 : e.deltaY;
    this.camera.zoom(Math.exp(Math.max(-500, Math.min(500, lines)) * 0.0015));
    this.onChange();
  }

  keydown(e) {
    if (!this.enabled || !(e.code in FLY_KEYS) || e.ctrlKey || e.metaKey || e.altKey) return;
    e.preventDefault();
    const wasIdle = this.keys.size === 0;
    if (e.repeat && this.keys.has(e.code)) return;
    this.keys.add(e.code);
    this.step(1 / 30); // a tap moves too, even if released before the next frame
    if (wasIdle) {
      this.lastFrame = performance.now();
      requestAnimationFrame((t) => this.fly(t));
    }
  }

  /** Moves by the pressed keys for ``dt`` seconds, at half the orbit distance a second. */
  step(dt) {
    const speed = this.camera.distance * 0.5;
    const v = [0, 0, 0];
    for (const code of this.keys) FLY_KEYS[code].forEach((c, i) => (v[i] += c));
    if (v.some((c) => c !== 0)) {
      this.camera.fly(v[0] * speed * dt, v[1] * speed * dt, v[2] * speed * dt);
      this.onChange();
    }
  }

  fly(now) {
    if (!this.keys.size) return;
    const dt = Math.min(0.1, Math.max(0, (now - this.lastFrame) / 1000)) || 1 / 60;
    this.lastFrame = now;
    this.step(dt);
    requestAnimationFrame((t) => this.fly(t));
  }
}
