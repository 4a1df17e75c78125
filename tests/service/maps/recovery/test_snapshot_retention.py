"""Deleting snapshots, retention of manual ones, and their disk use (docs/design/service.md §1.5, issue
19 item 10): `DELETE /v1/maps/{id}/snapshots/{sid}`; CORTEXLOC_SNAPSHOT_MANUAL_KEEP and _BYTES delete the
oldest manual snapshots first; the snapshot the next recovery starts from is never deleted before a
newer one exists; the map resource and /metrics say what the snapshots take on disk."""

from __future__ import annotations

import re

from tests.service.helpers import frame, make_client, post


def snap(c, map_id: str = "default") -> dict:
    r = c.post(f"/v1/maps/{map_id}/snapshots")
    assert r.status_code == 201, r.text
    return r.json()


def listed(c, map_id: str = "default") -> list[str]:
    return [s["snapshot_id"] for s in c.get(f"/v1/maps/{map_id}/snapshots").json()["snapshots"]]


def test_delete_a_snapshot_but_not_the_one_recovery_starts_from(tmp_path):
    data = tmp_path / "data"
    with make_client(data, snapshot_every=0) as c:
        assert post(c, frame(0)).status_code == 200
        a = snap(c)["snapshot_id"]
        assert post(c, frame(1)).status_code == 200
        b = snap(c)["snapshot_id"]
        r = c.delete(f"/v1/maps/default/snapshots/{b}")
        assert r.status_code == 409, r.text
        assert r.json()["type"] == "urn:cortexloc:problem:snapshot-in-use"
        assert c.delete(f"/v1/maps/default/snapshots/{a}").status_code == 204
        assert listed(c) == [b]
        assert not (data / "maps" / "default" / "snapshots" / a).exists()
        assert c.delete(f"/v1/maps/default/snapshots/{a}").status_code == 404
        c_id = snap(c)["snapshot_id"]
        assert c.delete(f"/v1/maps/default/snapshots/{b}").status_code == 204  # c is newer now
        assert listed(c) == [c_id]
    with make_client(data, snapshot_every=0) as c:  # recovers from the one left
        assert c.get("/v1/maps/default").json()["recovery"]["snapshot_id"] == c_id


def test_after_a_restore_the_restored_snapshot_is_the_one_kept(tmp_path):
    with make_client(tmp_path / "data", snapshot_every=0) as c:
        assert post(c, frame(0)).status_code == 200
        a = snap(c)["snapshot_id"]
        for i in (1, 2):
            assert post(c, frame(i)).status_code == 200
        assert c.post(f"/v1/maps/default/snapshots/{a}/restore").status_code == 200
        pre = listed(c)[0]  # the pre-restore snapshot: newest, but on the branch the restore left
        assert c.delete(f"/v1/maps/default/snapshots/{a}").status_code == 409
        assert c.delete(f"/v1/maps/default/snapshots/{pre}").status_code == 204
        assert listed(c) == [a]


def test_manual_snapshots_beyond_the_count_go_oldest_first(tmp_path):
    with make_client(tmp_path / "data", snapshot_every=2, snapshot_manual_keep=2) as c:
        taken = []
        for i in range(4):
            assert post(c, frame(i)).status_code == 200  # an automatic snapshot every second row
            taken.append(snap(c)["snapshot_id"])
        snaps = c.get("/v1/maps/default/snapshots").json()["snapshots"]
        assert [s["snapshot_id"] for s in snaps if s["kind"] == "manual"] == taken[:1:-1]
        assert sum(s["kind"] == "auto" for s in snaps) == 2  # untouched


def test_pre_restore_snapshots_are_kept_to_the_same_count_apart_from_manual_ones(tmp_path):
    """Found from outside: each restore wrote a pre-restore snapshot that no retention reached, so a loop
    of restores filled the disk (a map's size a restore, kept for good)."""
    with make_client(tmp_path / "data", snapshot_every=0, snapshot_manual_keep=2) as c:
        assert post(c, frame(0)).status_code == 200
        a = snap(c)["snapshot_id"]
        pres = []
        for i in range(4):
            assert post(c, frame(1 + i)).status_code == 200
            assert c.post(f"/v1/maps/default/snapshots/{a}/restore").status_code == 200
            pres.append(listed(c)[0])
        snaps = c.get("/v1/maps/default/snapshots").json()["snapshots"]
        assert [s["snapshot_id"] for s in snaps if s["kind"] == "pre-restore"] == pres[:1:-1]  # newest 2
        assert [s["snapshot_id"] for s in snaps if s["kind"] == "manual"] == [a]  # counted apart
        for p in pres[2:]:  # the kept ones still undo their restore
            assert c.post(f"/v1/maps/default/snapshots/{p}/restore").status_code == 200


def test_a_restore_keeps_its_pre_restore_snapshot_even_alone_over_the_byte_limit(tmp_path):
    """Found in review: pruned after the restore, the new pre-restore snapshot was no longer the recovery
    base, and alone over `CORTEXLOC_SNAPSHOT_MANUAL_BYTES` it was deleted at once, with the observations
    the restore took away."""
    with make_client(tmp_path / "data", snapshot_every=0, snapshot_manual_bytes=1) as c:
        assert post(c, frame(0)).status_code == 200
        a = snap(c)["snapshot_id"]
        assert post(c, frame(1)).status_code == 200
        r = c.post(f"/v1/maps/default/snapshots/{a}/restore")
        assert r.status_code == 200 and r.json()["discarded_observations"] == 1
        kinds = [s["kind"] for s in c.get("/v1/maps/default/snapshots").json()["snapshots"]]
        assert kinds == ["pre-restore", "manual"]
        pre = listed(c)[0]
        assert c.post(f"/v1/maps/default/snapshots/{pre}/restore").status_code == 200  # the undo
        assert c.get("/v1/maps/default").json()["observations"] == 2


def test_manual_snapshots_beyond_the_bytes_go_but_never_the_newest(tmp_path):
    with make_client(tmp_path / "data", snapshot_every=0, snapshot_manual_bytes=1) as c:
        for i in range(3):
            assert post(c, frame(i)).status_code == 200
            newest = snap(c)["snapshot_id"]
            assert listed(c) == [newest]  # over the byte limit alone, but recovery starts from it


def test_snapshot_disk_use_is_in_the_map_resource_and_metrics(tmp_path):
    with make_client(tmp_path / "data", snapshot_every=0) as c:
        assert post(c, frame(0)).status_code == 200
        sizes = [snap(c)["bytes"] for _ in range(2)]
        m = c.get("/v1/maps/default").json()
        assert (m["snapshot_count"], m["snapshots_bytes"]) == (2, sum(sizes))
        text = c.get("/metrics").text
        assert re.search(r'cortexloc_map_snapshots\{map="default"\} 2\.0', text)
        got = re.search(r'cortexloc_map_snapshots_bytes\{map="default"\} (\S+)', text)
        assert got and float(got.group(1)) == sum(sizes)
        assert re.search(r"cortexloc_memory_used_bytes \d", text)
        files = (tmp_path / "data" / "maps" / "default" / "snapshots").rglob("*")
        on_disk = sum(f.stat().st_size for f in files if f.is_file())
        assert on_disk == sum(sizes)


def test_automatic_pruning_keeps_the_snapshot_recovery_starts_from(tmp_path):
    with make_client(tmp_path / "data", snapshot_every=2, snapshot_keep=0) as c:
        for i in range(4):
            assert post(c, frame(i)).status_code == 200
        snaps = c.get("/v1/maps/default/snapshots").json()["snapshots"]
        assert [(s["kind"], s["seq"]) for s in snaps] == [("auto", 4)]  # the older one went
