// A plot frame shared by the two pictures: data bounds -> SVG coordinates, grid lines and tick labels.

import { svg } from "./format.js";

export const W = 600, H = 400;
const PAD = { left: 48, right: 12, top: 12, bottom: 34 };

function ticks(lo, hi, count) {
  const span = hi - lo || 1;
  const raw = span / count;
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((f) => f * mag).find((s) => span / s <= count) || 10 * mag;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(+v.toFixed(6));
  return out;
}

/** A frame over [x0, x1] x [y0, y1]; `equal`: one unit is as long on both axes (maps of poses). */
export function frame(root, [x0, x1], [y0, y1], { xLabel, yLabel, equal = false }) {
  if (x1 - x0 < 1e-9) { x0 -= 1; x1 += 1; }
  if (y1 - y0 < 1e-9) { y0 -= 1; y1 += 1; }
  const w = W - PAD.left - PAD.right, h = H - PAD.top - PAD.bottom;
  let sx = w / (x1 - x0), sy = h / (y1 - y0);
  if (equal) {
    const s = Math.min(sx, sy);
    const cx = (x0 + x1) / 2, cy = (y0 + y1) / 2;
    x0 = cx - w / s / 2; x1 = cx + w / s / 2; y0 = cy - h / s / 2; y1 = cy + h / s / 2;
    sx = sy = s;
  }
  const X = (x) => PAD.left + (x - x0) * sx;
  const Y = (y) => PAD.top + h - (y - y0) * sy;
  const g = svg("g");
  for (const t of ticks(x0, x1, 8)) {
    g.append(svg("line", { class: "grid", x1: X(t), x2: X(t), y1: PAD.top, y2: PAD.top + h }),
             svg("text", { x: X(t), y: PAD.top + h + 14, "text-anchor": "middle" }, String(t)));
  }
  for (const t of ticks(y0, y1, 6)) {
    g.append(svg("line", { class: "grid", x1: PAD.left, x2: PAD.left + w, y1: Y(t), y2: Y(t) }),
             svg("text", { x: PAD.left - 6, y: Y(t) + 4, "text-anchor": "end" }, String(t)));
  }
  g.append(svg("rect", { class: "axis", x: PAD.left, y: PAD.top, width: w, height: h, fill: "none" }),
           svg("text", { x: PAD.left + w / 2, y: H - 4, "text-anchor": "middle" }, xLabel),
           svg("text", { x: 12, y: PAD.top + h / 2, "text-anchor": "middle",
                         transform: `rotate(-90 12 ${PAD.top + h / 2})` }, yLabel));
  root.append(g);
  return { X, Y };
}

export const COLOURS = { hi: "#3fb950", mid: "#d29922", lo: "#f85149", none: "#6e7681", revisit: "#bc8cff",
                         learn: "#58a6ff" };
export const STREAM_COLOURS = ["#58a6ff", "#39c5cf", "#e3b341", "#db61a2", "#7ee787", "#ffa657"];
