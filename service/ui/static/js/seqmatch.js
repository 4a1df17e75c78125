// The sequence-match picture of one stream: each recent answer (x, oldest to newest) against the stored
// seq it matched (y), coloured by confidence; a revisit is ringed; a learned answer's own seq is a faint
// square, so a mapping run draws the diagonal and a revisit lands on an earlier part of it.

import * as A from "./answers.js";
import { level, svg } from "./format.js";
import { COLOURS, frame } from "./plot.js";

export function drawSeqMatch(root, answers, map) {
  root.replaceChildren();
  const ys = [];
  for (const e of answers) {
    if (typeof e.reply.seq === "number") ys.push(e.reply.seq);
    const m = A.matchedSeq(e.reply);
    if (m !== null) ys.push(m);
  }
  const top = Math.max(map && map.last_seq ? map.last_seq : 0, ...ys, 1);
  const { X, Y } = frame(root, [-0.5, Math.max(answers.length, 2) - 0.5], [0, top],
                         { xLabel: "query: recent answer of the stream, oldest → newest", yLabel: "matched seq" });
  if (!answers.length) {
    root.append(svg("text", { x: 300, y: 200, "text-anchor": "middle" }, "no answers yet"));
    return;
  }
  answers.forEach((e, i) => {
    const r = e.reply;
    if (typeof r.seq === "number") {
      root.append(svg("rect", { x: X(i) - 3, y: Y(r.seq) - 3, width: 6, height: 6, fill: COLOURS.learn,
                                opacity: 0.35 }));
    }
    const m = A.matchedSeq(r);
    if (m === null) return;
    const dot = svg("circle", { cx: X(i), cy: Y(m), r: 4, fill: COLOURS[level(A.confidence(r))],
                                class: "match-point", "data-seq": m });
    dot.append(svg("title", {}, `answer ${i}: seq ${m}, confidence ${A.confidence(r)?.toFixed(3)}`));
    root.append(dot);
    if (A.revisit(r)) {
      root.append(svg("circle", { cx: X(i), cy: Y(m), r: 7, fill: "none", stroke: COLOURS.revisit,
                                  "stroke-width": 2 }));
    }
  });
}
