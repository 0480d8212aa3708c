// The status line and the error list: every failure the page meets ends up here, in words.

import { h, setText } from "./dom.js";
import { describeError, isAbort } from "./api.js";

const MAX_ERRORS = 6;

export class StatusArea {
  constructor(line, errors) {
    this.line = line;
    this.errors = errors;
  }

  info(message) {
    setText(this.line, message);
    this.line.classList.remove("warn");
  }

  /** Shows an error (an Error or a sentence); ``context`` prefixes it when given. Aborts are not errors. */
  error(err, context = "") {
    if (isAbort(err)) return;
    const text = (context ? `${context}: ` : "") + describeError(err);
    console.warn(text, err);
    const item = h(
      "li",
      { class: "error" },
      h("span", { class: "msg" }, text),
      h("button", { type: "button", class: "dismiss", title: "Dismiss", "aria-label": "Dismiss" }, "×"),
    );
    item.querySelector("button").addEventListener("click", () => {
      item.remove();
      this.errors.hidden = !this.errors.children.length;
    });
    this.errors.prepend(item);
    while (this.errors.children.length > MAX_ERRORS) this.errors.lastElementChild.remove();
    this.errors.hidden = false;
  }

  clearErrors() {
    this.errors.replaceChildren();
    this.errors.hidden = true;
  }
}
