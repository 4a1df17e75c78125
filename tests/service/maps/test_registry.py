"""MapRegistry without HTTP (service/maps/registry.py): creation through the one configuration, the
refusals before anything is written, reopening by replay, and a stored map this version rejects served
as failed while the others serve (docs/design/service.md §1.1, §4.4)."""

from __future__ import annotations

import json

import pytest

from service.maps.config import MapOptions
from service.maps.errors import InvalidConfiguration, InvalidMapId, MapAlreadyExists
from service.maps.failed import FailedMap
from tests.service.helpers import tm_digest
from tests.service.maps.maps_fixtures import registry, route, step


def test_a_created_map_is_reopened_by_replay_as_it_was(tmp_path):
    with registry(tmp_path) as reg:
        rt = reg.create("lab", MapOptions(seed=3, memory="tm", revisit_threshold=0.7))
        for f in route(5):
            step(rt, f)
        before = (rt.store.count(), tm_digest(rt.tm), rt.config)
    with registry(tmp_path) as reg:
        rt = reg.get("lab")
        assert rt.state == "ready" and (rt.store.count(), tm_digest(rt.tm), rt.config) == before
        assert rt.recovery["source"] == "replay" and rt.recovery["mismatches"] == 0


def test_refusals_leave_nothing_behind(tmp_path):
    with registry(tmp_path) as reg:
        with pytest.raises(InvalidMapId):
            reg.create("Bad Id")
        with pytest.raises(InvalidMapId):  # a last newline: the pattern's `$` matches before it
            reg.create("lab\n")
        with pytest.raises(InvalidConfiguration):
            reg.create("lab", MapOptions(memory="lstm"))
        with pytest.raises(MapAlreadyExists):
            reg.create("default")
        assert set(reg.maps) == {"default"} and [r.map_id for r in reg.catalog.list_maps()] == ["default"]
        assert not (tmp_path / "maps" / "lab").exists()


def test_a_stored_configuration_this_version_rejects_fails_that_map_alone(tmp_path):
    with registry(tmp_path) as reg:
        reg.create("lab")
    db = reg.catalog.layout.catalog
    import sqlite3

    with sqlite3.connect(db) as con:  # what an older or newer version might have written
        params = json.loads(con.execute("SELECT params FROM maps WHERE map_id='lab'").fetchone()[0])
        changed = json.dumps({**params, "memory": "lstm"})
        con.execute("UPDATE maps SET params=? WHERE map_id='lab'", (changed,))
    with registry(tmp_path) as reg:
        failed = reg.get("lab")
        assert isinstance(failed, FailedMap) and failed.state_reason == "open-failed"
        assert failed.info().params["memory"] == "lstm"  # shown as stored, never run
        assert reg.get("default").state == "ready"


def test_a_deleted_map_and_a_replaced_memory_leave_the_process_at_once(tmp_path):
    """Found from outside: creating and deleting maps took the process's RSS far over its memory budget.
    A deleted map's objects sit in reference cycles; only the collector's rare full pass freed them (here
    it is off, so only the service's own collection, `budget.give_back`, can: without it the deleted map
    stays). The memory a restore replaces is in no cycle: it is freed by its last reference going, with
    or without `give_back` (checked by making it a no-op); the test keeps that it is freed at once."""
    import gc
    import weakref

    gc.collect()
    gc.disable()
    try:
        with registry(tmp_path) as reg:
            rt = reg.create("lab")
            for f in route(3):
                step(rt, f)
            snap = rt.snapshot("manual").snapshot_id
            for f in route(2, seed=1):
                step(rt, f)
            old_model = weakref.ref(rt.model)
            rt.restore(snap)
            assert old_model() is None  # the memory the restore replaced
            gone = weakref.ref(rt)
            del rt
            reg.delete("lab")
            assert gone() is None
    finally:
        gc.enable()
