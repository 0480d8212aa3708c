// DOM helpers. User and server text only ever reaches the page as text nodes (textContent) or
// through escapeHtml, never as markup.

const ESCAPES = { "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" };

export function escapeHtml(text) {
  return String(text).replace(/[&<>"']/g, (c) => ESCAPES[c]);
}

export function $(selector, root = document) {
  const el = root.querySelector(selector);
  if (!el) throw new Error(`the page has no element ${selector}`);
  return el;
}

/** Every element under ``root`` that matches ``selector``, as an array. */
export function $$(selector, root = document) {
  return Array.from(root.querySelectorAll(selector));
}

/** An element with properties/attributes and children (strings become text nodes). */
export function h(tag, props = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(props)) {
    if (v == null || v === false) continue;
    if (k === "class") el.className = v;
    else if (k === "dataset") Object.assign(el.dataset, v);
    else if (k.startsWith("on") && typeof v === "function") el.addEventListener(k.slice(2), v);
    else if (k in el && typeof v !== "string") el[k] = v;
    else el.setAttribute(k, v === true ? "" : String(v));
  }
  for (const c of children.flat()) {
    if (c == null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

export function setText(el, text) {
  el.textContent = text == null ? "" : String(text);
}

export function formatBytes(n) {
  if (!Number.isFinite(n)) return "–";
  const units = ["B", "KiB", "MiB", "GiB"];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) {
    n /= 1024;
    i++;
  }
  return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
}

export function formatSeconds(s) {
  if (!Number.isFinite(s)) return "–";
  return s < 1 ? `${Math.round(s * 1000)} ms` : `${s.toFixed(2)} s`;
}

/** A number from an input, or an error naming the field. */
export function readNumber(input, { min = -Infinity, max = Infinity, integer = false } = {}) {
  const label = input.dataset.label || input.name || input.id;
  const v = Number(input.value);
  if (input.value.trim() === "" || !Number.isFinite(v)) throw new Error(`${label}: enter a number`);
  if (integer && !Number.isInteger(v)) throw new Error(`${label}: enter a whole number`);
  if (v < min || v > max) throw new Error(`${label}: must be between ${min} and ${max}`);
  return v;
}
