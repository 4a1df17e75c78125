"""`storage.layout.Layout`: the one description of a data directory (docs/design/service.md §4.1)."""

from __future__ import annotations

from pathlib import Path

from models.frontend import slsbh
from storage.layout import Layout
from tests.service.helpers import frame, make_client, post


def test_paths_of_a_data_directory(tmp_path: Path) -> None:
    lay = Layout(str(tmp_path))
    assert lay == Layout(tmp_path) and lay.root == tmp_path
    assert lay.catalog == tmp_path / "catalog.sqlite"
    assert lay.map_db("m") == tmp_path / "maps" / "m" / "map.sqlite"
    assert lay.snapshot_dir("m", "s") == lay.snapshots_dir("m") / "s"
    assert lay.snapshot_dir("m", "s") == tmp_path / Layout.snapshot_relpath("m", "s")
    assert Layout.snapshot_relpath("m", "s") == "maps/m/snapshots/s"  # relative: the directory can move


def test_projection_is_where_save_projection_puts_it(tmp_path: Path) -> None:
    lay = Layout(tmp_path)
    path, sha = slsbh.save_projection(slsbh.make_projection(8, 4, seed=0), lay.projections)
    assert lay.projection(sha) == path


def test_the_catalog_and_the_service_follow_it(tmp_path: Path) -> None:
    # Every writer of the data directory puts its files where the layout says, whichever module writes.
    data = tmp_path / "data"
    with make_client(data) as c:
        assert post(c, frame(0)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        catalog = c.app.state.registry.catalog
        rt = c.app.state.registry.get("default")
        lay = catalog.layout
        assert lay == Layout(data) and catalog.path == lay.catalog
        assert rt.snapshot_dir(sid) == lay.snapshot_dir("default", sid)
        assert catalog.get_snapshot("default", sid).path == Layout.snapshot_relpath("default", sid)
        sha = rt.record.params["projection_sha256"]
        assert rt.projection_path == lay.projection(sha)
    assert lay.map_db("default").is_file() and lay.projection(sha).is_file()
    assert (lay.snapshot_dir("default", sid) / "manifest.json").is_file()
