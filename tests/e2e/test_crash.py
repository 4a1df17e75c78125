"""kill -9 while a robot is mapping: nothing acknowledged is lost, the database is intact, and the
restarted memory is the one that ran (docs/design/service.md §4.3, §10.4)."""

from __future__ import annotations

import threading
import time

from storage.mapstore import MapStore


def test_kill_9_loses_nothing_acknowledged(server_proc, http, make_frame):
    # A snapshot every 2 learned frames: some kills land in the middle of one.
    server_proc.extra_env = {"CORTEXLOC_SNAPSHOT_EVERY": "2"}
    base = server_proc.start()
    acked: list[tuple[int, str]] = []
    stop = threading.Event()

    def robot() -> None:
        place = 0
        while not stop.is_set():
            try:
                status, body = http(f"{base}/v1/maps/default/observations?learn=true&top_k=1",
                                    make_frame(place % 7))
            except OSError:
                return  # the server died under us: this frame was never acknowledged
            if status == 200:
                acked.append((body["seq"], body["observation_id"]))
            place += 1

    for round_ in range(2):
        # Kill once this round has some acknowledgements (a later point in the second round), not after
        # a fixed sleep: a slow machine would otherwise kill before the first one.
        want = len(acked) + 3 + 2 * round_
        t = threading.Thread(target=robot)
        t.start()
        deadline = time.monotonic() + 120
        while len(acked) < want and t.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        server_proc.kill9()
        stop.set()
        t.join(timeout=30)
        stop.clear()
        assert len(acked) >= want, f"the robot got {len(acked)} acknowledgements before the kill, not {want}"
        with MapStore.open(server_proc.data_dir / "maps" / "default" / "map.sqlite") as store:
            assert store.integrity_check()
            stored = {row.seq: row.observation_id for row in store.rows()}
        for seq, obs_id in acked:
            assert stored.get(seq) == obs_id, f"acknowledged seq {seq} lost"
        # Restart: recovery replays every row and must reproduce its winner cells, or the map fails.
        base = server_proc.start()
        status, m = http(f"{base}/v1/maps/default")
        assert status == 200 and m["state"] == "ready" and m["observations"] == len(stored)
        leftovers = [p.name for p in (server_proc.data_dir / "maps" / "default" / "snapshots").iterdir()
                     if p.name.startswith(".")]
        assert not leftovers  # a snapshot cut short by the kill is cleaned up, never loaded


def test_kill_9_after_a_snapshot_on_a_switch_back_to_mapping_recovers(server_proc, http, make_frame):
    """Issue 11, item 1, with CORTEXLOC_SNAPSHOT_EVERY=4 instead of 1000 (the same boundary): learned
    frames on other streams; then on `w` learn, localise, learn x4, the automatic snapshot landing on
    the first of the four; kill -9; restart. The map used to come back failed for good."""
    server_proc.extra_env = {"CORTEXLOC_SNAPSHOT_EVERY": "4"}
    base = server_proc.start()
    obs = f"{base}/v1/maps/default/observations"
    for place, stream in ((0, "a"), (1, "b")):
        assert http(f"{obs}?learn=true&stream={stream}", make_frame(place))[0] == 200
    assert http(f"{obs}?learn=true&stream=w", make_frame(2))[1]["seq"] == 3
    assert http(f"{obs}?learn=false&stream=w", make_frame(3))[0] == 200
    steps = []
    for seq, place in zip((4, 5, 6, 7), (4, 5, 6, 0), strict=True):
        status, body = http(f"{obs}?learn=true&stream=w", make_frame(place))
        assert status == 200 and body["seq"] == seq
        steps.append(body["sequence"]["step"])
    status, snaps = http(f"{base}/v1/maps/default/snapshots")
    assert [s["seq"] for s in snaps["snapshots"]] == [4]
    server_proc.kill9()

    base = server_proc.start()
    status, m = http(f"{base}/v1/maps/default")
    assert status == 200 and m["state"] == "ready", m
    assert m["recovery"]["source"] == "snapshot" and m["recovery"]["snapshot_seq"] == 4
    assert m["recovery"]["skipped_snapshots"] == [] and m["observations"] == 7
    status, body = http(f"{base}/v1/maps/default/observations?learn=true&stream=w", make_frame(1))
    assert status == 200 and body["sequence"]["step"] == steps[-1] + 1
    sid = snaps["snapshots"][0]["snapshot_id"]
    status, restored = http(f"{base}/v1/maps/default/snapshots/{sid}/restore", b"", "application/json")
    assert status == 200 and restored["state"] == "ready", restored
    server_proc.kill9()
    base = server_proc.start()  # and again after a second crash, now after a restore
    status, m = http(f"{base}/v1/maps/default")
    assert status == 200 and m["state"] == "ready" and m["observations"] == 4
    assert http(f"{base}/readyz")[0] == 200


def test_after_kill_9_a_learning_stream_resumes_its_place_like_its_uncrashed_twin(tmp_path,
                                                                                    shared_weights_dir):
    """Issue 34 item 7 with a real kill -9: a known pass, cut by the kill after the last automatic
    snapshot, carries on where it was. Rows made: the same as a twin server that never crashed (1-5
    duplicates before, the stream warming up again)."""
    import json
    import urllib.request

    from tests.e2e.conftest import Server, call
    from tests.service.helpers import frame

    lap, cut = list(range(30)), 17

    def drive(base: str, places, stream: str, noise: float) -> list[dict]:
        out = []
        for p in places:
            status, body = call(f"{base}/v1/maps/default/observations?learn=true&top_k=0&stream={stream}",
                                frame(p, noise=noise), "image/png")
            assert status == 200, body
            out.append(body)
        return out

    def patched(base: str) -> None:
        req = urllib.request.Request(f"{base}/v1/maps/default", data=json.dumps({"revisit_threshold": 0.5})
                                     .encode(), method="PATCH", headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(req, timeout=30) as r:
            assert r.status == 200

    rows = {}
    for name in ("twin", "crashed"):
        s = Server(tmp_path / name, shared_weights_dir)
        (tmp_path / name).mkdir()
        s.extra_env = {"CORTEXLOC_SNAPSHOT_EVERY": "7"}
        try:
            base = s.start()
            patched(base)
            got = drive(base, lap, "a", 0.0) + drive(base, lap[:cut], "b", 3.0)
            if name == "crashed":
                s.kill9()
                base = s.start()
                assert call(f"{base}/v1/maps/default")[1]["recovery"]["resumed_streams"] == 1
            got += drive(base, lap[cut:], "b", 3.0)
        finally:
            s.stop()
        rows[name] = [b["seq"] is not None for b in got]
    assert rows["crashed"] == rows["twin"]  # the same frames made rows: no duplicate
    assert 0 < sum(rows["twin"][len(lap):]) < len(lap)  # the second pass was mostly consolidated
