// The loop-closure panel: the map's log (GET /v1/maps/{id}/loop-closures), read on from the last id
// seen, the newest first; and its export as a file (fetched with the key, saved from a blob).

import { getBlob, getJson } from "./api.js";
import { closureFrame, el, num, text } from "./format.js";

const PAGE = 500;    // the route's most
const SHOWN = 50;    // rows of the table

/** Read the entries after `log.after` into `log.entries` (kept to the last SHOWN). */
export async function loadClosures(mapId, log) {
  for (let page = 0; page < 20; page += 1) {
    const body = await getJson(`/v1/maps/${encodeURIComponent(mapId)}/loop-closures?after=${log.after}&limit=${PAGE}`);
    for (const c of body.loop_closures) { log.entries.push(c); log.after = Math.max(log.after, c.id); }
    log.entries = log.entries.slice(-SHOWN);
    if (body.next_after === null) return;
  }
}

/** The table body's rows, newest first. */
export function closureRows(log) {
  return [...log.entries].reverse().map((c) => el("tr", { "data-id": c.id },
    el("td", { class: "num" }, num(c.id)),
    el("td", {}, c.created_at.slice(11, 19)),
    el("td", {}, c.stream),
    el("td", { class: "num" }, closureFrame(c)),
    el("td", { class: "num" }, num(c.place.seq)),
    el("td", {}, c.place.stream),
    el("td", {}, text(c.place.label)),
    el("td", { class: "num" }, num(c.confidence, 3)),
    el("td", { class: "num" }, num(c.support)),
    el("td", { class: "num" }, num(c.span))));
}

/** Save the whole log as `format` (csv | jsonl | g2o: the verified closures as edges). */
export async function saveExport(mapId, format) {
  const blob = await getBlob(`/v1/maps/${encodeURIComponent(mapId)}/loop-closures/export?format=${format}`);
  if (!blob) return;
  const a = el("a", { href: URL.createObjectURL(blob), download: `${mapId}-loop-closures.${format}` });
  a.click();
  URL.revokeObjectURL(a.href);
}


