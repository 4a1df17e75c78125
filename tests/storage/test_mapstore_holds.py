"""What a `map.sqlite` holds is read once, when the store opens it (`storage.mapschema.Holds`): each
flag says whether its table or column is in the file, for a file of every schema version, and no reader
of `storage/mapstore/` compares schema versions (issue 38: the flags were re-checked in every reader)."""

from __future__ import annotations

import ast
import dataclasses
import sqlite3
from pathlib import Path

import pytest

from storage import mapschema
from storage.mapschema import SCHEMA_VERSION, Holds
from storage.mapstore import MapMeta, MapStore
from tests.storage.v1_files import write_v1

ROOT = Path(__file__).resolve().parents[2]

#: flag -> (table, column or None: the table itself)
WHERE = {
    "thumbnails": ("thumbnails", None), "idempotency_keys": ("idempotency_keys", None),
    "loop_closures": ("loop_closures", None), "keyframes": ("keyframes", None),
    "closure_verification": ("loop_closures", "verification"), "visits": ("visits", None),
    "dropped": ("dropped", None), "recency": ("recency", None), "visit_keys": ("visit_keys", None),
    "stream_states": ("stream_states", None),
    "closure_consolidated_into": ("loop_closures", "consolidated_into"),
    "repairs": ("repairs", None), "closure_retracts": ("loop_closures", "retracts"), "joins": ("joins", None),
    "closure_span": ("loop_closures", "span"), "joined_rows": ("visits", "row_seq"), "flat": ("flat", None),
    "kept_joins": ("joins", "kept"),
}


def _file_of_version(path: Path, version: int) -> None:
    """A file as `version` wrote it: version 1's layout, then the migration steps up to `version`."""
    write_v1(path, MapMeta(map_id="m", params={}, projection_sha256="0" * 64, encoder_id="e",
                           cell_dtype="uint16"), [])
    steps = [getattr(mapschema, f"_MIGRATE_V{v}") for v in range(2, version + 1)]
    conn = sqlite3.connect(path, isolation_level=None)
    conn.executescript("BEGIN IMMEDIATE;" + "".join(steps) + "COMMIT;")
    conn.close()


@pytest.mark.parametrize("version", range(1, SCHEMA_VERSION + 1))
def test_each_flag_says_what_the_file_holds(tmp_path, version):
    path = tmp_path / "map.sqlite"
    _file_of_version(path, version)
    with MapStore.open(path, readonly=True) as store:
        assert store.meta.schema_version == version
        holds = store.holds
    conn = sqlite3.connect(path)
    tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}

    def columns(table: str) -> set[str]:
        return {r[1] for r in conn.execute(f"PRAGMA table_info({table})")}

    flags = {f.name for f in dataclasses.fields(Holds) if f.type in ("bool", bool)}
    assert flags == set(WHERE)  # every flag is checked here
    for flag, (table, column) in WHERE.items():
        there = table in tables and (column is None or column in columns(table))
        assert getattr(holds, flag) is there, (flag, version)
    read = {c.strip() for c in holds.row_columns.split(",")} - {"NULL"}
    assert read <= columns("observations") and len(holds.row_columns.split(",")) == 11
    conn.close()


def test_a_written_file_holds_everything(tmp_path):
    with MapStore.create(tmp_path / "map.sqlite", MapMeta(map_id="m", params={}, projection_sha256="0" * 64,
                                                          encoder_id="e", cell_dtype="uint16")) as store:
        assert all(getattr(store.holds, flag) for flag in WHERE)
        assert store.holds.row_columns == mapschema.COLUMNS


def test_no_reader_compares_schema_versions():
    """Only the store's opening reads the version (to refuse a newer file and to read `Holds` once)."""
    found = []
    for path in sorted([*ROOT.glob("storage/mapstore*.py"), *ROOT.glob("storage/mapstore/*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Compare) and any(
                    isinstance(n, ast.Attribute) and n.attr == "schema_version"
                    for side in (node.left, *node.comparators) for n in ast.walk(side)):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert len(found) == 1 and found[0].startswith("storage/mapstore/store.py:"), found
