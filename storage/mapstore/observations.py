"""`map.sqlite`'s observations (docs/design/service.md §4.2–§4.3): the rows, appended with what commits
in their transaction (thumbnail, keyframe, idempotency key, loop closure, drops, joins, recency, stream
state, flatness), their seqs, and the reads of rows, thumbnails, flat rows and idempotency keys.

Seqs are assigned here, strictly increasing and never reused: the next is `max(last_seq, seq_floor) + 1`
(`storage.mapstore`'s docstring).
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterable, Iterator
from typing import Any

from storage._common import StoreCorrupt, transaction, utc_now
from storage.mapschema import (
    COLUMNS,
    INPUT_DTYPE,
    DuplicateObservation,
    KeyRecord,
    NewObservation,
    Observation,
    decode,
    encode,
    load_json,
)
from storage.mapstore.closures import closure_params

__all__ = ["PAGE", "Observations"]

PAGE = 1024  # rows per SELECT in `rows()`: bounded memory, and no read transaction held between pages


class Observations:
    """`MapStore`'s rows (module docstring). It owns the last seq, the count and the seq floor."""

    _last_seq: int
    _count: int
    _seq_floor: int

    @property
    def seq_floor(self) -> int:
        """The high-water mark below or at which no seq is handed out."""
        return self._seq_floor

    def raise_seq_floor(self, seq: int) -> None:
        """Raise (never lower) the seq floor, e.g. after the catalog's high-water mark moved."""
        with self._lock:
            self._seq_floor = max(self._seq_floor, int(seq))

    def next_seq(self) -> int:
        """The seq the next `append` will assign."""
        with self._lock:
            return max(self._last_seq, self._seq_floor) + 1

    def append(self, row: NewObservation, *, durable: bool = True) -> int:
        """INSERT one observation and COMMIT; durable (WAL, synchronous=FULL) when this returns.

        Args:
            durable: False: COMMIT without its fsync (synchronous=NORMAL for this transaction): the row
                is visible and survives a crash of the process, and is durable once a later `sync`
                returns (group commit, docs/design/service.md §4.3): acknowledge it only then.

        Returns:
            Its seq.

        Raises:
            ValueError: arrays not sorted/distinct/in range, or a context_prev_seq that is not earlier.
            DuplicateObservation: the observation_id is already stored.
            StorageFull: no room to write; nothing was written and the seq is not consumed.
        """
        return self.append_many([row], durable=durable)[0]

    def append_many(self, rows: Iterable[NewObservation], *, durable: bool = True) -> list[int]:
        """INSERT several observations in one transaction (all or none); `durable` as in `append`.

        Each reply of the service must still wait for this commit (docs/design/service.md §4.3).

        Returns:
            Their seqs, in order.
        """
        rows = list(rows)
        with self._lock:
            conn = self._db()
            first = max(self._last_seq, self._seq_floor) + 1
            params = []
            for i, r in enumerate(rows):
                seq = first + i
                prev = r.context_prev_seq
                if prev is not None and not 0 < int(prev) < seq:
                    raise ValueError(f"context_prev_seq {prev} must be in [1, {seq})")
                params.append((seq, str(r.observation_id), str(r.stream),
                               None if prev is None else int(prev), r.label, str(r.created_at),
                               str(r.image_sha256), encode(r.input_sdr, INPUT_DTYPE, "input_sdr"),
                               encode(r.winner_cells, self._cell_dtype, "winner_cells"),
                               None if r.metadata is None else json.dumps(r.metadata, separators=(",", ":")),
                               None if r.place is None else int(r.place)))
            if not params:
                return []
            thumbs = [(first + i, r.thumbnail) for i, r in enumerate(rows) if r.thumbnail is not None]
            keys = [(r.key.key, r.key.fingerprint, first + i, r.key.reply, str(r.created_at))
                    for i, r in enumerate(rows) if r.key is not None]
            frames = [(first + i, r.keyframe[0], None if r.keyframe[1] is None
                       else json.dumps(r.keyframe[1], separators=(",", ":")))
                      for i, r in enumerate(rows) if r.keyframe is not None]
            closures = [closure_params(r.closure, first + i)
                        for i, r in enumerate(rows) if r.closure is not None]
            drops = [(int(d), "appearance-cap", first + i) for i, r in enumerate(rows) for d in r.drops]
            resumes = [(str(r.stream), first + i, r.resume)
                       for i, r in enumerate(rows) if r.resume is not None]
            touches = [(int(t), first + i) for i, r in enumerate(rows) for t in r.touched]
            joins = [(str(r.stream), j, first + i - 1) for i, r in enumerate(rows) for j in r.joins]
            kept = [(str(r.stream), j, first + i - 1) for i, r in enumerate(rows) for j in r.kept]
            flat = [(first + i,) for i, r in enumerate(rows) if r.flat and self.holds.flat]
            if not durable:  # per connection, outside a transaction: this commit alone skips its fsync
                conn.execute("PRAGMA synchronous=NORMAL")
            try:
                with transaction(conn):
                    conn.executemany(f"INSERT INTO observations ({COLUMNS}) VALUES (?,?,?,?,?,?,?,?,?,?,?)",
                                     params)
                    self._drop(conn, drops)
                    now = utc_now()  # one step's joins, kept or not, share one time (`join_problems`)
                    gone = self._join(conn, joins, now)
                    self._keep(conn, kept, now)
                    self._touch(conn, touches)
                    self._resume(conn, resumes)
                    # The row's thumbnail and idempotency key commit with it, or nothing does.
                    conn.executemany("INSERT INTO thumbnails (seq, jpeg) VALUES (?, ?)", thumbs)
                    conn.executemany("INSERT INTO keyframes (seq, features, camera) VALUES (?, ?, ?)", frames)
                    conn.executemany("INSERT INTO flat (seq) VALUES (?)", flat)
                    conn.executemany("INSERT INTO idempotency_keys (key, fingerprint, seq, reply, created_at)"
                                     " VALUES (?, ?, ?, ?, ?)", keys)
                    if keys and self.max_keys is not None:  # the keys of the last max_keys seqs stay
                        conn.execute("DELETE FROM idempotency_keys WHERE seq <= ?",
                                     (first + len(params) - 1 - self.max_keys,))
                    self._log_closures(conn, closures)
            except sqlite3.IntegrityError as exc:
                if "observation_id" in str(exc) or "idempotency_keys.key" in str(exc):
                    raise DuplicateObservation(str(exc)) from exc
                raise
            finally:
                if not durable:
                    conn.execute("PRAGMA synchronous=FULL")
            # Only after COMMIT returned: a failed commit consumes no seq and changes no counter.
            self._last_seq = first + len(params) - 1
            self._count += len(params) - gone
            return list(range(first, first + len(params)))

    def count(self) -> int:
        """Number of stored observations."""
        with self._lock:
            return self._count

    def count_after(self, seq: int) -> int:
        """Number of stored observations with a seq above `seq` (a recovery's tail after a snapshot)."""
        with self._lock:
            return int(self._db().execute("SELECT count(*) FROM observations WHERE seq > ?",
                                          (int(seq),)).fetchone()[0])

    def last_seq(self) -> int:
        """Highest seq stored (a row held, or one a join turned into a visit, §11.8; 0 when empty); the seq
        floor is not counted."""
        with self._lock:
            return self._last_seq

    def get(self, seq: int) -> Observation | None:
        """The observation with this seq, or None."""
        with self._lock:
            r = self._db().execute(f"SELECT {self.holds.row_columns} FROM observations WHERE seq = ?",
                                   (int(seq),)).fetchone()
        return None if r is None else self._row(r)

    def get_many(self, seqs: Iterable[int]) -> dict[int, Observation]:
        """Observations by seq (missing seqs are absent from the result); for the top-k of a ranking."""
        wanted = sorted({int(s) for s in seqs})
        out: dict[int, Observation] = {}
        # SQLite limits bound parameters per statement; 500 is far below every build's limit.
        for i in range(0, len(wanted), 500):
            chunk = wanted[i:i + 500]
            marks = ",".join("?" * len(chunk))
            with self._lock:
                found = self._db().execute(f"SELECT {self.holds.row_columns} FROM observations "
                                           f"WHERE seq IN ({marks})", chunk).fetchall()
            out.update((int(r[0]), self._row(r)) for r in found)
        return out

    def rows(self, after_seq: int = 0) -> Iterator[Observation]:
        """Observations with seq > `after_seq`, in seq order (replay, index rebuild).

        Read in pages by seq, so appends between pages are fine and no read transaction is held while
        the caller works on a row.
        """
        last = int(after_seq)
        while page := self.page(last, PAGE):
            yield from page
            last = page[-1].seq

    def page(self, after_seq: int, limit: int) -> list[Observation]:
        """At most `limit` observations with seq > `after_seq`, in seq order."""
        with self._lock:
            found = self._db().execute(
                f"SELECT {self.holds.row_columns} FROM observations WHERE seq > ? ORDER BY seq LIMIT ?",
                (int(after_seq), int(limit))).fetchall()
        return [self._row(r) for r in found]

    def _row(self, r: tuple[Any, ...]) -> Observation:
        try:
            return Observation(seq=int(r[0]), observation_id=r[1], stream=r[2],
                               context_prev_seq=None if r[3] is None else int(r[3]), label=r[4],
                               created_at=r[5], image_sha256=r[6], input_sdr=decode(r[7], INPUT_DTYPE),
                               winner_cells=decode(r[8], self._cell_dtype), metadata=load_json(r[9]),
                               place=None if r[10] is None else int(r[10]))
        except StoreCorrupt as e:  # which row: what verify and the map's failure reason show
            raise StoreCorrupt(f"{self.path}: observation seq {r[0]}: {e}") from e

    def flat(self) -> set[int]:
        """The rows whose frame was flat (docs/design/science.md §11.7; `NewObservation.flat`). Empty for a
        file before version 13: its rows are not known flat."""
        if not self.holds.flat:
            return set()
        with self._lock:
            return {int(r[0]) for r in self._db().execute("SELECT seq FROM flat")}

    def thumbnail(self, seq: int) -> bytes | None:
        """The JPEG thumbnail stored with this seq, or None."""
        if not self.holds.thumbnails:
            return None
        with self._lock:
            r = self._db().execute("SELECT jpeg FROM thumbnails WHERE seq = ?", (int(seq),)).fetchone()
        return None if r is None else bytes(r[0])

    def with_thumbnails(self, seqs: Iterable[int]) -> set[int]:
        """Those of `seqs` (at most 500) that have a thumbnail."""
        wanted = sorted({int(s) for s in seqs})
        if not self.holds.thumbnails or not wanted:
            return set()
        with self._lock:
            marks = ",".join("?" * len(wanted))
            found = self._db().execute(f"SELECT seq FROM thumbnails WHERE seq IN ({marks})",
                                       wanted).fetchall()
        return {int(r[0]) for r in found}

    def key_record(self, key: str) -> KeyRecord | None:
        """The idempotent post stored under `key`, or None (never stored, or pruned)."""
        if not self.holds.idempotency_keys:
            return None
        with self._lock:
            r = self._db().execute("SELECT key, fingerprint, reply FROM idempotency_keys WHERE key = ?",
                                   (key,)).fetchone()
            # a consolidated frame's post (docs/design/science.md §11.8)
            if r is None and self.holds.visit_keys:
                r = self._db().execute("SELECT key, fingerprint, reply FROM visit_keys WHERE key = ?",
                                       (key,)).fetchone()
            # a version 5-6 file opened read-only: its visit log holds them
            elif r is None and self.holds.visits:
                r = self._db().execute("SELECT idempotency_key, fingerprint, reply FROM visits "
                                       "WHERE idempotency_key = ?", (key,)).fetchone()
        return None if r is None else KeyRecord(*r)
