// The robot's path from the stored rows' poses (metadata.pose x, y), the poses of recent queries, and a
// link from each recent answer's pose to the pose of the place it matched: violet for a revisit of the
// sequence place, dashed grey for a top frame match when the service gives no place.

import * as A from "./answers.js";
import { level, svg } from "./format.js";
import { COLOURS, STREAM_COLOURS, frame } from "./plot.js";

const LINKS = 64;  // the newest answers drawn as links

/** Draws into `root`; returns a short note for under the picture. */
export function drawTrajectory(root, stored, queries, poseOf) {
  root.replaceChildren();
  const pts = [...stored.map((s) => s.pose), ...queries.map((q) => q.pose)];
  const xs = pts.map((p) => p.x), ys = pts.map((p) => p.y);
  const pad = 0.05 * Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), 1);
  const unit = (pts.find((p) => p.frame_id) || {}).frame_id;
  const { X, Y } = frame(root, [Math.min(...xs) - pad, Math.max(...xs) + pad],
                         [Math.min(...ys) - pad, Math.max(...ys) + pad],
                         { xLabel: `x${unit ? ` (${unit})` : ""}`, yLabel: "y", equal: true });
  const streams = [...new Set(stored.map((s) => s.stream))].sort();
  for (const [i, name] of streams.entries()) {
    const own = stored.filter((s) => s.stream === name).sort((a, b) => a.seq - b.seq);
    const colour = STREAM_COLOURS[i % STREAM_COLOURS.length];
    root.append(svg("polyline", { points: own.map((s) => `${X(s.pose.x)},${Y(s.pose.y)}`).join(" "),
                                  fill: "none", stroke: colour, "stroke-width": 1.5, opacity: 0.8 }));
    for (const s of own) root.append(svg("circle", { cx: X(s.pose.x), cy: Y(s.pose.y), r: 2, fill: colour }));
  }
  let links = 0, revisits = 0;
  for (const q of queries.slice(-LINKS)) {
    // With sequence places, only a revisit is a link (a new place links nowhere, whatever the frame
    // matched); without them, the top frame match is drawn dashed.
    const r = q.e.reply;
    const rv = r.place === undefined ? null : Boolean(r.place && r.place.revisit);
    if (rv === false) continue;
    const seq = A.matchedSeq(r);
    const to = seq === null ? null : poseOf(seq);
    if (!to || seq === r.seq) continue;
    links += 1; revisits += rv ? 1 : 0;
    root.append(svg("line", { x1: X(q.pose.x), y1: Y(q.pose.y), x2: X(to.x), y2: Y(to.y),
                              stroke: rv ? COLOURS.revisit : COLOURS.none, "stroke-width": rv ? 1.5 : 1,
                              "stroke-dasharray": rv ? null : "4 3", opacity: 0.9 }));
  }
  for (const q of queries.filter((v) => !v.e.reply.learned)) {
    root.append(svg("circle", { cx: X(q.pose.x), cy: Y(q.pose.y), r: 3,
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
  return `${stored.length} stored pose(s) in ${streams.length} stream(s); ${links} link(s) from recent ` +
         `answers, ${revisits} revisit(s). White ring: the latest answer's pose.`;
}
