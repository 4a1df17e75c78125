"""`map.sqlite`'s places beyond the rows (docs/design/science.md §11.8–§11.9, docs/design/service.md §4.2):
the visits log (a consolidated frame: the memory learned it, no row was made) with its keys and pruning,
the warm-up joins and the dropped rows (out of the index: over a place's cap, forgotten, joined).
"""

from __future__ import annotations

import heapq
import json
import sqlite3
from collections.abc import Iterable, Iterator

import numpy as np

from storage._common import transaction, utc_now
from storage.mapschema import (
    INPUT_DTYPE,
    DuplicateObservation,
    JoinedRow,
    NewVisit,
    Visit,
    decode,
    encode,
    load_json,
)
from storage.mapstore.closures import closure_params
from storage.mapstore.observations import PAGE

__all__ = ["Visits"]


class Visits:
    """`MapStore`'s visits, joins and dropped rows (module docstring); no state of its own."""

    def add_visit(self, visit: NewVisit) -> int:
        """Log a consolidated frame (docs/design/science.md §11.8) with its loop closure and idempotency
        key, and COMMIT: durable when this returns, before its reply (docs/design/service.md §4.3).

        Returns:
            Its id (the visits' log order).

        Raises:
            DuplicateObservation: its idempotency key is already stored. StorageFull: nothing was written.
        """
        meta = None if visit.metadata is None else json.dumps(visit.metadata, separators=(",", ":"))
        key = visit.key
        with self._lock:
            conn = self._db()
            if key is not None and conn.execute("SELECT 1 FROM idempotency_keys WHERE key = ?",
                                                (key.key,)).fetchone():
                raise DuplicateObservation(f"idempotency key {key.key} is already stored")
            try:
                with transaction(conn):
                    cur = conn.execute(
                        "INSERT INTO visits (after_seq, stream, seq, context_prev_seq, input_sdr, "
                        "winner_cells, metadata, created_at) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                        (self._last_seq, str(visit.stream), int(visit.seq),
                         None if visit.context_prev_seq is None else int(visit.context_prev_seq),
                         encode(visit.input_sdr, INPUT_DTYPE, "input_sdr"),
                         encode(visit.winner_cells, self._cell_dtype, "winner_cells"), meta,
                         str(visit.created_at)))
                    visit_id = int(cur.lastrowid or 0)
                    if key is not None:  # kept apart from the log, which is pruned (§4.2)
                        conn.execute("INSERT INTO visit_keys (key, fingerprint, visit, reply, created_at) "
                                     "VALUES (?, ?, ?, ?, ?)",
                                     (key.key, key.fingerprint, visit_id, key.reply, str(visit.created_at)))
                        if self.max_keys is not None:  # the keys of the last max_keys visits stay
                            conn.execute("DELETE FROM visit_keys WHERE visit <= ?",
                                         (visit_id - self.max_keys,))
                    clock = max(self._last_seq, self._seq_floor) + 1  # the seq the live step was given
                    now, after = utc_now(), self._last_seq  # one step's joins, kept or not, share one time
                    gone = self._join(conn, [(str(visit.stream), j, after) for j in visit.joins], now)
                    self._keep(conn, [(str(visit.stream), j, after) for j in visit.kept], now)
                    # after the step's joins: `join_problems` reads a drop logged at the same `after_seq`
                    # before a join as made at an earlier step (the row was not held at that join)
                    self._drop(conn, [(int(d), "appearance-cap", self._last_seq) for d in visit.drops])
                    self._touch(conn, [(int(t), clock) for t in visit.touched])
                    if visit.resume is not None:
                        self._resume(conn, [(str(visit.stream), clock, visit.resume)])
                    if visit.closure is not None:
                        self._log_closures(conn, [closure_params(visit.closure, None, visit.seq)])
            except sqlite3.IntegrityError as exc:
                if "visit_keys.key" in str(exc):
                    raise DuplicateObservation(str(exc)) from exc
                raise
            self._count -= gone  # only after COMMIT returned
            return visit_id

    def visits(self, after_id: int = 0, rows_after: int = 0) -> Iterator[Visit]:
        """Logged visits with id > `after_id`, in the order they were learned (their `after_seq`, then log
        order: a joined row's visit, logged at its join, takes its row's place, §11.8), read in pages
        (replay). `rows_after`: a joined row's visit only if its row is after it (a snapshot at that seq
        learned the rows up to it)."""
        if not self.holds.visits:
            return
        row = "row_seq" if self.holds.joined_rows else "NULL"
        last = (-1, 0)
        while True:
            with self._lock:
                found = self._db().execute(
                    "SELECT id, after_seq, stream, seq, context_prev_seq, input_sdr, winner_cells, "
                    f"created_at, metadata, {row} FROM visits WHERE id > ? AND (after_seq, id) > (?, ?) "
                    f"AND coalesce({row}, ?) > ? ORDER BY after_seq, id LIMIT ?",
                    (int(after_id), *last, int(rows_after) + 1, int(rows_after), PAGE)).fetchall()
            if not found:
                return
            for r in found:
                yield Visit(id=int(r[0]), after_seq=int(r[1]), stream=r[2], seq=int(r[3]),
                            context_prev_seq=None if r[4] is None else int(r[4]),
                            input_sdr=decode(r[5], INPUT_DTYPE), winner_cells=decode(r[6], self._cell_dtype),
                            created_at=r[7], metadata=load_json(r[8]),
                            row=None if r[9] is None else int(r[9]))
            last = (int(found[-1][1]), int(found[-1][0]))

    def visit_stats(self) -> tuple[int, int, int]:
        """(visits logged, the first id kept (0: none), the last id ever logged (0: none))."""
        if not self.holds.visits:
            return 0, 0, 0
        with self._lock:
            n, lo, hi = self._db().execute("SELECT count(*), coalesce(min(id), 0), coalesce(max(id), 0) "
                                           "FROM visits").fetchone()
        return int(n), int(lo), int(hi)

    def oldest_plain_visit(self) -> int | None:
        """The id of the oldest visit kept that a consolidated frame made (not a warm-up join's, whose
        `after_seq` is its row's, back in the log): every visit the log pruned was learned before it
        (`service.maps.repair`). None: no such visit kept."""
        if not self.holds.visits:
            return None
        plain = "row_seq IS NULL" if self.holds.joined_rows else "1"
        with self._lock:
            r = self._db().execute(f"SELECT min(id) FROM visits WHERE {plain}").fetchone()
        return None if r is None or r[0] is None else int(r[0])

    def visit_mark(self, visit_id: int) -> str | None:
        """What tells visit `visit_id` from another that got its id on another branch (a restore rolls
        the log back and ids are handed out again): its stream and created_at; None: no such visit."""
        if not self.holds.visits:
            return None
        with self._lock:
            r = self._db().execute("SELECT stream, created_at FROM visits WHERE id = ?",
                                   (int(visit_id),)).fetchone()
        return None if r is None else f"{r[0]}|{r[1]}"

    def visits_pruned_through(self) -> int:
        """The last visit id pruned from the log (0: none ever was): a replay that starts before it
        cannot reproduce the memory (docs/design/service.md §4.4).

        Durable as the log itself: ids start at 1 and are never reused (SQLite hands out max(id) + 1,
        and `prune_visits` always keeps the newest), so the oldest id kept minus one is how far the log
        was pruned."""
        _, first, _ = self.visit_stats()
        return max(first - 1, 0)

    def prune_visits(self, covered: int, keep: int) -> int:
        """Delete the oldest visits beyond the last `keep` (at least 1: `visits_pruned_through` reads
        the oldest kept), but only those with id <= `covered` (a snapshot holds the memory they taught;
        the replay after it never needs them). Returns how many."""
        if not self.holds.visits:
            return 0
        keep = max(int(keep), 1)
        with self._lock:
            conn = self._db()
            with transaction(conn):
                cur = conn.execute("DELETE FROM visits WHERE id <= ? AND "
                                   "id <= (SELECT max(id) FROM visits) - ?", (int(covered), int(keep)))
            return int(cur.rowcount)

    def drop(self, seqs: Iterable[int], reason: str) -> None:
        """Record rows as no longer held (a forgotten place, docs/design/science.md §11.9) and COMMIT."""
        with self._lock:
            conn = self._db()
            with transaction(conn):
                self._drop(conn, [(int(s), reason, self._last_seq) for s in seqs])

    def _drop(self, conn: sqlite3.Connection, drops: list[tuple[int, str, int]]) -> None:
        if drops:
            conn.executemany("INSERT OR IGNORE INTO dropped (seq, reason, after_seq, created_at) "
                             "VALUES (?, ?, ?, ?)", [(*d, utc_now()) for d in drops])

    def _keep(self, conn: sqlite3.Connection, kept: list[tuple[str, tuple[int, int], int]], now: str) -> None:
        """Warm-up joins that keep their row (stream, (row, old row), after_seq; schema 14), made at `now`:
        the join alone, `kept` 1; the row stays held, an appearance of the old row's place (§11.8), neither
        dropped nor deleted."""
        if kept:
            conn.executemany("INSERT INTO joins (seq, place_seq, stream, after_seq, created_at, kept) "
                             "VALUES (?, ?, ?, ?, ?, 1)",
                             [(int(row), int(old), stream, after, now) for stream, (row, old), after in kept])

    def _join(self, conn: sqlite3.Connection, joins: list[tuple[str, tuple[int, int], int]], now: str) -> int:
        """Warm-up joins (stream, (row, old row), after_seq), each row dropped (`joined`) with it; from
        schema 12 each row that no loop closure or repair names is turned into a visit of the old row
        (`visits.row_seq`, after the row before it) and deleted, so a join leaves no row behind (§11.8).
        Made at `now` (the step's joins share it). Returns how many rows were deleted."""
        if not joins:
            return 0
        v12 = self.holds.joined_rows
        # from schema 12 the row's record as acknowledged goes with the join (`joined_row`)
        kept = ("observation_id", "image_sha256", "label", "created_at", "metadata") if v12 else ()
        names = "".join(f", {'row_created_at' if k == 'created_at' else k}" for k in kept)
        reads = "".join(f", (SELECT {k} FROM observations WHERE seq = ?)" for k in kept)
        conn.executemany(f"INSERT INTO joins (seq, place_seq, stream, after_seq, created_at{names}) "
                         f"VALUES (?, ?, ?, ?, ?{reads})",
                         [(int(row), int(old), stream, after, now, *((int(row),) * len(kept)))
                          for stream, (row, old), after in joins])
        self._drop(conn, [(int(row), "joined", after) for _, (row, _old), after in joins])
        if not v12:
            return 0
        gone = 0
        for _, (row, old), _after in joins:
            cur = conn.execute(
                "INSERT INTO visits (after_seq, stream, seq, context_prev_seq, input_sdr, winner_cells, "
                "metadata, created_at, row_seq) SELECT o.seq - 1, o.stream, ?, o.context_prev_seq, "
                "o.input_sdr, o.winner_cells, o.metadata, o.created_at, o.seq FROM observations o "
                "WHERE o.seq = ? AND NOT EXISTS (SELECT 1 FROM loop_closures c WHERE c.seq = o.seq "
                "OR c.place_seq = o.seq) AND NOT EXISTS (SELECT 1 FROM repairs r WHERE r.seq = o.seq)",
                (int(old), int(row)))
            if cur.rowcount:
                for table in ("thumbnails", "keyframes", "recency", "flat", "observations"):
                    conn.execute(f"DELETE FROM {table} WHERE seq = ?", (int(row),))
                gone += 1
        return gone

    def observation_id(self, seq: int) -> str | None:
        """The observation id of row `seq`, held or joined away (a warm-up join turned it into a visit,
        schema 12); None: no such row in this file."""
        with self._lock:
            db = self._db()
            r = db.execute("SELECT observation_id FROM observations WHERE seq = ?", (int(seq),)).fetchone()
            if r is None and self.holds.joined_rows:
                r = db.execute("SELECT observation_id FROM joins WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else r[0]

    def code(self, seq: int) -> np.ndarray | None:
        """Row `seq`'s frame code (`input_sdr`), held or joined away (its visit's, schema 12); None: none."""
        with self._lock:
            db = self._db()
            r = db.execute("SELECT input_sdr FROM observations WHERE seq = ?", (int(seq),)).fetchone()
            if r is None and self.holds.joined_rows:
                r = db.execute("SELECT input_sdr FROM visits WHERE row_seq = ?", (int(seq),)).fetchone()
        return None if r is None else decode(r[0], INPUT_DTYPE)

    def joined_row(self, seq: int) -> JoinedRow | None:
        """The record of row `seq` if a warm-up join turned it into a visit and deleted it (schema 12),
        as it was acknowledged; None otherwise (a row held, or none)."""
        found = self.joined_rows(int(seq) - 1, 1)
        return found[0] if found and found[0].seq == int(seq) else None

    def joined_rows(self, after_seq: int, limit: int) -> list[JoinedRow]:
        """At most `limit` records of rows a warm-up join turned into visits and deleted (schema 12), with
        seq > `after_seq`, in seq order (the listing of a map's rows keeps them, so it only grows)."""
        if not self.holds.joined_rows:
            return []
        with self._lock:
            found = self._db().execute(
                "SELECT seq, observation_id, stream, label, row_created_at, image_sha256, metadata, "
                "place_seq FROM joins j WHERE seq > ? AND observation_id IS NOT NULL "
                "AND NOT EXISTS (SELECT 1 FROM observations o WHERE o.seq = j.seq) ORDER BY seq LIMIT ?",
                (int(after_seq), int(limit))).fetchall()
        return [JoinedRow(seq=int(r[0]), observation_id=r[1], stream=r[2], label=r[3], created_at=r[4],
                          image_sha256=r[5], metadata=load_json(r[6]), place_seq=int(r[7])) for r in found]

    def joined_to(self, seq: int) -> int | None:
        """The old row whose place row `seq` joined (a warm-up join, kept or not), or None."""
        if not self.holds.joins:
            return None
        with self._lock:
            r = self._db().execute("SELECT place_seq FROM joins WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else int(r[0])

    def joins(self) -> list[tuple[int, int]]:
        """The warm-up joins (row, old row whose place it joined) in log order (docs/design/science.md
        §11.8); the rows are `dropped` (reason `joined`), but those of joins that keep their row (`kept`)."""
        if not self.holds.joins:
            return []
        with self._lock:
            return [(int(r[0]), int(r[1])) for r in self._db().execute(
                "SELECT seq, place_seq FROM joins ORDER BY after_seq, seq")]

    def join_problems(self, reach: int) -> list[str]:
        """What is wrong with the warm-up joins (`cortexloc verify`, docs/design/science.md §11.8): a join
        whose row is not dropped as `joined`, or a kept one (schema 14) whose row is, or is not stored; one
        that reached back over `reach` or more of its stream's rows held then; a row dropped as `joined`
        with no join that drops it."""
        if not self.holds.joins:
            return []
        kept = "j.kept" if self.holds.kept_joins else "0"
        with self._lock:
            db = self._db()
            out = [f"join of row {r[0]}: the row is not dropped as joined" for r in db.execute(
                "SELECT j.seq FROM joins j LEFT JOIN dropped d ON d.seq = j.seq "
                f"WHERE d.reason IS NOT 'joined' AND {kept} = 0")]
            out += [f"kept join of row {r[0]}: the row is dropped as joined" for r in db.execute(
                "SELECT j.seq FROM joins j JOIN dropped d ON d.seq = j.seq "
                f"WHERE d.reason = 'joined' AND {kept} = 1")]
            out += [f"kept join of row {r[0]}: the row is not stored" for r in db.execute(
                f"SELECT j.seq FROM joins j WHERE {kept} = 1 "
                "AND NOT EXISTS (SELECT 1 FROM observations o WHERE o.seq = j.seq)")]
            out += [f"row {r[0]} is dropped as joined without a join" for r in db.execute(
                "SELECT d.seq FROM dropped d LEFT JOIN joins j ON j.seq = d.seq "
                f"WHERE d.reason = 'joined' AND (j.seq IS NULL OR {kept} = 1)")]
            # The rows the live rule looked through: the stream's rows made after the joined one and
            # still held when the join was made (a row dropped at an earlier step, joined or over its
            # place's cap, had left the memory; a row a repair re-made is no step of it). Steps that
            # store no row (a consolidated frame) share their `after_seq` (an outside probe: a restart's
            # warm-up rows joined over two frames in a row, the newest then the older, read as an
            # over-reach). One step writes its joins with one `created_at`, so another time is another
            # step; which came first, the visits its joined rows became say (the log's order, schema 12),
            # or failing them (a row a closure names stays a row; an older file) the times, which a clock
            # stepped back can mislead. A row dropped over its place's cap or forgotten at the same
            # `after_seq` before the join (a kept join's drop at an earlier consolidated frame, a review;
            # a forgetting before the step) is read by the times alone: a step logs its drops after its
            # joins, so its own drops were still held at its joins, as the live rule read them.
            split = ("SELECT seq FROM repairs WHERE kind = 'split'" if self.holds.repairs
                     else "SELECT NULL WHERE 0")
            rows = ("(SELECT seq, stream FROM observations UNION ALL SELECT row_seq, stream FROM visits "
                    "WHERE row_seq IS NOT NULL)") if self.holds.joined_rows else "observations"
            before = "k.created_at < j.created_at"
            dropping = "k.kept = 0" if self.holds.kept_joins else "1"  # a kept join's row stays held
            if self.holds.joined_rows:
                logged = "(SELECT id FROM visits WHERE row_seq = {})"
                before = f"COALESCE({logged.format('k.seq')} < {logged.format('j.seq')}, {before})"
            out += [f"join of row {r[0]}: {r[1]} held rows of its stream since, the reach is {reach}"
                    for r in db.execute(
                        f"SELECT j.seq, (SELECT count(*) FROM {rows} o WHERE o.stream = j.stream "
                        "AND o.seq > j.seq AND o.seq <= j.after_seq AND NOT EXISTS (SELECT 1 FROM dropped d "
                        "WHERE d.seq = o.seq AND (d.after_seq < j.after_seq OR (d.after_seq = j.after_seq "
                        f"AND (EXISTS (SELECT 1 FROM joins k WHERE k.seq = d.seq AND {dropping} "
                        f"AND k.created_at != j.created_at AND {before}) "
                        "OR (d.reason != 'joined' AND d.created_at < j.created_at))))) "
                        f"AND o.seq NOT IN ({split})) AS n FROM joins j WHERE n >= ?", (int(reach),))]
            return out

    def dropped(self) -> dict[int, str]:
        """The rows no longer held and why (`appearance-cap` | `forgotten` | `joined`)."""
        if not self.holds.dropped:
            return {}
        with self._lock:
            return {int(r[0]): r[1] for r in self._db().execute("SELECT seq, reason FROM dropped")}

    def held(self) -> int:
        """How many rows are held: stored (or turned into a visit by a join) and not dropped, what a rebuilt
        index holds (`CORTEXLOC_MAX_OBSERVATIONS` caps this, docs/design/science.md §11.9)."""
        rows = "SELECT seq FROM observations"
        if self.holds.joined_rows:  # a joined row's visit is that row again (§11.8)
            rows += " UNION SELECT row_seq FROM visits WHERE row_seq IS NOT NULL"
        held = f"SELECT count(*) FROM ({rows})"
        if self.holds.dropped:
            held += " WHERE seq NOT IN (SELECT seq FROM dropped)"
        with self._lock:
            return int(self._db().execute(held).fetchone()[0])

    def learned_seqs(self) -> Iterator[int]:
        """The seq of every learned row the file knows, ascending (a seq twice where a row was joined and
        kept): held, dropped, or joined into a visit (its row deleted, schema 12; its join record stays
        when its visit is pruned). Read in pages, so a million rows never sit in memory at once."""
        sources = [self._seqs_paged("SELECT seq FROM observations WHERE seq > ? ORDER BY seq LIMIT ?")]
        if self.holds.joins:
            sources.append(self._seqs_paged("SELECT seq FROM joins WHERE seq > ? ORDER BY seq LIMIT ?"))
        return heapq.merge(*sources)

    def consolidated_visits(self, from_id: int = 0) -> Iterator[tuple[int, str, str]]:
        """The consolidated visits logged (no joined row's) with id >= `from_id`, as (id, stream, created_at),
        by id: a visit's id is handed out again on another branch, so its stream and time tell them apart
        (as `visit_mark`). In pages."""
        if not self.holds.visits:
            return
        own = " AND row_seq IS NULL" if self.holds.joined_rows else ""
        last = int(from_id) - 1
        while True:
            with self._lock:
                page = [(int(r[0]), r[1], r[2]) for r in self._db().execute(
                    f"SELECT id, stream, created_at FROM visits WHERE id > ?{own} ORDER BY id LIMIT ?",
                    (last, PAGE))]
            yield from page
            if len(page) < PAGE:
                return
            last = page[-1][0]

    def _seqs_paged(self, sql: str) -> Iterator[int]:
        last = 0
        while True:
            with self._lock:
                page = [int(r[0]) for r in self._db().execute(sql, (last, PAGE))]
            yield from page
            if len(page) < PAGE:
                return
            last = page[-1]
