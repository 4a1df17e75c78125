// What the panels read from one recent answer ({received_at, reply}); each field may be missing on a
// service that does not send it yet (`undefined`), or be null (sent, but no value).

export function place(reply) { return reply.place; }

export function topMatch(reply) { return reply.matches && reply.matches.length ? reply.matches[0] : null; }

/** The stored seq the answer points at: the sequence place on a service that sends places (null: no
 *  place), else the top frame match. */
export function matchedSeq(reply) {
  if (reply.place !== undefined) return reply.place ? reply.place.seq : null;
  const m = topMatch(reply);
  return m ? m.seq : null;
}

/** 0..1 for the same answer: the place's confidence, else the top match's score (Dice); or null. */
export function confidence(reply) {
  if (reply.place !== undefined) return reply.place ? reply.place.confidence : null;
  const m = topMatch(reply);
  return m ? m.score : null;
}

/** true / false from the sequence place; null when the service gives no place. */
export function revisit(reply) {
  const p = reply.place;
  return p && typeof p.revisit === "boolean" ? p.revisit : null;
}

export function pose(metadata) {
  const p = metadata && metadata.pose;
  return p && Number.isFinite(p.x) && Number.isFinite(p.y) ? p : null;
}
