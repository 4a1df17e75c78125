"""map.sqlite schema 9 (docs/design/science.md §11.6; docs/design/service.md §4.2): a repair of merges
made from a stream's own recent trail, in one transaction: visits re-made as rows, rows given back their
place, loop closures retracted by new entries; and the migration of an older file."""

from __future__ import annotations

import dataclasses
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from storage.mapschema import SCHEMA_VERSION, NewClosure
from storage.mapstore import MapMeta, MapStore
from tests.storage.conftest import make_row
from tests.storage.test_mapstore_places import DROP_SPAN, _as_version, visit


def hit(store: MapStore) -> tuple[int, int]:
    """Rows 1-3, a visit into row 2 and row 3's closure naming row 2: (the visit's id, the closure's)."""
    store.append(make_row(1))
    store.append(make_row(2, prev=1))
    store.append(dataclasses.replace(make_row(3, prev=2), place=2,
                                     closure=NewClosure(stream="default", place_seq=2, confidence=0.9,
                                                        support=4)))
    v = store.add_visit(dataclasses.replace(visit(10, 2, 3), stream="default"))
    return v, store.closures(0, 10)[0].id


def test_a_repair_remakes_visits_unjoins_rows_and_retracts_closures_in_one_go(store: MapStore) -> None:
    v, c = hit(store)
    [made] = store.repair(list(store.visits()), [(3, 2)], [c])
    row = store.get(made)
    assert made == 4 and store.count() == 4 and row is not None
    assert (row.stream, row.context_prev_seq, row.place, row.image_sha256) == ("default", 3, None, "")
    assert np.array_equal(row.input_sdr, make_row(10).input_sdr)
    assert np.array_equal(row.winner_cells, make_row(10).winner_cells)
    assert [(r.kind, r.seq, r.visit, r.was) for r in store.repairs()] == [
        ("split", 4, v, 2), ("unjoin", 3, None, 2)]
    log = store.closures(0, 10)
    assert [(e.id, e.retracts, e.seq, e.place_seq, e.confidence) for e in log] == [
        (c, None, 3, 2, 0.9), (c + 1, c, 3, 2, 0.0)]
    assert store.retracted() == {c} and store.joined() == {3: 2}  # a retraction joins nothing
    # a closure is retracted once, whatever asks again; the log's rows are never edited
    store.repair([], [], [c])
    assert len(store.closures(0, 10)) == 2
    with pytest.raises(sqlite3.IntegrityError):  # a row is re-made once
        store.repair(list(store.visits()), [], [])
    assert store.count() == 4 and store.next_seq() == 5  # the failed one consumed no seq


def test_a_version_8_file_is_migrated_keeping_its_log(tmp_path: Path, meta: MapMeta) -> None:
    path = tmp_path / "map.sqlite"
    with MapStore.create(path, meta) as store:
        v, c = hit(store)
    _as_version(path, 8, DROP_SPAN)
    with MapStore.open(path, readonly=True) as old:
        assert old.repairs() == [] and old.retracted() == set() and old.closures(0, 10)[0].retracts is None
    with MapStore.open(path) as store:
        assert store.meta.schema_version == SCHEMA_VERSION
        assert store.repair(list(store.visits()), [], [c]) == [4] and store.retracted() == {c}
        assert [x.id for x in store.visits()] == [v]  # the visit stays: the replay teaches the memory with it
