// Formatting shared by the panels: one spelling of "no value" and of sizes, scores and times.

export const NONE = "—";

export function num(v, digits = 0) {
  return typeof v === "number" && Number.isFinite(v) ? v.toFixed(digits) : NONE;
}

/** A number as JavaScript spells it exactly (the shortest that reads back the same: 0.95, 0.9496), where
 * rounding would hide the value that decides something, like a revisit threshold. */
export function exact(v) {
  return typeof v === "number" && Number.isFinite(v) ? String(v) : NONE;
}

/** `v` with `digits` decimals, or as many more as it takes to stay on its own side of `threshold`:
 * 0.9496 beside a threshold of 0.95 reads "0.9496", never "0.95". */
export function beside(v, threshold, digits = 2) {
  if (typeof v !== "number" || !Number.isFinite(v)) return NONE;
  if (typeof threshold !== "number" || !Number.isFinite(threshold)) return v.toFixed(digits);
  for (let d = digits; d <= 15; d += 1) {
    const shown = v.toFixed(d);
    if ((Number(shown) >= threshold) === (v >= threshold)) return shown;
  }
  return exact(v);
}

export function bytes(v) {
  if (typeof v !== "number" || !Number.isFinite(v)) return NONE;
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (v >= 1024 && i < units.length - 1) { v /= 1024; i += 1; }
  return `${v.toFixed(i === 0 ? 0 : 1)} ${units[i]}`;
}

/** A logged loop closure's frame: its row, else "visit" (a learning stream's consolidated frame, which
 * joined row `consolidated_into`) or "localising" (a localising stream's: no row at all); a retraction
 * entry (a repair withdrew closure `retracts`) says so. */
export function closureFrame(c) {
  if (c.retracts !== null && c.retracts !== undefined) return `retracts ${num(c.retracts)}`;
  if (c.seq !== null && c.seq !== undefined) return num(c.seq);
  return c.consolidated_into !== null && c.consolidated_into !== undefined ? "visit" : "localising";
}

export function text(v) { return v === null || v === undefined || v === "" ? NONE : String(v); }

export function clock(iso) {
  const d = new Date(iso);
  return Number.isNaN(d.getTime()) ? NONE : d.toLocaleTimeString([], { hour12: false }) +
    "." + String(d.getMilliseconds()).padStart(3, "0");
}

/** Confidence class: hi (confident), mid (unsure), lo (weak); none without a value. */
export function level(v) {
  if (typeof v !== "number" || !Number.isFinite(v)) return "none";
  return v >= 0.7 ? "hi" : v >= 0.4 ? "mid" : "lo";
}

/** An element with attributes and children (strings become text nodes). */
export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    // A style through the CSSOM: the page's Content-Security-Policy refuses style attributes.
    if (k === "class") node.className = v;
    else if (k === "style") node.style.cssText = String(v);
    else node.setAttribute(k, v === true ? "" : String(v));
  }
  for (const c of children) if (c !== null && c !== undefined) node.append(c);
  return node;
}

// The SVG namespace is taken from the page's own <svg> elements, so the shipped files name no URL at all.
export function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(document.querySelector("svg").namespaceURI, tag);
  for (const [k, v] of Object.entries(attrs)) if (v !== null && v !== undefined) node.setAttribute(k, String(v));
  for (const c of children) if (c !== null && c !== undefined) node.append(c);
  return node;
}
