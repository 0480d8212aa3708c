// Adaptive quality of the moving camera: a ladder of (internal size, march step) levels ordered
// by cost (pixels / step), and a controller that picks the level whose measured frame time
// holds the budget. At rest the view is drawn at full size with the field's own step.

export const BUDGET_MS = 16;
export const MIN_SIZE = 128;
const MAX_STEP_SCALE = 32; // (a forward-scattering field at 128 px takes 15-30 on a software GPU)

/** Levels from the full size down: size shrinks to 256 px, then the step doubles, then size
 * shrinks to MIN_SIZE, then the step grows to MAX_STEP_SCALE. Each { size, stepScale, cost }. */
export function ladder(full) {
  const levels = [];
  const push = (size, stepScale) => {
    const s = Math.max(MIN_SIZE, Math.min(full, Math.round(size / 8) * 8));
    levels.push({ size: s, stepScale, cost: (s * s) / stepScale });
  };
  let size = full;
  for (; size > 256; size *= 0.85) push(size, 1);
  push(Math.min(full, 256), 1);
  push(Math.min(full, 256), 1.5);
  for (size = Math.min(full, 256); size > MIN_SIZE; size *= 0.85) push(size, 2);
  for (let s = 2; s <= MAX_STEP_SCALE; s *= 1.25) push(MIN_SIZE, Math.round(s * 4) / 4);
  levels.sort((a, b) => b.cost - a.cost);
  return levels.filter((l, i) => i === 0 || l.cost < levels[i - 1].cost);
}

const VSYNC_MS = 1000 / 60;
// A frame that keeps pace with the display says only that it cost less than one refresh: the
// cost per pixel is then lowered a little each time, so that the level creeps up until a frame
// takes longer than the display and the measured cost holds it there.
const CREEP = 0.93;

export class QualityController {
  /** full: the viewport's size in device pixels. */
  constructor(full, budgetMs = BUDGET_MS) {
    this.budget = budgetMs;
    this.msPerCost = NaN; // measured milliseconds per unit of cost (pixel / step)
    this.resize(full);
  }

  resize(full) {
    this.full = full;
    this.levels = ladder(full);
  }

  /** The costliest level expected to hold the budget (the budget is at least one refresh). */
  current() {
    if (!Number.isFinite(this.msPerCost)) return this.levels[this.levelFor(256 * 256)];
    return this.levels[this.levelFor((1.15 * Math.max(this.budget, VSYNC_MS)) / this.msPerCost)];
  }

  /** The index of the costliest level that costs at most ``cost``. */
  levelFor(cost) {
    const i = this.levels.findIndex((l) => l.cost <= cost);
    return i < 0 ? this.levels.length - 1 : i;
  }

  /** Reports that a frame of ``cost`` (pixels / step, x1.6 for the exact march) took ``ms``. */
  report(ms, cost) {
    if (!(ms > 0) || !(cost > 0)) return;
    const rate = ms / cost;
    if (!Number.isFinite(this.msPerCost)) this.msPerCost = rate;
    else if (ms < 1.2 * VSYNC_MS) this.msPerCost = Math.min(this.msPerCost, rate) * CREEP;
    else this.msPerCost = 0.5 * this.msPerCost + 0.5 * rate;
  }

  /** Rows of a strip of ``width`` px of the exact march that fit two frames' budget (at rest
   * a strip only delays the reaction to the next move, by at most that). */
  rowsFor(width, exactFactor) {
    if (!Number.isFinite(this.msPerCost)) return 16;
    return Math.floor((2 * Math.max(this.budget, VSYNC_MS)) / (this.msPerCost * width * exactFactor));
  }
}
