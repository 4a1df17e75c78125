"""Loop closure while mapping (docs/design/science.md §11.6, docs/design/service.md §1.2): a learning stream
knows when it is back, never by its own trail, and every revisit is logged durably."""

from __future__ import annotations

import csv
import io
import json

import cv2
import numpy as np

from tests.service.helpers import frame, make_client, post

LAP = list(range(30))
THRESHOLD = 0.5  # the synthetic maps are small: confidence earns less per frame than on a real route


def drive(c, places, stream="mapper", learn="true", noise=3.0, **params) -> list[dict]:
    return [post(c, frame(p, noise=noise), stream=stream, learn=learn, top_k=0, **params).json()
            for p in places]


def revisits(bodies: list[dict]) -> list[dict]:
    return [b for b in bodies if b["place"] is not None and b["place"]["revisit"]]


def patched(c) -> None:
    assert c.patch("/v1/maps/default", json={"revisit_threshold": THRESHOLD}).status_code == 200


def test_standing_still_is_not_a_revisit(tmp_path):
    # 40 near-identical frames of a stopped robot: each is the best match of the next, and none is a
    # revisit however many pass (the old rule hid the last 10 rows only: the 11th back was "a revisit").
    with make_client(tmp_path / "data") as c:
        patched(c)
        before = drive(c, LAP[:20])
        stop = drive(c, [20] * 40)
        after = drive(c, range(21, 40))
    stop_seqs = {b["seq"] for b in stop}
    assert revisits(before + stop + after) == []
    assert all(b["place"] is None or b["place"]["seq"] not in stop_seqs for b in stop)


def test_a_lap_on_ones_own_trail_is_a_revisit_and_names_the_first_lap(tmp_path):
    with make_client(tmp_path / "data") as c:
        patched(c)
        lap1 = drive(c, LAP, noise=0.0)
        lap2 = drive(c, LAP)
    assert revisits(lap1) == []  # continuing along one's own trail is not a revisit
    first = {p: b["seq"] for p, b in zip(LAP, lap1, strict=True)}
    called = revisits(lap2)
    assert len(called) >= len(LAP) - 10
    for b in lap2:
        assert b["place"] is None or b["place"]["seq"] != b["seq"]  # never the row the frame created
    for place, b in zip(LAP, lap2, strict=True):  # the place is lap 1's (science.md §11.8)
        if b in called:
            assert b["place"]["place_id"] == first[place]


def test_an_excursion_of_any_length_then_back_is_a_revisit(tmp_path):
    with make_client(tmp_path / "data") as c:
        patched(c)
        start = drive(c, LAP[:20], noise=0.0)
        drive(c, range(100, 112))  # a short excursion through places never seen
        back = drive(c, LAP[:20])
    seqs = {b["seq"] for b in start}
    called = revisits(back)
    assert len(called) >= 8 and all(b["place"]["seq"] in seqs for b in called)


def test_two_robots_on_one_map_recognise_each_others_rows_at_once(tmp_path):
    # Rows of other streams are always candidates: robot b, learning, is back on a's trail from its start.
    with make_client(tmp_path / "data") as c:
        patched(c)
        a = drive(c, LAP, stream="a", noise=0.0)
        b = drive(c, LAP, stream="b")
    a_seqs = {x["seq"] for x in a}
    called = revisits(b)
    assert revisits(a) == [] and len(called) >= len(LAP) - 10
    assert all(x["place"]["seq"] in a_seqs and x["place"]["stream"] == "a" for x in called)


def test_a_restart_between_laps_keeps_the_stream_and_its_trail(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        patched(c)
        lap1 = drive(c, LAP, noise=0.0)
    with make_client(data) as c:
        lap2 = drive(c, LAP)
        stop = drive(c, [LAP[-1]] * 40)  # after the restart, standing still is still not a revisit
    assert len(revisits(lap2)) >= len(LAP) - 10
    assert {b["place"]["seq"] for b in revisits(lap2)} <= {b["seq"] for b in lap1}
    stop_seqs = {b["seq"] for b in stop}
    assert all(b["place"]["seq"] not in stop_seqs for b in revisits(stop))


def test_the_loop_closure_log_pages_exports_and_survives_a_restart(tmp_path):
    data = tmp_path / "data"
    # lap 1 posed 2 m a frame (a pose that never changes is a robot that never moved: one row, §11.6)
    metas = [{"stamp": 1700000000.5 + p, "pose": {"x": 1.0 + 2.0 * p, "y": 2.0, "yaw": 0.1}} for p in LAP]
    with make_client(data) as c:
        patched(c)
        lap1 = [post(c, frame(p), stream="mapper", learn="true", top_k=0, metadata=json.dumps(m)).json()
                for p, m in zip(LAP, metas, strict=True)]
        lap2 = drive(c, LAP, metadata=json.dumps({"stamp": "1700000100.25"}))
        localised = drive(c, LAP, stream="robot", learn="false")
        page = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()
    learned, loc = revisits(lap2), revisits(localised)
    assert learned and loc
    log = page["loop_closures"]
    assert page["next_after"] is None
    # Every revisit told, in order: a learning stream's with its row, a localising stream's without.
    assert [(e["stream"], e["seq"], e["place"]["seq"]) for e in log] == (
        [("mapper", b["seq"], b["place"]["seq"]) for b in learned]
        + [("robot", None, b["place"]["seq"]) for b in loc])
    first = log[0]
    assert first["confidence"] >= THRESHOLD and first["support"] >= 1
    meta = next(m for m, b in zip(metas, lap1, strict=True) if b["seq"] == first["place"]["seq"])
    assert first["place"]["metadata"] == meta and first["metadata"] == {"stamp": "1700000100.25"}
    assert first["observation_id"] == learned[0]["observation_id"]
    assert first["place"]["observation_id"] == next(b["observation_id"] for b in lap1
                                                    if b["seq"] == first["place"]["seq"])
    with make_client(data) as c:
        again = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()["loop_closures"]
        two = c.get("/v1/maps/default/loop-closures", params={"limit": 2}).json()
        rest = c.get("/v1/maps/default/loop-closures",
                     params={"after": two["next_after"], "limit": 500}).json()
        text = c.get("/v1/maps/default/loop-closures/export", params={"format": "csv"})
        lines = c.get("/v1/maps/default/loop-closures/export", params={"format": "jsonl"})
        assert c.get("/v1/maps/default/loop-closures", params={"limit": 0}).status_code == 400
        assert c.get("/v1/maps/nope/loop-closures").status_code == 404
    assert again == log  # durable across a restart
    assert two["loop_closures"] + rest["loop_closures"] == log and len(two["loop_closures"]) == 2
    assert text.headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(text.text)))
    records = [json.loads(line) for line in lines.text.splitlines()]
    assert len(rows) == len(records) == len(log)
    assert records[0]["stamp"] == 1700000100.25 and records[0]["place_stamp"] == meta["stamp"]
    assert (records[0]["place_x"], records[0]["place_y"], records[0]["place_yaw"]) == (
        meta["pose"]["x"], 2.0, 0.1)
    assert records[0]["x"] is None and rows[0]["x"] == ""
    assert float(rows[0]["stamp"]) == 1700000100.25 and rows[0]["place_observation_id"] == \
        log[0]["place"]["observation_id"]
    assert records[-1]["seq"] is None and records[-1]["stream"] == "robot"


def test_the_log_is_carried_by_a_snapshot_and_a_restore_and_is_bounded(tmp_path):
    with make_client(tmp_path / "data", loop_closures=5) as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        drive(c, LAP[:15])
        kept = c.get("/v1/maps/default/loop-closures").json()["loop_closures"]
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        drive(c, LAP[15:])
        later = c.get("/v1/maps/default/loop-closures").json()["loop_closures"]
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        restored = c.get("/v1/maps/default/loop-closures").json()["loop_closures"]
    assert len(kept) == 5 and len(later) == 5  # the last 5 (the setting), oldest pruned
    assert later[0]["id"] > kept[-1]["id"]
    assert restored == kept  # the restore's file holds the log as it was at the snapshot


def test_a_page_names_the_oldest_id_kept_so_a_follower_behind_the_prune_knows_it_missed_entries(tmp_path):
    with make_client(tmp_path / "data", loop_closures=5) as c:
        empty = c.get("/v1/maps/default/loop-closures")
        patched(c)
        drive(c, LAP, noise=0.0)
        drive(c, LAP[:15])
        first = c.get("/v1/maps/default/loop-closures", params={"limit": 1}).json()
        read = first["loop_closures"][0]["id"]  # a follower reads one entry, then falls behind
        drive(c, LAP[15:])
        page = c.get("/v1/maps/default/loop-closures", params={"after": read}).json()
        ids = [e["id"] for e in page["loop_closures"]]
    assert empty.status_code == 200 and empty.json()["oldest"] is None, empty.text
    assert first["oldest"] == read
    assert len(ids) == 5 and page["oldest"] == ids[0]  # the last 5 kept: the rest pruned unread
    assert read < page["oldest"] - 1  # the follower's rule says so (docs/design/service.md §1.2)
    assert page["next_after"] is None  # nothing more for now: it polls again with after=ids[-1]


def test_a_restore_over_a_longer_log_keeps_the_restored_entries_within_the_cap(tmp_path):
    # The restore rolls back more ids than the log keeps: the next closures continue above them, and the
    # cap counts entries, so the restored ones stay (by id arithmetic, the first new one pruned them all).
    with make_client(tmp_path / "data", loop_closures=5) as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        drive(c, LAP[:15])
        kept = [e["id"] for e in c.get("/v1/maps/default/loop-closures").json()["loop_closures"]]
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        drive(c, LAP[15:])  # more closures than the 5 kept: their ids are rolled back below
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        new = revisits(drive(c, LAP[15:17]))
        log = [e["id"] for e in c.get("/v1/maps/default/loop-closures").json()["loop_closures"]]
    assert len(kept) == 5 and 1 <= len(new) <= 2
    assert log[:5 - len(new)] == kept[len(new):]  # the restored entries, less as many as came after
    assert len(log) == 5 and min(log[5 - len(new):]) > max(kept) + 5  # the new ones, above the rolled back


def test_after_a_restore_log_ids_are_not_handed_out_again_and_the_epoch_says_so(tmp_path):
    # A back end following the log with a cursor: the ids after the restore continue above every id it
    # was given (it misses none of the new ones), and the epoch tells it to read again from 0 (what came
    # after the snapshot is gone). A restart keeps both.
    data = tmp_path / "data"
    with make_client(data) as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        drive(c, LAP[:15])
        page = c.get("/v1/maps/default/loop-closures").json()
        epoch = page["epoch"]
        assert epoch and c.get("/v1/maps/default/observations").json()["epoch"] == epoch
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        drive(c, LAP[15:])
        log = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()["loop_closures"]
        cursor = log[-1]["id"]
        assert cursor > page["loop_closures"][-1]["id"]
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        restored = c.get("/v1/maps/default/loop-closures").json()["epoch"]
        assert restored != epoch and c.get("/v1/maps/default/observations").json()["epoch"] == restored
        called = revisits(drive(c, LAP[15:]))
        assert called
        new = c.get("/v1/maps/default/loop-closures", params={"after": cursor}).json()
    assert len(new["loop_closures"]) == len(called) and new["epoch"] == restored
    assert min(e["id"] for e in new["loop_closures"]) == cursor + 1
    with make_client(data) as c:  # the marks and the count are the catalog's: a restart keeps them
        again = c.get("/v1/maps/default/loop-closures", params={"after": cursor}).json()
        assert again == new
        # a map deleted and made again under the same id is another map: its ids start again, its
        # epoch differs from every one before
        assert c.delete("/v1/maps/default").status_code == 204
        assert c.post("/v1/maps", json={"map_id": "default"}).status_code == 201
        assert c.get("/v1/maps/default/loop-closures").json()["epoch"] not in (epoch, restored)


def test_a_moved_map_keeps_its_epoch_and_no_copy_hands_out_an_id_again(tmp_path):
    # The marks of a restore travel with a snapshot (its manifest's lineage). A move between shards
    # (`MapRegistry.import_live`) is the same map: its epoch stays, so a back end's cursor stays good; a
    # map imported with `cortexloc import` is another map (another epoch). Neither hands out a seq or a
    # log id the map handed out before the snapshot, even one a restore had rolled back (before, both
    # started again above the file's own: the rolled-back ids came back).
    from typer.testing import CliRunner

    from service.cli import app as cli_app

    with make_client(tmp_path / "a") as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        drive(c, LAP[:15])
        snap = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        later = drive(c, [*LAP[15:], *range(100, 105)])  # closures and new rows the restore rolls back
        log = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()["loop_closures"]
        cursor, last_seq = log[-1]["id"], max(b["seq"] or 0 for b in later)
        assert last_seq > 0
        assert c.post(f"/v1/maps/default/snapshots/{snap}/restore").status_code == 200
        epoch = c.get("/v1/maps/default/loop-closures").json()["epoch"]
        tar_id = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        tar = tmp_path / "default.tar"
        tar.write_bytes(c.get(f"/v1/maps/default/snapshots/{tar_id}/download").content)

    def continues(c) -> tuple[str, list[int], list[int]]:
        """The map's epoch after it learns on, the log ids and the seqs that learning handed out."""
        def ids() -> set[int]:
            page = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()
            return {e["id"] for e in page["loop_closures"]}
        held = ids()
        bodies = drive(c, [*LAP[15:], *range(200, 205)])  # a stretch it knows, then new places
        return (c.get("/v1/maps/default/loop-closures").json()["epoch"], sorted(ids() - held),
                [b["seq"] for b in bodies if b["seq"] is not None])

    with make_client(tmp_path / "b") as c:  # the receiving shard of a move
        assert c.delete("/v1/maps/default").status_code == 204
        c.app.state.registry.import_live(tar, 1 << 30)
        assert c.get("/v1/maps/default/loop-closures").json()["epoch"] == epoch
        moved_epoch, moved_log, moved_seqs = continues(c)
    assert moved_epoch == epoch
    assert moved_log and moved_log[0] == cursor + 1 and moved_seqs and min(moved_seqs) == last_seq + 1

    assert CliRunner().invoke(cli_app, ["import", str(tar), "--data-dir", str(tmp_path / "c")]).exit_code == 0
    with make_client(tmp_path / "c") as c:  # a copy: another map
        patched(c)
        copy_epoch, copy_log, copy_seqs = continues(c)
    assert copy_epoch not in (epoch, moved_epoch)
    assert copy_log and copy_log[0] == cursor + 1 and copy_seqs and min(copy_seqs) == last_seq + 1


def test_a_repeated_localisation_post_logs_its_closure_once(tmp_path):
    data = tmp_path / "data"
    with make_client(data) as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        bodies = drive(c, LAP[:12], stream="robot", learn="false")
        assert bodies[-1]["place"]["revisit"]
        body = frame(LAP[12], noise=3.0)
        headers = {"Content-Type": "image/png", "Idempotency-Key": "closure-key-0001"}
        for _ in range(2):
            c.post("/v1/maps/default/observations", content=body, headers=headers,
                   params={"stream": "robot", "learn": "false"})
        n = len(c.get("/v1/maps/default/loop-closures").json()["loop_closures"])
    with make_client(data) as c:  # after a restart the key's reply is gone, its closure is not logged twice
        c.post("/v1/maps/default/observations", content=body, headers=headers,
               params={"stream": "robot", "learn": "false"})
        assert len(c.get("/v1/maps/default/loop-closures").json()["loop_closures"]) == n


def test_each_revisits_reply_names_its_log_entry_so_a_retraction_can_be_matched_to_its_edge(tmp_path):
    # A back end that builds its graph from the replies (the ROS 2 node's topic) must be able to drop the
    # edge a later retraction names by id: every revisit's reply carries its entry's id, whichever way it
    # was logged (a learned row's commit, a consolidated frame's visit, a localising stream's own entry),
    # and a keyed localisation's retry, even after a restart, names its first post's entry.
    data = tmp_path / "data"
    with make_client(data) as c:
        patched(c)
        lap1 = drive(c, LAP, noise=0.0)
        lap2 = drive(c, LAP)
        localised = drive(c, LAP[:12], stream="robot", learn="false")
        body = frame(LAP[12], noise=3.0)
        headers = {"Content-Type": "image/png", "Idempotency-Key": "closure-id-key-01"}
        keyed = [c.post("/v1/maps/default/observations", content=body, headers=headers,
                        params={"stream": "robot", "learn": "false"}).json() for _ in range(2)]
        log = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()
        # a map that consolidates nothing: each revisit's closure commits with its own row
        assert c.post("/v1/maps", json={"map_id": "rows", "revisit_threshold": THRESHOLD,
                                        "localiser": {"consolidate": 1.0}}).status_code == 201
        row_laps = [post(c, frame(p, noise=n), map_id="rows", stream="mapper", learn="true", top_k=0).json()
                    for n in (0.0, 3.0) for p in LAP]
        row_log = c.get("/v1/maps/rows/loop-closures", params={"limit": 500}).json()["loop_closures"]
    with make_client(data) as c:  # the key's cached reply is gone: the store names the entry
        again = c.post("/v1/maps/default/observations", content=body, headers=headers,
                       params={"stream": "robot", "learn": "false"}).json()
    told = [*revisits(lap1 + lap2 + localised), keyed[0]]
    assert keyed[0]["place"]["revisit"]
    assert all(b["seq"] is None for b in revisits(lap2))  # consolidated (visits, no rows of their own)
    with_rows = revisits(row_laps)
    assert len(with_rows) >= 8 and all(b["seq"] is not None for b in with_rows)
    assert [b["loop_closure_id"] for b in with_rows] == [e["id"] for e in row_log]
    assert [b["loop_closure_id"] for b in told] == [e["id"] for e in log["loop_closures"]]
    assert len({b["loop_closure_id"] for b in told}) == len(told) >= 10
    assert all(b["loop_closure_id"] is None for b in lap1 + lap2 + localised if b not in told)
    assert keyed[1]["loop_closure_id"] == again["loop_closure_id"] == keyed[0]["loop_closure_id"]
    assert log["newest"] == log["loop_closures"][-1]["id"]


def test_a_key_a_localising_pass_used_or_one_past_the_kept_keys_gives_a_learned_closure_its_own_id(tmp_path):
    # A review found the reply naming an id the store never gave its closure: a learned closure was logged
    # with its post's key, and a key already in the log (a localising pass of the same bag under one run
    # id, or a retry past the last `idempotency_keys`) dropped the entry, so the reply named the id the
    # next frame's closure then got. Each learned revisit must name an entry of its own row.
    def keyed(c, place: int, learn: str, noise: float) -> dict:
        return c.post("/v1/maps/rows/observations", content=frame(place, noise=noise),
                      headers={"Content-Type": "image/png", "Idempotency-Key": f"bag-run-1-{place:04d}"},
                      params={"stream": "robot", "learn": learn, "top_k": 0}).json()

    data = tmp_path / "data"
    with make_client(data, idempotency_keys=1) as c:
        assert c.post("/v1/maps", json={"map_id": "rows", "revisit_threshold": THRESHOLD,
                                        "localiser": {"consolidate": 1.0}}).status_code == 201
        for p in LAP:  # the first lap, unkeyed
            post(c, frame(p), map_id="rows", stream="mapper", learn="true", top_k=0)
        localised = [keyed(c, p, "false", 3.0) for p in LAP]  # a localising pass of the bag
    # (while the service holds a localisation's reply, its key on a learning post is refused as reused)
    with make_client(data, idempotency_keys=1) as c:
        learned = [keyed(c, p, "true", 3.0) for p in LAP]  # the same bag mapped, the same keys
        first = next(p for p, b in zip(LAP, learned, strict=True) if b in revisits(learned))
        again = keyed(c, first, "true", 3.0)  # a retry past the one kept key: learned anew
        log = c.get("/v1/maps/rows/loop-closures", params={"limit": 500}).json()["loop_closures"]
    by_id = {e["id"]: e for e in log}
    told = [b for b in [*revisits(learned), again] if b["place"]["revisit"]]
    assert revisits(localised) and len(told) >= 10 and all(b["seq"] is not None for b in told)
    for b in told:
        e = by_id[b["loop_closure_id"]]
        assert (e["stream"], e["seq"], e["place"]["seq"]) == ("robot", b["seq"], b["place"]["seq"])
    assert len({b["loop_closure_id"] for b in told}) == len(told) and again["seq"] > learned[-1]["seq"]


def dark(k: int) -> bytes:
    """A near-black tunnel frame: a flat level, sensor noise and a small bright speck (a lamp, the
    camera's timestamp overlay): no place can be told from it (docs/design/science.md §11.7)."""
    rng = np.random.default_rng(500 + k)
    img = np.clip(6.0 + rng.normal(0, 1.5, (96, 128, 3)), 0, 255)
    img[4:8, 110:124] = 230
    img[46:50, 62:66] = 200
    ok, buf = cv2.imencode(".png", img.astype(np.uint8))
    assert ok
    return buf.tobytes()


def test_frames_with_no_information_are_never_revisits(tmp_path):
    # Two tunnels on one lap: the second one's dark frames are the first's best match by far, yet they
    # say nothing about where the robot is, so no answer in or after them is a revisit, and none is
    # logged; the dark frames say why.
    with make_client(tmp_path / "data") as c:
        patched(c)
        bodies = drive(c, LAP[:10])
        bodies += [post(c, dark(k), stream="mapper", learn="true", top_k=0).json() for k in range(6)]
        bodies += drive(c, range(40, 52))
        tunnel2 = [post(c, dark(10 + k), stream="mapper", learn="true", top_k=0).json() for k in range(6)]
        after = drive(c, range(60, 66))
        log = c.get("/v1/maps/default/loop-closures").json()
    assert revisits(bodies + tunnel2 + after) == []
    assert log["loop_closures"] == []
    assert all(b["place"]["low_information"] for b in tunnel2)
    assert not any(b["place"]["low_information"] for b in after)


def test_the_answer_the_log_and_the_exports_carry_the_span(tmp_path):
    # docs/design/science.md §11.11: `place.span` (how many places the stream may be at) and
    # `place.span_seqs` (their best rows, the answer's first) in the reply; each logged closure keeps the
    # span it was told, and the CSV and JSON lines exports carry it (a back end weighs the edge by it).
    with make_client(tmp_path / "data") as c:
        patched(c)
        drive(c, LAP, noise=0.0)
        lap2 = drive(c, LAP)
        log = c.get("/v1/maps/default/loop-closures", params={"limit": 500}).json()["loop_closures"]
        text = c.get("/v1/maps/default/loop-closures/export", params={"format": "csv"}).text
        lines = c.get("/v1/maps/default/loop-closures/export", params={"format": "jsonl"}).text
        spec = c.get("/openapi.json").json()
    answered = [b["place"] for b in lap2 if b["place"] is not None]
    assert answered and all(p["span"] >= 1 and p["span_seqs"][0] == p["seq"]
                            and len(p["span_seqs"]) == min(p["span"], 16) for p in answered)
    called = revisits(lap2)
    assert called and all(b["place"]["span"] <= 3 for b in called)  # the map's span_max, the default
    assert [(e["span"], e["span_seqs"]) for e in log] == [(b["place"]["span"], b["place"]["span_seqs"])
                                                          for b in called]
    rows = list(csv.DictReader(io.StringIO(text)))
    records = [json.loads(line) for line in lines.splitlines()]
    assert [(int(r["span"]), [int(q) for q in r["span_seqs"].split()]) for r in rows] == [
        (r["span"], r["span_seqs"]) for r in records] == [(e["span"], e["span_seqs"]) for e in log]
    schemas = spec["components"]["schemas"]
    assert {"span", "span_seqs"} <= set(schemas["PlaceResult"]["properties"]) & set(
        schemas["LoopClosureModel"]["properties"])
