// Pixels: PNG blobs to ImageData, sRGB to linear, and the mean absolute error of two images.

const SRGB_TO_LINEAR = new Float32Array(256);
for (let i = 0; i < 256; i++) {
  const c = i / 255;
  SRGB_TO_LINEAR[i] = c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4;
}

export function srgbToLinear(byte) {
  return SRGB_TO_LINEAR[byte];
}

/** The sRGB byte of a linear value (clamped to [0, 1]), as the server's PNGs have it. */
export function linearToSrgb8(x) {
  const c = x <= 0.0031308 ? 12.92 * x : 1.055 * x ** (1 / 2.4) - 0.055;
  return Math.max(0, Math.min(255, Math.round(c * 255)));
}

/** The pixels of an image blob (a PNG), as ImageData at the image's own size. */
export async function imageDataOf(blob) {
  const bitmap = await createImageBitmap(blob, { colorSpaceConversion: "none", premultiplyAlpha: "none" });
  const canvas = document.createElement("canvas");
  canvas.width = bitmap.width;
  canvas.height = bitmap.height;
  const ctx = canvas.getContext("2d", { willReadFrequently: true });
  ctx.drawImage(bitmap, 0, 0);
  bitmap.close();
  return ctx.getImageData(0, 0, canvas.width, canvas.height);
}

/**
 * Compares an image with a reference (same size), on linear values (sRGB undone), RGB only.
 * Returns { mae, refMean, testMean, relative (mae / refMean), diff (per-pixel mean |a-b|),
 * fgMean (the reference's mean over pixels where either image is not black) }.
 */
export function compareImages(test, ref) {
  if (test.width !== ref.width || test.height !== ref.height) {
    throw new Error(`the images differ in size (${test.width}×${test.height} and ${ref.width}×${ref.height})`);
  }
  const n = test.width * test.height;
  const a = test.data;
  const b = ref.data;
  const diff = new Float32Array(n);
  let sumAbs = 0;
  let sumRef = 0;
  let sumTest = 0;
  let fgSum = 0;
  let fgCount = 0;
  for (let p = 0; p < n; p++) {
    let d = 0;
    let ys = 0;
    let xs = 0;
    for (let c = 0; c < 3; c++) {
      const x = SRGB_TO_LINEAR[a[4 * p + c]];
      const y = SRGB_TO_LINEAR[b[4 * p + c]];
      d += Math.abs(x - y);
      ys += y;
      xs += x;
    }
    diff[p] = d / 3;
    sumAbs += d;
    sumRef += ys;
    sumTest += xs;
    if (xs > 0 || ys > 0) {
      fgSum += ys / 3;
      fgCount++;
    }
  }
  const mae = sumAbs / (3 * n);
  const refMean = sumRef / (3 * n);
  return {
    mae,
    refMean,
    testMean: sumTest / (3 * n),
    relative: refMean > 0 ? mae / refMean : NaN,
    diff,
    fgMean: fgCount ? fgSum / fgCount : 0,
  };
}

/** A heat map of per-pixel differences: black 0, red, then yellow at ``full``. */
export function heatmap(diff, width, height, full) {
  const out = new ImageData(width, height);
  for (let p = 0; p < diff.length; p++) {
    const t = Math.min(1, diff[p] / (full || 1));
    out.data[4 * p] = Math.round(255 * Math.min(1, 2 * t));
    out.data[4 * p + 1] = Math.round(255 * Math.max(0, 2 * t - 1));
    out.data[4 * p + 2] = 0;
    out.data[4 * p + 3] = 255;
  }
  return out;
}
