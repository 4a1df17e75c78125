// The map viewer: polls the API and redraws four panels (maps, recent answers, trajectory, sequence
// match). Selecting a map: click its row, or open /ui/?map=ID.

import { apiKey, getImageUrl, getJson, HttpError, setApiKey } from "./api.js";
import * as A from "./answers.js";
import { closureRows, loadClosures, saveExport } from "./closures.js";
import { NONE, beside, bytes, clock, el, exact, level, num, text } from "./format.js";
import { drawSeqMatch } from "./seqmatch.js";
import { drawTrajectory } from "./trajectory.js";

const POLL_MS = 2000;         // the recent answers and the map list
const MEMORY_EVERY = 3;       // memory sizes every third poll: they run on the map's writer
const RECENT_LIMIT = 100;     // answers asked for (the service keeps at most its ring's capacity)
const ROWS_SHOWN = 60;        // rows of the recent table
const OBS_PAGE = 500;         // stored rows per page of /observations (the route's most)

const state = {
  maps: [], memory: {}, selected: new URLSearchParams(location.search).get("map"), stream: "",
  recent: [], recentSig: "", rows: new Map(), rowsAfter: 0, thumbs: new Map(), tick: 0, busy: false,
  closures: { entries: [], after: 0 },
};

const $ = (id) => document.getElementById(id);

function setStatus(kind, message) {
  $("status").dataset.state = kind;
  $("status").textContent = message;
}

function enc(s) { return encodeURIComponent(s); }

function selectedMap() { return state.maps.find((m) => m.map_id === state.selected) || null; }

// ------------------------------------------------------------------------------------------- maps

function renderMaps() {
  const body = $("maps").tBodies[0];
  body.replaceChildren(...state.maps.map((m) => {
    const mem = state.memory[m.map_id];
    const tr = el("tr", { "data-map-id": m.map_id, class: m.map_id === state.selected ? "selected" : null },
      el("td", {}, m.map_id),
      el("td", { class: `state-${m.state}`, title: m.state_reason || "" }, m.state),
      el("td", { title: m.encoder || "" }, text(m.backbone)),
      el("td", {}, text(m.preset)),
      el("td", { class: "num revisit-threshold" }, exact(m.revisit_threshold)),
      el("td", { class: "num obs-count" }, num(m.observations)),
      el("td", { class: "num" }, num(m.streams ? m.streams.length : undefined)),
      el("td", { class: "num" }, bytes(mem && mem.tm ? mem.tm.allocated_bytes : undefined)),
      el("td", { class: "num" }, bytes(mem && mem.index ? mem.index.bytes : undefined)),
      el("td", { class: "num" }, bytes(mem ? mem.projection_bytes : undefined)),
      el("td", { class: "num" }, bytes(mem && mem.storage ? mem.storage.db_bytes + mem.storage.wal_bytes
                                                           : undefined)));
    tr.addEventListener("click", () => select(m.map_id));
    return tr;
  }));
}

function forget(mapId) {
  // What was read of the map shown before: its answers and stored rows.
  state.selected = mapId;
  state.recent = []; state.rows = new Map(); state.rowsAfter = 0; state.stream = "";
  state.closures = { entries: [], after: 0 };
}

function select(mapId) {
  if (mapId === state.selected) return;
  forget(mapId);
  const url = new URL(location.href);
  url.searchParams.set("map", mapId);
  history.replaceState(null, "", url);
  renderMaps();
  poll();
}

function renderStreams(map) {
  const pick = $("stream");
  const names = new Set(map ? map.streams || [] : []);
  for (const e of state.recent) names.add(e.reply.stream);
  const wanted = ["", ...[...names].sort()];
  const have = [...pick.options].map((o) => o.value);
  if (wanted.join("\n") !== have.join("\n")) {
    pick.replaceChildren(...wanted.map((s) => el("option", { value: s }, s || "all")));
  }
  pick.value = state.stream;
}

// ---------------------------------------------------------------------------------------- answers

function thumbnailsOn(map) { return Boolean(map && map.thumbnails); }

/** A cell with the thumbnail at `route` (fetched once, kept while a row shows it; `key` tells apart
 * images that may come back under one route, as a recent answer's after a restart), or "—". */
function thumb(map, route, alt, shown, key = route) {
  const cell = el("td", { class: "thumb" });
  if (!thumbnailsOn(map) || !route) { cell.textContent = NONE; return cell; }
  shown.add(key);
  if (!state.thumbs.has(key)) {
    state.thumbs.set(key, null);
    getImageUrl(route).then((url) => { state.thumbs.set(key, url || NONE); renderRecent(); })
      .catch(() => state.thumbs.set(key, NONE));
  }
  const url = state.thumbs.get(key);
  if (url && url !== NONE) cell.append(el("img", { src: url, "data-thumb": route, alt }));
  else cell.textContent = url === NONE ? NONE : "…";
  return cell;
}

/** The stored row's thumbnail route, or null. */
function storedThumb(map, seq) {
  return typeof seq === "number" ? `/v1/maps/${enc(map.map_id)}/observations/${seq}/thumbnail` : null;
}

/** The query frame's thumbnail: the one the recent ring keeps (localised frames too), else a learned
 * row's stored one (an older service), else none. */
function queryThumb(map, e, shown) {
  if (e.has_thumbnail && typeof e.answer_id === "number") {
    const route = `/v1/maps/${enc(map.map_id)}/recent/${e.answer_id}/thumbnail`;
    return thumb(map, route, "query frame", shown, `${route}@${e.received_at}`);
  }
  return thumb(map, map && e.reply.learned ? storedThumb(map, e.reply.seq) : null, "query frame", shown);
}

function forgetThumbs(shown) {
  // Object URLs hold their image until revoked: keep those of the rows on screen only.
  for (const [key, url] of state.thumbs) {
    if (shown.has(key)) continue;
    if (url && url !== NONE) URL.revokeObjectURL(url);
    state.thumbs.delete(key);
  }
}

function confidenceCell(v, threshold) {
  const cls = level(v);
  if (cls === "none") return el("td", { class: "num none" }, NONE);
  const bar = el("span", { class: "bar" }, el("i", { class: cls, style: `width:${Math.round(v * 100)}%` }));
  return el("td", { class: "num" }, el("span", { class: `conf ${cls}` }, bar, beside(v, threshold)));
}

/** "revisit" (confidence at or above the map's revisit threshold when the answer was given) or "below
 * threshold": a place the map knows, not a new one (docs/design/service.md §1.2). */
function revisitCell(place, threshold, spanMax) {
  if (!place || typeof place.revisit !== "boolean") {
    return el("td", { class: "none" }, NONE);
  }
  if (place.low_information) {  // too flat to say where it is: never a revisit (science.md §11.7)
    return el("td", { title: "the frame is too flat (dark, blank or overexposed) to say where it is: "
                              + "never a revisit, whatever its confidence" },
              el("span", { class: "badge below" }, "low information"));
  }
  if (!place.revisit && place.span > spanMax && place.confidence >= threshold) {  // science.md §11.11
    return el("td", { title: `sure of the stretch, not of the row: ${place.span} places score within the `
                              + "map's span_margin of the best, more than its span_max: no revisit" },
              el("span", { class: "badge below" }, "wide span"));
  }
  if (!place.revisit && place.lagging && place.confidence >= threshold) {  // science.md §11.13
    return el("td", { title: "the path stayed on its rows while the robot moved on: it has fallen more than "
                              + "the map's lag_max of the robot's moves behind, so no revisit" },
              el("span", { class: "badge below" }, "lagging"));
  }
  const at = `the map's revisit threshold, now ${exact(threshold)}`;
  return el("td", { title: place.revisit ? `confidence at or above ${at}` : `confidence below ${at}` },
            place.revisit ? el("span", { class: "badge revisit" }, "revisit")
                          : el("span", { class: "badge below" }, "below threshold"));
}

function renderRecent() {
  const map = selectedMap();
  $("recent-map").textContent = map ? map.map_id : "";
  const shown = state.recent.filter((e) => !state.stream || e.reply.stream === state.stream);
  // Redrawn only when something shown changed: a new <img> decodes again, and would blink every poll.
  const loaded = [...state.thumbs.values()].filter((u) => u !== null).length;
  const sig = JSON.stringify([map && map.map_id, map && map.thumbnails, map && map.revisit_threshold,
                              state.stream, shown.length,
                              shown.length ? shown[shown.length - 1].received_at : null, loaded]);
  if (sig === state.recentSig) return;
  state.recentSig = sig;
  const rows = shown.slice(-ROWS_SHOWN).map((e, i) => ({ e, i: shown.length - Math.min(shown.length, ROWS_SHOWN) + i }))
    .reverse();
  const shownThumbs = new Set();
  $("recent").tBodies[0].replaceChildren(...rows.map(({ e, i }) => {
    const r = e.reply;
    const p = A.place(r);
    const m = A.topMatch(r);
    return el("tr", { "data-index": i, "data-seq": r.seq ?? "", "data-mode": r.learned ? "learn" : "localise" },
      el("td", { class: "num" }, clock(e.received_at)),
      el("td", {}, r.stream),
      el("td", {}, el("span", { class: `badge ${r.learned ? "learn" : "localise"}` },
                      r.learned ? "learned" : "localised")),
      el("td", { class: "num" }, num(r.seq ?? undefined)),
      el("td", { class: "num" }, num(r.sequence ? r.sequence.step : undefined)),
      el("td", { class: "num place-seq" }, p ? num(p.seq) : NONE),
      el("td", {}, p ? text(p.label) : NONE),
      confidenceCell(p ? p.confidence : undefined, map ? map.revisit_threshold : undefined),
      revisitCell(p, map ? map.revisit_threshold : undefined,
                  map && map.params && map.params.localiser ? map.params.localiser.span_max : undefined),
      el("td", { class: "num" }, p ? num(p.support) : NONE),
      el("td", { class: "num" }, p ? num(p.span) : NONE),
      el("td", { class: "num match-seq" }, m ? num(m.seq) : NONE),
      el("td", {}, m ? text(m.label) : NONE),
      el("td", { class: `num ${level(m ? m.score : undefined)}` }, m ? num(m.score, 3) : NONE),
      queryThumb(map, e, shownThumbs),
      thumb(map, p && map ? storedThumb(map, p.seq) : null, `place ${p ? p.seq : ""}`, shownThumbs));
  }));
  forgetThumbs(shownThumbs);
  const notes = [];
  if (!state.recent.length) notes.push("No answers since the service started (the list is kept in memory only).");
  if (shown.some((e) => !A.place(e.reply))) {
    notes.push("Place — : the stream is in its warm-up (its first frames), or the map had nothing stored.");
  }
  if (map && shown.some((e) => A.place(e.reply) && !A.revisit(e.reply))) {
    notes.push(`Below threshold: the map's best place, at a confidence under its revisit threshold ` +
               `(${exact(map.revisit_threshold)}), so not claimed as a revisit.`);
  }
  if (map && !thumbnailsOn(map)) notes.push("Thumbnails are off for this map.");
  $("recent-note").textContent = notes.join(" ");
}

// ----------------------------------------------------------------------------------------- poses

async function loadRows(map) {
  // Stored rows with their metadata, paged on from the last seq read (later polls read only new rows).
  for (let page = 0; page < 20; page += 1) {
    const body = await getJson(`/v1/maps/${enc(map.map_id)}/observations?after_seq=${state.rowsAfter}&limit=${OBS_PAGE}`);
    for (const row of body.observations) {
      state.rows.set(row.seq, row);
      state.rowsAfter = Math.max(state.rowsAfter, row.seq);
    }
    if (body.next_after_seq === null) return;
  }
}

function renderTrajectory() {
  const panel = $("trajectory-panel");
  const stored = [...state.rows.values()].map((row) => ({ seq: row.seq, stream: row.stream, pose: A.pose(row.metadata) }))
    .filter((r) => r.pose);
  const queries = state.recent.map((e) => ({ e, pose: A.pose(e.reply.metadata) })).filter((q) => q.pose);
  const poseOf = (seq, place) => A.pose(state.rows.get(seq)?.metadata) ?? A.pose(place?.metadata);
  if (!stored.length && !queries.length) {
    panel.classList.add("empty");
    $("trajectory").replaceChildren();
    $("trajectory-note").textContent =
      "No poses yet: post observations with metadata {\"pose\": {\"x\": …, \"y\": …}} to draw the trajectory.";
    return;
  }
  panel.classList.remove("empty");
  $("trajectory-note").textContent = drawTrajectory($("trajectory"), stored, queries, poseOf);
}

// ----------------------------------------------------------------------------------------- poll

async function poll() {
  if (state.busy) return;
  state.busy = true;
  try {
    const list = await getJson("/v1/maps");
    state.maps = list.maps;
    if (!selectedMap() && state.maps.length) forget(state.maps[0].map_id);  // none chosen, or deleted
    if (state.tick % MEMORY_EVERY === 0 || state.maps.some((m) => !(m.map_id in state.memory))) {
      await Promise.all(state.maps.map(async (m) => {
        try { state.memory[m.map_id] = await getJson(`/v1/maps/${enc(m.map_id)}/memory`); }
        catch { state.memory[m.map_id] = null; }
      }));
    }
    const map = selectedMap();
    if (map) {
      const recent = await getJson(`/v1/maps/${enc(map.map_id)}/recent?limit=${RECENT_LIMIT}`);
      state.recent = recent.answers;
      if (map.last_seq < state.rowsAfter) {  // restored to a snapshot: later seqs are gone, and may come back
        state.rows = new Map(); state.rowsAfter = 0; forgetThumbs(new Set());
        state.closures = { entries: [], after: 0 };  // the restore's log is the snapshot's
      }
      if (map.state === "ready" || map.state === "replaying") {  // a recovering map's rows are not readable yet
        await loadRows(map);
        await loadClosures(map.map_id, state.closures);
      }
    }
    renderMaps();
    renderStreams(map);
    renderRecent();
    renderTrajectory();
    $("closures").tBodies[0].replaceChildren(...closureRows(state.closures));
    $("closures-note").textContent = state.closures.entries.length ? "" :
      "No loop closure yet: a revisit (place.revisit) of any stream, learning or localising, is logged here.";
    $("seqmatch-stream").textContent = state.stream || "all streams";
    drawSeqMatch($("seqmatch"), state.recent.filter((e) => !state.stream || e.reply.stream === state.stream), map);
    const last = state.recent.length ? clock(state.recent[state.recent.length - 1].received_at) : NONE;
    setStatus("live", `${state.maps.length} map(s) · ${state.recent.length} recent answer(s) · last ${last} · ` +
                      `polling every ${POLL_MS / 1000} s`);
  } catch (err) {
    const needKey = err instanceof HttpError && err.status === 401;
    setStatus("error", needKey ? `the service needs the API key for reads${apiKey() ? " (the one given is refused)" : ""}`
                               : `cannot reach the service: ${err.message}`);
  } finally {
    state.tick += 1;
    state.busy = false;
  }
}

$("key-form").addEventListener("submit", (ev) => {
  ev.preventDefault();
  setApiKey($("api-key").value.trim());
  $("api-key").value = "";
  poll();
});
for (const format of ["csv", "jsonl", "g2o"]) {
  $(`export-${format}`).addEventListener("click", () => { const m = selectedMap(); if (m) saveExport(m.map_id, format); });
}
$("stream").addEventListener("change", () => { state.stream = $("stream").value; poll(); });

poll();
setInterval(poll, POLL_MS);
