// What the panels read from one recent answer ({received_at, reply}, the reply as the service sent it:
// docs/design/service.md §1.2). `place` is null during a stream's warm-up and `metadata` when none was
// posted; a missing field reads as null, so the page shows "—" instead of failing.

/** The sequence place of the answer, or null (warm-up, or nothing stored yet). */
export function place(reply) { return reply.place ?? null; }

export function topMatch(reply) { return reply.matches && reply.matches.length ? reply.matches[0] : null; }

/** The stored seq the answer is at: its sequence place's, or null. */
export function placeSeq(reply) { return place(reply) ? place(reply).seq : null; }

/** The place's confidence in [0, 1], or null. */
export function confidence(reply) { return place(reply) ? place(reply).confidence : null; }

/** true when the place is a revisit (confidence >= the map's revisit_threshold). */
export function revisit(reply) { return Boolean(place(reply) && place(reply).revisit); }

/** `metadata.pose` when it has finite x and y, else null. */
export function pose(metadata) {
  const p = metadata && metadata.pose;
  return p && Number.isFinite(p.x) && Number.isFinite(p.y) ? p : null;
}
