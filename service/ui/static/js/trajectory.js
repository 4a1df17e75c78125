// The robot's path (docs/design/service.md §1.7): the stored rows' poses (metadata.pose x, y) as one line
// per stream with every few seqs labelled, the localised answers' poses coloured by the place's
// confidence (grey: no place yet) on a dashed line per stream, and a violet link from each revisit's pose to the pose of the place.

import * as A from "./answers.js";
import { level, svg } from "./format.js";
import { COLOURS, STREAM_COLOURS, frame } from "./plot.js";

const LINKS = 64;      // the newest answers drawn as links
const SEQ_LABELS = 12; // about this many seq labels along the stored path

/** Draws into `root`; `stored` [{seq, stream, pose}], `queries` [{e, pose}] oldest first, `poseOf(seq)`
 *  the pose of a stored row or null. Returns a short note for under the picture. */
export function drawTrajectory(root, stored, queries, poseOf) {
  root.replaceChildren();
  const pts = [...stored.map((s) => s.pose), ...queries.map((q) => q.pose)];
  const xs = pts.map((p) => p.x), ys = pts.map((p) => p.y);
  const [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
  const pad = 0.1 * Math.max(x1 / 2 - x0 / 2, y1 / 2 - y0 / 2, 1);  // halves: no overflow at ±1.8e308
  const unit = (pts.find((p) => p.frame_id) || {}).frame_id;
  const { X, Y } = frame(root, [Math.max(x0 - pad, -Number.MAX_VALUE), Math.min(x1 + pad, Number.MAX_VALUE)],
                         [Math.max(y0 - pad, -Number.MAX_VALUE), Math.min(y1 + pad, Number.MAX_VALUE)],
                         { xLabel: `x${unit ? ` (${unit})` : ""}`, yLabel: "y", equal: true });
  const streams = [...new Set(stored.map((s) => s.stream))].sort();
  const every = Math.max(1, Math.ceil(stored.length / SEQ_LABELS));
  for (const [i, name] of streams.entries()) {
    const own = stored.filter((s) => s.stream === name).sort((a, b) => a.seq - b.seq);
    const colour = STREAM_COLOURS[i % STREAM_COLOURS.length];
    root.append(svg("polyline", { points: own.map((s) => `${X(s.pose.x)},${Y(s.pose.y)}`).join(" "),
                                  fill: "none", stroke: colour, "stroke-width": 1.5, opacity: 0.8 }));
    own.forEach((s, k) => {
      root.append(svg("circle", { class: "stored-pose", cx: X(s.pose.x), cy: Y(s.pose.y), r: 2.5, fill: colour }));
      if (k % every === 0 || k === own.length - 1) {
        root.append(svg("text", { class: "seq-label", x: X(s.pose.x) + 5, y: Y(s.pose.y) - 5 }, String(s.seq)));
      }
    });
  }
  const localised = queries.filter((q) => !q.e.reply.learned);
  for (const name of new Set(localised.map((q) => q.e.reply.stream))) {  // each localising robot's own line
    const own = localised.filter((q) => q.e.reply.stream === name);
    root.append(svg("polyline", { points: own.map((q) => `${X(q.pose.x)},${Y(q.pose.y)}`).join(" "), fill: "none",
                                  stroke: COLOURS.none, "stroke-width": 1, "stroke-dasharray": "3 3" }));
  }
  let links = 0;
  for (const q of queries.slice(-LINKS)) {
    const p = A.place(q.e.reply);
    const to = p && p.revisit ? poseOf(p.seq, p) : null;
    if (!to) continue;
    links += 1;
    root.append(svg("line", { class: "revisit-link", x1: X(q.pose.x), y1: Y(q.pose.y), x2: X(to.x), y2: Y(to.y),
                              stroke: COLOURS.revisit, "stroke-width": 2 }));
  }
  for (const q of localised) {
    root.append(svg("circle", { class: "query-pose", cx: X(q.pose.x), cy: Y(q.pose.y), r: 3.5,
                                fill: COLOURS[level(A.confidence(q.e.reply))] }));
  }
  const now = queries[queries.length - 1];
  if (now) {
    const yaw = Number.isFinite(now.pose.yaw) ? now.pose.yaw : null;
    const cx = X(now.pose.x), cy = Y(now.pose.y);
    root.append(svg("circle", { cx, cy, r: 7, fill: "none", stroke: "#ffffff", "stroke-width": 2 }));
    if (yaw !== null) {
      root.append(svg("line", { x1: cx, y1: cy, x2: cx + 14 * Math.cos(yaw), y2: cy - 14 * Math.sin(yaw),
                                stroke: "#ffffff", "stroke-width": 2 }));
    }
  }
  return `${stored.length} stored pose(s) in ${streams.length} stream(s) · ${localised.length} localised ` +
         `pose(s) · ${links} revisit link(s) · white ring: the latest answer's pose and heading.`;
}
