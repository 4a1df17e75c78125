"""`cortexloc verify`: an offline full check that finds what recovery from a snapshot never looks at,
and changes nothing (issue 11, item 12)."""

from __future__ import annotations

import re
import sqlite3
from pathlib import Path

from typer.testing import CliRunner

from service.cli import app as cli_app
from tests.service.helpers import frame, make_client, post
from tests.service.maps.recovery.test_recovery import corrupt_winner_cells, snapshot_dirs


def files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def run_verify(data: Path, *args: str):
    return CliRunner().invoke(cli_app, ["verify", "--data-dir", str(data), *args])


def test_verify_reports_a_changed_row_under_a_snapshot_and_changes_nothing(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=4) as c:
        c.post("/v1/maps", json={"map_id": "other"})
        for p in (0, 1, 2, 3, 0, 1, 2, 3, 4):
            post(c, frame(p))
        post(c, frame(5), map_id="other")
    ok = run_verify(data)
    assert ok.exit_code == 0, ok.output
    assert re.search(r"map default: ok; 9 rows replayed .* 0 mismatched; snapshots 3 ok, 0 bad", ok.output)
    assert "2 map(s) checked, 0 with problems" in ok.output
    # Seq 3 lies under every snapshot: recovery never replays it again, so only verify can see it.
    corrupt_winner_cells(data / "maps" / "default" / "map.sqlite", seq=3)
    newest = snapshot_dirs(data)[0]
    (newest / "memory.npz").write_bytes(b"rot")
    before = files(data)
    r = run_verify(data, "--map", "default")
    assert r.exit_code == 1, r.output
    assert "map default: PROBLEMS; 9 rows replayed" in r.output
    assert "differ from the replay at seq 3\n" in r.output
    assert "snapshots 2 ok, 1 bad" in r.output and f"snapshot {newest.name}:" in r.output
    assert "1 map(s) checked, 1 with problems" in r.output
    assert files(data) == before  # byte-identical, and no -wal/-shm or other file appeared
    assert run_verify(data, "--map", "other").exit_code == 0
    assert run_verify(data, "--map", "nope").exit_code == 2


def test_verify_reports_a_malformed_map_file_and_checks_the_other_maps(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        c.post("/v1/maps", json={"map_id": "other"})
        for p in range(6):
            post(c, frame(p))
        post(c, frame(5), map_id="other")
    db = data / "maps" / "default" / "map.sqlite"
    conn = sqlite3.connect(db)
    root = conn.execute("SELECT rootpage FROM sqlite_master WHERE name = 'observations'").fetchone()[0]
    size = conn.execute("PRAGMA page_size").fetchone()[0]
    conn.close()
    with open(db, "r+b") as f:  # random bytes over a page of the rows: "database disk image is malformed"
        f.seek((root - 1) * size)
        f.write(bytes(range(256)) * (size // 256))
    r = run_verify(data)
    assert r.exit_code == 1, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception  # no traceback
    assert "map default: PROBLEMS" in r.output and "malformed" in r.output
    assert re.search(r"map other: ok; 1 rows replayed", r.output), r.output
    assert "2 map(s) checked, 1 with problems" in r.output
