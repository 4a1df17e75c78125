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


def _edit_row_metadata(db: Path, seq: int, text: str) -> None:
    """Write `text` as a row's stored metadata past the append-only triggers (an edit outside the service)."""
    conn = sqlite3.connect(db)
    triggers = conn.execute("SELECT name, sql FROM sqlite_master WHERE type = 'trigger' "
                            "AND tbl_name = 'observations'").fetchall()
    with conn:
        for name, _ in triggers:
            conn.execute(f'DROP TRIGGER "{name}"')
        conn.execute("UPDATE observations SET metadata = ? WHERE seq = ?", (text, seq))
        for _, sql in triggers:
            conn.execute(sql)
    conn.close()


def test_verify_names_a_row_whose_metadata_is_unreadable_and_checks_the_other_maps(tmp_path):
    # Found from outside: a JSONDecodeError's traceback, and the maps after it never checked.
    data = tmp_path / "data"
    with make_client(data) as c:
        c.post("/v1/maps", json={"map_id": "other"})
        for p in range(4):
            post(c, frame(p), metadata='{"stamp": 1.5}')
        post(c, frame(5), map_id="other")
    _edit_row_metadata(data / "maps" / "default" / "map.sqlite", 2, "{bad")
    r = run_verify(data)
    assert r.exit_code == 1, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), r.exception  # no traceback
    assert "map default: PROBLEMS" in r.output and "observation seq 2" in r.output, r.output
    assert "unreadable" in r.output
    assert re.search(r"map other: ok; 1 rows replayed", r.output), r.output
    assert "2 map(s) checked, 1 with problems" in r.output
    with make_client(data) as c:  # the service says the same: that map failed as corrupt, the other serves
        m = c.get("/v1/maps/default").json()
        assert (m["state"], m["state_reason"]) == ("failed", "database-corrupt")
        assert c.get("/readyz").status_code == 200 and post(c, frame(6), map_id="other").status_code == 200


def test_a_check_that_fails_outright_is_that_maps_problem_and_the_others_are_checked(tmp_path, monkeypatch):
    import service.maps.recovery as recovery

    data = tmp_path / "data"
    with make_client(data) as c:
        c.post("/v1/maps", json={"map_id": "other"})
        post(c, frame(1))
        post(c, frame(5), map_id="other")
    real = recovery.verify_map

    def flaky(catalog, record, **kw):
        if record.map_id == "default":
            raise RuntimeError("a fault no check names")
        return real(catalog, record, **kw)

    monkeypatch.setattr(recovery, "verify_map", flaky)
    r = run_verify(data)
    assert r.exit_code == 1 and (r.exception is None or isinstance(r.exception, SystemExit)), r.output
    assert "map default: PROBLEMS" in r.output and "RuntimeError: a fault no check names" in r.output
    assert re.search(r"map other: ok; 1 rows replayed", r.output), r.output
    assert "2 map(s) checked, 1 with problems" in r.output


def test_the_progress_bar_never_shows_more_done_than_its_total(capsys):
    # verify on a live data directory showed 149/138: rows learned after the total was read
    from service.cli.common import progress

    with progress("verify x") as tick:
        assert tick is not None
        tick(149, 138)
    assert "149/149" in capsys.readouterr().err
