"""map.sqlite schemas 5 to 9 (docs/design/science.md §11.8, §11.9, §11.11; docs/design/service.md §4.2): a
row's place, the visit log (consolidated frames, replayed), dropped rows, rows' recency (schema 6), visit
keys and streams' states (schema 7), a visit's closure naming the row it joined (schema 8), a closure's
span (schema 11), and the migration of an older map whose places come from its loop-closure log."""

from __future__ import annotations

import dataclasses
import sqlite3
import time
from pathlib import Path

import numpy as np
import pytest

from models.localisation import PlaceMap
from storage.mapschema import SCHEMA_VERSION, KeyRecord, NewClosure, NewVisit
from storage.mapstore import DuplicateObservation, MapMeta, MapStore
from tests.storage.conftest import make_row

#: Schema 9's closure columns, undone (a file as version 8 and before wrote it).
DROP_SPAN = "ALTER TABLE loop_closures DROP COLUMN span; ALTER TABLE loop_closures DROP COLUMN span_seqs;"


def visit(i: int, seq: int, prev: int | None, key: str | None = None) -> NewVisit:
    row = make_row(i)
    return NewVisit(stream="b", seq=seq, context_prev_seq=prev, input_sdr=row.input_sdr,
                    winner_cells=row.winner_cells, metadata={"stamp": float(i)},
                    key=None if key is None else KeyRecord(key, "f" * 64, '{"reply": 1}'))


def test_a_visit_commits_in_order_after_its_rows_and_reads_back(store: MapStore) -> None:
    store.append(make_row(1))
    store.append(make_row(2, prev=1))
    closure = NewClosure(stream="b", place_seq=1, confidence=0.99, support=6)
    first = store.add_visit(dataclasses.replace(visit(10, 1, None), closure=closure))
    second = store.add_visit(visit(11, 2, 1))
    store.append(make_row(3, prev=2))
    got = list(store.visits())
    assert [v.id for v in got] == [first, second] and [v.after_seq for v in got] == [2, 2]
    assert (got[1].seq, got[1].context_prev_seq, got[1].metadata) == (2, 1, {"stamp": 11.0})
    assert np.array_equal(got[0].input_sdr, make_row(10).input_sdr)
    assert np.array_equal(got[0].winner_cells, make_row(10).winner_cells)
    # logged with it, naming the row the frame was consolidated into (schema 8)
    assert [(c.seq, c.place_seq, c.consolidated_into) for c in store.closures(0, 10)] == [(None, 1, 1)]
    assert list(store.visits(after_id=first)) and store.visit_stats() == (2, first, second)


def test_recency_commits_with_the_row_or_visit_that_used_it_at_the_live_clock(tmp_path: Path,
                                                                             meta: MapMeta) -> None:
    """Schema 6 `recency`: the rows a step used, at its seq (a row) or at the seq the store would have
    given it (a visit: the high-water mark after a restore counts, as it does for the live step), kept
    at the latest; the recovery reads it back (docs/design/science.md §11.9)."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as store:
        store.append(make_row(1))
        store.append(dataclasses.replace(make_row(2, prev=1), touched=(1,)))
        assert store.recency() == {1: 2}
        store.add_visit(dataclasses.replace(visit(10, 2, 1), touched=(1, 2)))  # clock 3: the next seq
        assert store.recency() == {1: 3, 2: 3}
    with MapStore.open(path, seq_floor=40) as store:  # a restored file: the next seq is 41
        store.add_visit(dataclasses.replace(visit(11, 1, None), touched=(1,)))
        store.append(dataclasses.replace(make_row(3, prev=2), touched=(2,)))
        assert store.recency() == {1: 41, 2: 41}
        place_map = PlaceMap(None, 4096)
        place_map.rebuild(store.rows(), used=store.recency())
        assert place_map.used[[1, 2, 41]].tolist() == [41, 41, 41]


def test_a_visit_key_answers_a_repeat_and_is_never_stored_twice(store: MapStore) -> None:
    store.append(make_row(1))
    store.add_visit(visit(10, 1, None, key="visit-key-0001"))
    assert store.key_record("visit-key-0001") == KeyRecord("visit-key-0001", "f" * 64, '{"reply": 1}')
    with pytest.raises(DuplicateObservation):
        store.add_visit(visit(11, 1, None, key="visit-key-0001"))
    assert store.visit_stats()[0] == 1


def test_visits_are_pruned_only_once_a_snapshot_covers_them(store: MapStore) -> None:
    store.append(make_row(1))
    ids = [store.add_visit(visit(10 + i, 1, None)) for i in range(6)]
    assert store.prune_visits(covered=0, keep=2) == 0  # none covered: the replay needs them all
    assert store.prune_visits(covered=ids[2], keep=2) == 3  # covered and beyond the last 2
    assert [v.id for v in store.visits()] == ids[3:]
    assert store.prune_visits(covered=ids[-1], keep=2) == 1 and [v.id for v in store.visits()] == ids[4:]


def test_the_prune_cursor_survives_every_prune_and_the_ids_go_on(store: MapStore) -> None:
    """`visits_pruned_through` (what recovery and verify read to refuse a replay that needs pruned visits)
    is the oldest id kept minus one: a prune keeps the newest even when asked to keep none, so ids are
    never handed out again and the cursor never falls back."""
    store.append(make_row(1))
    assert store.visits_pruned_through() == 0
    ids = [store.add_visit(visit(10 + i, 1, None)) for i in range(4)]
    assert store.visits_pruned_through() == 0
    assert store.prune_visits(covered=ids[-1], keep=0) == 3
    assert [v.id for v in store.visits()] == ids[3:] and store.visits_pruned_through() == ids[2]
    nxt = store.add_visit(visit(20, 1, None))
    assert nxt == ids[-1] + 1 and store.visits_pruned_through() == ids[2]


def test_a_row_s_place_and_the_rows_it_dropped_commit_with_it(store: MapStore) -> None:
    store.append(make_row(1))
    store.append(make_row(2))
    store.append(dataclasses.replace(make_row(3), place=1, drops=(2,)))
    store.drop([1], "forgotten")
    assert [r.place for r in store.rows()] == [None, None, 1]
    assert store.dropped() == {2: "appearance-cap", 1: "forgotten"}
    assert store.count() == 3  # the rows stay: the replay and the snapshots read them
    assert store.held() == 1  # but only row 3 is held (what the index holds and the row cap counts)


#: What version 9 added, undone (every older file lacks it).
#: What version 14 added, undone: the joins' `kept`, the delete triggers as version 12 made them.
V14_UNDONE = "".join(
    f"DROP TRIGGER {t}_no_delete; CREATE TRIGGER {t}_no_delete BEFORE DELETE ON {t} "
    f"WHEN NOT EXISTS (SELECT 1 FROM joins WHERE seq = OLD.seq) "
    f"BEGIN SELECT RAISE(ABORT, '{t} are append-only'); END;"
    for t in ("observations", "thumbnails", "keyframes")) + "ALTER TABLE joins DROP COLUMN kept;"
#: What version 13 added, undone: the flat rows (and what came after).
V13_UNDONE = V14_UNDONE + "DROP TABLE flat;"
#: What version 12 added, undone (every older file fabricated here lacks it): the visits' `row_seq`, the
#: joins' `observation_id`, the replay-order indexes, the delete triggers that let a joined row go.
V12_UNDONE = V13_UNDONE + "DROP INDEX visits_learned; DROP INDEX visits_row; " \
    "ALTER TABLE visits DROP COLUMN row_seq; " \
    "ALTER TABLE joins DROP COLUMN observation_id; " + "".join(
        f"DROP TRIGGER {t}_no_delete; CREATE TRIGGER {t}_no_delete BEFORE DELETE ON {t} "
        f"BEGIN SELECT RAISE(ABORT, '{t} are append-only'); END;"
        for t in ("observations", "thumbnails", "keyframes"))
V9_UNDONE = V12_UNDONE + "DROP TABLE repairs; ALTER TABLE loop_closures DROP COLUMN retracts;"


def _undone_to(path: Path, version: int, undone: str) -> None:
    """Today's file as schema `version` wrote it: `undone` (SQL, what the later versions added, undone)
    run on it, and its version."""
    conn = sqlite3.connect(path)
    conn.executescript(undone + f"""
        DROP TRIGGER meta_no_update;
        UPDATE meta SET value = '{version}' WHERE key = 'schema_version';
        CREATE TRIGGER meta_no_update BEFORE UPDATE ON meta
        BEGIN SELECT RAISE(ABORT, 'map metadata is frozen'); END;
    """)
    conn.close()


def _as_version(path: Path, version: int, changes: str) -> None:
    """Today's file as schema `version` wrote it: `changes` (SQL) undone from it, and its version (and what
    version 9 added: the repairs and the closures' `retracts`)."""
    changes = ("DROP TABLE joins;" if version < 10 else "") + changes  # version 10: the warm-up joins
    _undone_to(path, version, V9_UNDONE + changes)


def _as_version_4(path: Path) -> None:
    """No visits, no dropped rows, no place column, no recency, no visit keys or streams' states, no
    closures' `consolidated_into` or span."""
    _as_version(path, 4, """
        DROP TABLE visits;
        DROP TABLE dropped;
        DROP TABLE recency;
        DROP TABLE visit_keys;
        DROP TABLE stream_states;
        ALTER TABLE loop_closures DROP COLUMN consolidated_into;
        ALTER TABLE loop_closures DROP COLUMN span;
        ALTER TABLE loop_closures DROP COLUMN span_seqs;
        ALTER TABLE observations DROP COLUMN place;
    """)


def test_an_old_map_is_migrated_and_its_places_come_from_its_loop_closures(tmp_path: Path,
                                                                           meta: MapMeta) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        for i in range(1, 4):  # a first lap, rows 1-3
            made.append(make_row(i, stream="a", prev=i - 1 or None))
        for i in range(4, 7):  # a second lap that revisited rows 1-3 (a closure logged with each row)
            made.append(dataclasses.replace(make_row(i, stream="a", prev=i - 1), closure=NewClosure(
                stream="a", place_seq=i - 3, confidence=0.99, support=5)))
        made.append(make_row(7, stream="a", prev=6))  # no revisit: its own place
    _as_version_4(path)
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, reads as before
        assert ro.meta.schema_version == 4 and ro.dropped() == {} and list(ro.visits()) == []
        assert [r.place for r in ro.rows()] == [None] * 7
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        assert [r.place for r in store.rows()] == [None] * 7 and store.joined() == {4: 1, 5: 2, 6: 3}
        place_map = PlaceMap(None, 4096)
        place_map.rebuild(store.rows(), store.dropped(), store.joined())
        assert [place_map.place_of(s) for s in range(1, 8)] == [1, 2, 3, 1, 2, 3, 7]
        assert place_map.appearances(2) == [2, 5] and place_map.places() == 4
        store.append(dataclasses.replace(make_row(8, stream="a", prev=7), place=7))  # and it goes on
        assert store.get(8).place == 7


def test_visit_keys_outlive_the_pruned_visits_and_are_bounded_like_row_keys(tmp_path: Path,
                                                                             meta: MapMeta) -> None:
    """Schema 7 `visit_keys` (issue 34 item 6): kept whatever the visit log's pruning, the keys of the
    last `max_keys` visits."""
    with MapStore.create(tmp_path / "map.sqlite", meta, max_keys=3) as store:
        store.append(make_row(1))
        ids = [store.add_visit(visit(10 + i, 1, None, key=f"visit-key-{i:04d}")) for i in range(5)]
        assert store.prune_visits(covered=ids[-1], keep=1) == 4 and store.visit_stats()[0] == 1
        assert [store.key_record(f"visit-key-{i:04d}") is not None for i in range(5)] == [False, False,
                                                                                           True, True, True]
        with pytest.raises(DuplicateObservation):
            store.add_visit(visit(20, 1, None, key="visit-key-0004"))


def test_a_version_6_file_keeps_its_logged_visit_keys(tmp_path: Path, meta: MapMeta) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
        made.add_visit(visit(10, 1, None, key="visit-key-0001"))
    # As schema 6 wrote it: the key in the visit log.
    _as_version(path, 6, """
        UPDATE visits SET idempotency_key = 'visit-key-0001', fingerprint = (SELECT fingerprint FROM
            visit_keys), reply = (SELECT reply FROM visit_keys);
        DROP TABLE visit_keys;
        DROP TABLE stream_states;
        ALTER TABLE loop_closures DROP COLUMN consolidated_into;
        ALTER TABLE loop_closures DROP COLUMN span;
        ALTER TABLE loop_closures DROP COLUMN span_seqs;
    """)
    record = KeyRecord("visit-key-0001", "f" * 64, '{"reply": 1}')
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, read from the log
        assert ro.meta.schema_version == 6 and ro.key_record("visit-key-0001") == record
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        assert store.prune_visits(covered=10**6, keep=0) == 0  # the only visit stays (the newest)
        assert store.key_record("visit-key-0001") == record


def test_a_stream_s_state_commits_with_its_learned_step_and_is_pruned_once_a_snapshot_holds_it(
        store: MapStore) -> None:
    """Schema 7 `stream_states` (issue 34 item 7): the last learned step's state of each stream."""
    store.append(dataclasses.replace(make_row(1), resume=b"a1"))
    store.append(dataclasses.replace(make_row(2, stream="c"), resume=b"c2"))
    store.add_visit(dataclasses.replace(visit(10, 1, None), resume=b"b3"))
    store.append(dataclasses.replace(make_row(3), resume=b"a4"))
    assert store.stream_states() == {make_row(1).stream: b"a4", "c": b"c2", "b": b"b3"}
    assert store.prune_stream_states(through=2) == 1  # c's, at seq 2; b's visit is at clock 3
    assert set(store.stream_states()) == {make_row(1).stream, "b"}


@pytest.mark.parametrize("version", [6, 7])
def test_an_older_file_gains_the_visits_closure_column(tmp_path: Path, meta: MapMeta, version: int) -> None:
    """Schema 8 `loop_closures.consolidated_into`: a version 7 file gains it, a version 6 file goes
    through 7 (visit keys, streams' states) to it."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
        made.add_closure(NewClosure(stream="loc", place_seq=1, confidence=0.9, support=2))
    _as_version(path, version, "ALTER TABLE loop_closures DROP COLUMN consolidated_into;" + DROP_SPAN
                + ("DROP TABLE visit_keys; DROP TABLE stream_states;" if version == 6 else ""))
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, reads as before
        assert ro.meta.schema_version == version
        assert [c.consolidated_into for c in ro.closures(0, 10)] == [None]
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        closure = NewClosure(stream="b", place_seq=1, confidence=0.99, support=6)
        store.add_visit(dataclasses.replace(visit(10, 1, None), closure=closure))
        assert [(c.stream, c.seq, c.consolidated_into) for c in store.closures(0, 10)] == [
            ("loc", None, None), ("b", None, 1)]


def test_a_version_8_file_gains_the_closures_span(tmp_path: Path, meta: MapMeta) -> None:
    """Schema 9 `loop_closures.span`, `span_seqs` (issue 37): a version 8 file's closures read None (not
    recorded) before and after the migration; closures logged after it carry their span."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
        made.add_closure(NewClosure(stream="loc", place_seq=1, confidence=0.9, support=2))
    _as_version(path, 8, DROP_SPAN)
    with MapStore.open(path, readonly=True) as ro:  # read-only: not migrated, reads as before
        assert ro.meta.schema_version == 8
        assert [(c.span, c.span_seqs) for c in ro.closures(0, 10)] == [(None, None)]
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        store.add_closure(NewClosure(stream="loc", place_seq=1, confidence=0.95, support=9, span=3,
                                     span_seqs=(1, 2, 5)))
        store.append(dataclasses.replace(make_row(2, prev=1), closure=NewClosure(
            stream="a", place_seq=1, confidence=0.99, support=6, span=1, span_seqs=(1,))))
        assert [(c.stream, c.span, c.span_seqs) for c in store.closures(0, 10)] == [
            ("loc", None, None), ("loc", 3, (1, 2, 5)), ("a", 1, (1,))]
    with MapStore.open(path, readonly=True) as ro:  # and it is durable
        assert [c.span for c in ro.closures(0, 10)] == [None, 3, 1]


def test_verify_counts_only_the_rows_held_when_a_join_was_made(store: MapStore) -> None:
    """`join_problems` (docs/design/science.md §11.8): the live rule looks through the stream's newest
    `reach` rows still held, so a row dropped at an earlier step is not counted against a join's reach
    (verify called a legal join a problem); one more held row is."""
    reach = 3
    store.append(make_row(1, stream="old"))  # the old place
    store.append(make_row(2, stream="a"))  # the warm-up row, joined later
    store.append(make_row(3, stream="a", prev=2))
    store.append(dataclasses.replace(make_row(4, stream="a", prev=3), drops=(3,)))  # row 3 leaves
    store.append(make_row(5, stream="a", prev=4))
    store.append(dataclasses.replace(make_row(6, stream="a", prev=5), joins=((2, 1),)))
    # rows 3-5 were made after row 2, row 3 dropped before the join: 2 held, within the reach of 3
    assert store.join_problems(reach) == []
    assert [p.split(":")[0] for p in store.join_problems(reach - 1)] == ["join of row 2"]


def test_verify_reads_joins_over_frames_that_store_no_row_in_their_order(store: MapStore) -> None:
    """Found from outside: a restarted drive's warm-up rows were joined over two frames in a row, the
    newest `reach` held rows on the first, the older ones on the second, a consolidated frame that stores
    no row and so shares the first's `after_seq`; verify counted the rows the first step had joined
    against the second's reach and called a map written only by the service a problem."""
    reach = 3
    store.append(make_row(1, stream="old"))  # the old place
    for i in range(2, 7):
        store.append(make_row(i, stream="a", prev=i - 1 if i > 2 else None))
    for i, joins in ((7, ((6, 1), (5, 1), (4, 1))), (8, ((3, 1), (2, 1)))):  # two frames in a row
        store.add_visit(dataclasses.replace(visit(i, 1, 6), stream="a", joins=joins))
        time.sleep(0.002)  # (the next step's clock reads later)
    assert [v.after_seq for v in store.visits() if v.row is None] == [6, 6]  # no row between them
    # at the second step rows 4-6 had left: rows 2 and 3 were the newest held, within the reach of 3
    assert store.join_problems(reach) == []
    # a join over as many held rows as the reach is still found: rows 5 and 6 when row 4 was joined
    assert [p.split(":")[0] for p in store.join_problems(2)] == ["join of row 4"]
    assert [p.split(":")[0] for p in store.join_problems(1)] == ["join of row 2", "join of row 4",
                                                                 "join of row 5"]


def test_verify_orders_those_steps_by_the_log_not_the_clock(store: MapStore, monkeypatch) -> None:
    """Found in review: ordered by their wall-clock times, two such steps read the wrong way round after
    the clock stepped back between them, and an over-reach went unreported. The visits their joined
    rows became keep the log's order."""
    clock = ["2025-01-01T00:00:10.000000Z"]
    monkeypatch.setattr("storage.mapstore.visits.utc_now", lambda: clock[0])
    store.append(make_row(1, stream="old"))
    for i in range(2, 7):
        store.append(make_row(i, stream="a", prev=i - 1 if i > 2 else None))
    for i, joins in ((7, ((2, 1),)), (8, ((6, 1), (5, 1), (4, 1), (3, 1)))):  # row 2 first, over rows 3-6
        store.add_visit(dataclasses.replace(visit(i, 1, 6), stream="a", joins=joins))
        clock[0] = "2025-01-01T00:00:05.000000Z"  # the clock steps back between the two
    assert [p.split(":")[0] for p in store.join_problems(3)] == ["join of row 2", "join of row 3"]


def test_a_join_turns_its_row_into_a_visit_and_deletes_it_and_its_seq_is_never_handed_out_again(
        tmp_path: Path, meta: MapMeta) -> None:
    """Schema 12 (docs/design/science.md §11.8): the join, in its transaction, logs the joined row's frame
    as a visit of the old row (`row` = its seq, replayed as that row: after the row before it, before
    the rows after it) and deletes the row, its thumbnail and keyframe; the row's code and observation id
    are still read (the own-trail rule, a snapshot's last row), its seq is never handed out again, and
    the file's triggers let only a joined row go. Before: the row stayed, one a drive."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as store:
        store.append(make_row(1, stream="old"))
        store.append(dataclasses.replace(make_row(2, stream="a"), thumbnail=b"jpeg"))  # the warm-up row
        store.add_visit(NewVisit(stream="a", seq=1, context_prev_seq=2, input_sdr=np.arange(3),
                                 winner_cells=np.arange(3)))  # (a visit logged before the join)
        store.append(make_row(3, stream="a", prev=2))
        store.append(dataclasses.replace(make_row(4, stream="a", prev=3), joins=((2, 1),)))
        assert store.get(2) is None and store.count() == 3 and store.thumbnail(2) is None
        # the joined row first (where it was learned), then the visit logged after it
        assert [(v.seq, v.row, v.after_seq) for v in store.visits()] == [(1, 2, 1), (1, None, 2)]
        assert store.observation_id(2) == "obs-00000002" and store.joined_to(2) == 1
        assert np.array_equal(store.code(2), make_row(2).input_sdr)
        assert [(v.row, v.id) for v in store.visits(rows_after=2)] == [(None, 1)]  # a snapshot at 2 holds it
        assert store.join_problems(15) == [] and store.dropped()[2] == "joined"
        assert store.held() == 3  # rows 1, 3, 4: the joined row is dropped
    conn = sqlite3.connect(path)
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        conn.execute("DELETE FROM observations WHERE seq = 3")  # a row no join names stays
    conn.close()
    with MapStore.open(path) as store:
        store.append(make_row(5, stream="a", prev=4))
        store.append(dataclasses.replace(make_row(6, stream="a", prev=5), joins=((5, 1),)))
    with MapStore.open(path) as store:  # the newest row joined away: its seq stays used
        assert store.count() == 4 and store.last_seq() == 6 and store.next_seq() == 7


def test_a_rows_flatness_commits_with_it_and_a_rebuild_knows_it(tmp_path: Path, meta: MapMeta) -> None:
    """Schema 13 `flat` (docs/design/science.md §11.7): a row whose frame was flat is recorded in its
    transaction; the recovery's rebuild reads it back (a later flat frame is a visit of it, whatever its
    code); a row a warm-up join deletes leaves it too."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as store:
        store.append(make_row(1))
        store.append(dataclasses.replace(make_row(2, prev=1), flat=True))
        store.append(dataclasses.replace(make_row(3, prev=2), flat=True))
        store.append(dataclasses.replace(make_row(4, prev=3), joins=((3, 1),)))  # row 3 joined away
        assert store.flat() == {2}
    with MapStore.open(path) as store:
        assert store.flat() == {2}
        place_map = PlaceMap(None, 4096)
        place_map.rebuild(store.rows(), store.dropped(), flat=store.flat())
        assert place_map.flat[[1, 2, 4]].tolist() == [False, True, False]


def test_a_version_12_file_is_migrated_and_its_rows_are_not_known_flat(tmp_path: Path, meta: MapMeta) -> None:
    """Schema 12 -> 13: the `flat` table, empty: an older file's rows read as not flat (they were stored
    before flatness was), and the map goes on recording it."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1))
        made.append(dataclasses.replace(make_row(2, prev=1), flat=True))
    _undone_to(path, 12, V13_UNDONE)
    with MapStore.open(path, readonly=True) as old:  # read-only: as it is
        assert old.meta.schema_version == 12 and old.flat() == set()
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION and store.flat() == set()
        place_map = PlaceMap(None, 4096)
        place_map.rebuild(store.rows(), flat=store.flat())
        assert not place_map.flat[[1, 2]].any()
        store.append(dataclasses.replace(make_row(3, prev=2), flat=True))
        assert store.flat() == {3}


def test_the_oldest_plain_visit_kept_is_after_every_pruned_one_where_a_join_s_visit_is_older(
        store: MapStore) -> None:
    """A review: a warm-up join's visit takes its row's place back in the log, so the oldest visit kept
    may be a join's, learned after visits the prune took; the repair's mark goes before the oldest visit
    a consolidated frame made (`service.maps.repair`)."""
    store.append(make_row(1, stream="old"))
    store.append(make_row(2, stream="a"))  # the warm-up row, joined later
    store.append(make_row(3, stream="a", prev=2))
    first = store.add_visit(dataclasses.replace(visit(10, 1, 3), stream="b"))  # to be pruned
    store.append(dataclasses.replace(make_row(4, stream="a", prev=3), joins=((2, 1),)))  # row 2's visit
    plain = store.add_visit(dataclasses.replace(visit(11, 1, 4), stream="b"))
    assert store.oldest_plain_visit() == first
    assert store.prune_visits(covered=first, keep=1) == 1
    kept = list(store.visits())
    assert kept[0].row == 2 and kept[0].id > first  # the join's visit: first in the log, not the oldest
    assert store.oldest_plain_visit() == plain


def test_a_kept_join_keeps_its_row_held_and_on_disk_and_logs_the_drops_of_its_place(
        tmp_path: Path, meta: MapMeta) -> None:
    """Schema 14 (docs/design/science.md §11.8): a warm-up join that keeps its row (another season's first
    frames: like the old row, not represented by it) logs the join alone, `kept`; the row stays in the
    file, held, its own record, and the file's triggers still refuse to delete it. A visit's transaction
    carries the appearance-cap drops its kept joins caused. `verify` tells a kept join from a join whose
    drop is missing, and a kept join whose row was dropped as joined."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as store:
        store.append(make_row(1, stream="old"))
        store.append(make_row(2, stream="old", prev=1))
        store.append(dataclasses.replace(make_row(3, stream="a"), thumbnail=b"jpeg"))  # warm-up rows
        store.append(make_row(4, stream="a", prev=3))
        store.append(dataclasses.replace(make_row(5, stream="a", prev=4), kept=((3, 1),)))
        store.add_visit(dataclasses.replace(visit(6, 2, 5), stream="a", kept=((4, 2),), drops=(2,)))
        assert store.joins() == [(3, 1), (4, 2)] and store.joined_to(3) == 1
        assert store.get(3) is not None and store.thumbnail(3) == b"jpeg"  # on disk, as stored
        assert store.dropped() == {2: "appearance-cap"}  # the visit's drop; rows 3 and 4 are held
        assert store.held() == 4 and store.joined_row(3) is None
        assert store.join_problems(3) == []
    conn = sqlite3.connect(path)
    with pytest.raises(sqlite3.IntegrityError, match="append-only"):
        conn.execute("DELETE FROM observations WHERE seq = 3")
    conn.execute("INSERT INTO dropped (seq, reason, after_seq, created_at) VALUES (3, 'joined', 5, 'x')")
    conn.execute("UPDATE joins SET kept = 0 WHERE seq = 4")  # a join that drops its row, not dropped
    conn.commit()
    conn.close()
    with MapStore.open(path, readonly=True) as store:
        assert sorted(p.split(":")[0] for p in store.join_problems(3)) == [
            "join of row 4", "kept join of row 3", "row 3 is dropped as joined without a join"]


def test_a_version_13_file_is_migrated_and_its_joins_read_as_not_kept(tmp_path: Path, meta: MapMeta) -> None:
    """Schema 13 -> 14: `joins.kept`, 0 for every older join (each dropped its row), and the delete
    triggers that let only a join that does not keep its row take it."""
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as made:
        made.append(make_row(1, stream="old"))
        made.append(make_row(2, stream="a"))
        made.append(dataclasses.replace(make_row(3, stream="a", prev=2), joins=((2, 1),)))
    _undone_to(path, 13, V14_UNDONE)
    with MapStore.open(path, readonly=True) as old:  # read-only: as it is
        assert old.meta.schema_version == 13 and old.joins() == [(2, 1)] and old.join_problems(3) == []
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION and store.join_problems(3) == []
        store.append(make_row(4, stream="a"))
        store.append(dataclasses.replace(make_row(5, stream="a", prev=4), kept=((4, 1),)))
        assert store.joins() == [(2, 1), (4, 1)] and store.get(4) is not None and store.join_problems(3) == []


def test_verify_reads_a_drop_at_an_earlier_consolidated_frame_as_made_before_a_later_join(
        store: MapStore) -> None:
    """A review: a visit's appearance-cap drops (a kept join's, schema 14) share the `after_seq` of the
    visits after it; verify counted a row dropped at one consolidated frame as held at a join made at the
    next, and called a map written only by the service a problem. A step's own drops (logged after its
    joins) were held at its joins, as the live rule read them."""
    reach = 3
    store.append(make_row(1, stream="old"))
    for i in range(2, 6):
        store.append(make_row(i, stream="a", prev=i - 1 if i > 2 else None))
    store.add_visit(dataclasses.replace(visit(6, 1, 5), stream="a", kept=((5, 1),), drops=(4,)))
    time.sleep(0.002)  # (the next step's clock reads later)
    store.add_visit(dataclasses.replace(visit(7, 1, 5), stream="a", joins=((2, 1),)))
    # rows 3 and 5 held since row 2, row 4 dropped at the step before: within the reach of 3
    assert store.join_problems(reach) == []
    assert [p.split(":")[0] for p in store.join_problems(2)] == ["join of row 2"]
    # a step's own drops count: row 4 dropped with the join of row 2 was held at it
    store.add_visit(dataclasses.replace(visit(8, 1, 5), stream="a", joins=((3, 1),), drops=(5,)))
    assert [p.split(":")[0] for p in store.join_problems(2)] == ["join of row 2"]
    assert [p.split(":")[0] for p in store.join_problems(1)] == ["join of row 2", "join of row 3"]


def test_one_step_s_joins_kept_or_not_share_one_time(store: MapStore) -> None:
    """A review: a step's dropping and kept joins were stamped by two clock reads, which `join_problems`
    reads as two steps (a later time is a later step where no visit orders them)."""
    store.append(make_row(1, stream="old"))
    for i in range(2, 5):
        store.append(make_row(i, stream="a", prev=i - 1 if i > 2 else None))
    store.add_visit(dataclasses.replace(visit(5, 1, 4), stream="a", joins=((4, 1),), kept=((3, 1), (2, 1))))
    times = {r[0] for r in store._db().execute("SELECT created_at FROM joins")}
    assert len(times) == 1 and store.joins() == [(2, 1), (3, 1), (4, 1)]
