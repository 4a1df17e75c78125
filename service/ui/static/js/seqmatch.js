// The sequence-match picture (docs/design/service.md §1.7): the recent answers in view (x, oldest to
// newest) against stored seqs (y). A learned answer draws a faint square at its own new seq, so a mapping
// run draws the diagonal; an answer with a sequence place draws one dot at the place's seq, green /
// amber / red by confidence, ringed when it is a revisit, so a second pass lands on an earlier part of
// the diagonal. A localised answer without a place (the stream's warm-up) draws a grey dot on the x
// axis; its frame matches are in the table.

import * as A from "./answers.js";
import { level, num, svg } from "./format.js";
import { COLOURS, frame } from "./plot.js";

export function drawSeqMatch(root, answers, map) {
  root.replaceChildren();
  const ys = answers.flatMap((e) => [e.reply.seq, A.placeSeq(e.reply)]).filter((v) => typeof v === "number");
  const top = Math.max(map && map.last_seq ? map.last_seq : 0, ...ys, 1);
  const { X, Y } = frame(root, [-0.5, Math.max(answers.length, 2) - 0.5], [0, top],
                         { xLabel: "recent answer, oldest → newest", yLabel: "stored seq" });
  if (!answers.length) {
    root.append(svg("text", { x: 300, y: 200, "text-anchor": "middle" }, "no answers yet"));
    return;
  }
  answers.forEach((e, i) => {
    const r = e.reply;
    if (typeof r.seq === "number") {
      root.append(svg("rect", { class: "learned-point", x: X(i) - 3, y: Y(r.seq) - 3, width: 6, height: 6,
                                fill: COLOURS.learn, opacity: 0.45 }));
    }
    const p = A.place(r);
    if (!p) {
      if (!r.learned) {
        root.append(svg("circle", { class: "no-place", cx: X(i), cy: Y(0), r: 3, fill: COLOURS.none }));
      }
      return;
    }
    const dot = svg("circle", { cx: X(i), cy: Y(p.seq), r: 4, fill: COLOURS[level(p.confidence)],
                                class: "match-point", "data-seq": p.seq });
    dot.append(svg("title", {}, `${r.stream}: place ${p.seq}, confidence ${num(p.confidence, 2)}`));
    root.append(dot);
    if (p.revisit) {
      root.append(svg("circle", { class: "revisit-ring", cx: X(i), cy: Y(p.seq), r: 7, fill: "none",
                                  stroke: COLOURS.revisit, "stroke-width": 2 }));
    }
  });
}
