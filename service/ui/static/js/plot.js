// A plot frame shared by the two pictures: data bounds -> SVG coordinates, grid lines and tick labels.

import { svg } from "./format.js";

export const W = 600, H = 400;
const PAD = { left: 48, right: 12, top: 12, bottom: 34 };

/** Round values in [lo, hi], about `count` of them; bounded for any finite lo <= hi: the ticks are
 *  counted by index (never `v += step`, which stalls once step is below the spacing of doubles at v). */
export function ticks(lo, hi, count) {
  if (!Number.isFinite(lo) || !Number.isFinite(hi) || hi < lo) return [];
  const raw = hi / count - lo / count;  // span / count without overflowing at ±1.8e308
  if (!(raw > 0)) return [lo];
  const mag = 10 ** Math.floor(Math.log10(raw));
  const step = [1, 2, 5, 10].map((f) => f * mag).find((s) => hi / s - lo / s <= count) || 10 * mag;
  const first = Math.ceil(lo / step - 1e-9), n = Math.min(Math.floor(hi / step + 1e-9) - first, 2 * count);
  const out = [];
  for (let i = 0; i <= n; i += 1) {
    const v = Number(((first + i) * step).toPrecision(12));
    if (out.length === 0 || v > out[out.length - 1]) out.push(v);  // equal once below the doubles' spacing
  }
  return out;
}

/** [lo, hi] widened to a span the doubles can draw at its magnitude (a single point, or 1e16 +- 1). */
function widen(lo, hi) {
  const d = Math.max(1, 1e-6 * Math.max(Math.abs(lo), Math.abs(hi)));
  return hi - lo >= d * 1e-3 ? [lo, hi] : [Math.max(lo - d, -Number.MAX_VALUE), Math.min(hi + d, Number.MAX_VALUE)];
}

/** A frame over [x0, x1] x [y0, y1]; `equal`: one unit is as long on both axes (maps of poses). Any
 *  finite bounds: coordinates are halved first where a span would overflow (±1.8e308). */
export function frame(root, [x0, x1], [y0, y1], { xLabel, yLabel, equal = false }) {
  [x0, x1] = widen(x0, x1);
  [y0, y1] = widen(y0, y1);
  const k = Number.isFinite(x1 - x0) && Number.isFinite(y1 - y0) ? 1 : 0.5;
  const w = W - PAD.left - PAD.right, h = H - PAD.top - PAD.bottom;
  let sx = w / (k * x1 - k * x0), sy = h / (k * y1 - k * y0);
  if (equal) {
    const s = Math.min(sx, sy);
    const cx = x0 / 2 + x1 / 2, cy = y0 / 2 + y1 / 2;
    const M = Number.MAX_VALUE, half = (n) => n / s / 2 / k;
    [x0, x1, y0, y1] = [cx - half(w), cx + half(w), cy - half(h), cy + half(h)].map((v) => Math.min(Math.max(v, -M), M));
    sx = sy = s;
  }
  const X = (x) => PAD.left + (k * x - k * x0) * sx;
  const Y = (y) => PAD.top + h - (k * y - k * y0) * sy;
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
