"""The Ray Serve scale-out on a real local Ray cluster (issue 26, items 1-4; issue 34, item 5): `cortexloc
serve --ray` with 1 encoder replica and 2 shards; 4 maps, 2 streams each, posted through the typed
client; a shard's replica, then the encoder's, then the ingress's killed with SIGKILL mid-stream. Ray
restarts each (a shard from its data directory); meanwhile clients get 503 + Retry-After (problem+json),
or the proxy's plain 500 for a request the dead ingress held; their retries with the same
Idempotency-Key are replayed, not learned twice; then acknowledged == stored on every map, no post was
lost or answered 500, a map moves between shards with one command (the same map there: its epoch
kept), and `cortexloc verify` finds every
shard's maps clean.

Kept light for 2 shared cores: tiny maps (128 columns, k = 64), 64x48 frames, the torch runtime (no
ONNX export per replica), a cluster of 4 logical CPUs, an 80 MB object store and no dashboard.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from collections import Counter

import cv2
import httpx
import numpy as np
import pytest

pytest.importorskip("ray", reason="the `ray` extra is not installed (pip install '.[ray]'; `make test` "
                                  "installs it)")

from cortexloc_client import Client, CortexlocError, RetryPolicy
from tests.e2e.scaleout_cluster import RayCluster

# one pytest-xdist worker runs the whole file (`make test`): its module's cluster starts once
pytestmark = pytest.mark.xdist_group("ray-cluster")

KEY = "scaleout-test-key"
MAPS = ("m0", "m1", "m2", "m3")
STREAMS = ("left", "right")
FRAMES = 10  # per stream
TINY = {"tm": {"columnDimensions": 128, "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16,
               "maxNewSynapseCount": 8, "activationThreshold": 4, "minThreshold": 2}, "slsbh": {"k": 64}}


def tiny_frame(place: int) -> bytes:
    rng = np.random.default_rng(place)
    img = cv2.resize(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8), (64, 48), interpolation=cv2.INTER_CUBIC)
    return cv2.imencode(".jpg", img)[1].tobytes()


class Recording(httpx.HTTPTransport):
    """Every reply's status, content type and Retry-After (the client retries on its own)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[tuple[int, str, str | None]] = []
        self.lock = threading.Lock()

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        r = super().handle_request(request)
        with self.lock:
            self.seen.append((r.status_code, r.headers.get("content-type", ""), r.headers.get("retry-after")))
        return r


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, request):
    work = tmp_path_factory.mktemp("scaleout")
    c = RayCluster(work, {"CORTEXLOC_WEIGHTS_DIR": str(work / "no-weights"), "CORTEXLOC_RUNTIME": "torch",
                          "CORTEXLOC_API_KEY": KEY, "CORTEXLOC_LOG_FORMAT": "text"})
    request.addfinalizer(c.stop)  # torn down whatever happens below
    c.start()
    try:
        c.serve(shards=2, encoder_replicas=1)
    except RuntimeError as e:
        pytest.fail(str(e))
    return c


def _kill_mid_stream(c: RayCluster, client: Client, seen: Recording, acked: dict, tag: str,
                     victim: str) -> dict:
    """8 robots (4 maps x 2 streams) post FRAMES keyed frames each; the victim deployment's replica is
    SIGKILLed after the round's 12th acknowledgement. A post the client gave up on is counted, and the
    robot goes on with its next frame (the figures of a run before the fix).

    Returns:
        The round's figures: posts, acknowledged, failed (and how many of those were a 500), the replies
        the transport saw (503, the app's problem+json 500, the proxy's plain 500), the errors by key, and
        per map the posts begun after the kill that were acknowledged (the old replica was dead by then,
        so a restarted one answered them).
    """
    pid = c.pids(victim)[victim]
    first = len(seen.seen)
    failed: dict[str, CortexlocError | httpx.HTTPError] = {}
    done: list[str] = []  # keys answered or given up on (list.append is atomic across threads)
    killed = threading.Event()
    after_kill: list[str] = []  # maps of the posts begun after the kill and acknowledged

    def robot(map_id: str, stream: str) -> None:
        for i in range(FRAMES):
            key = f"{map_id}-{stream}-{i:04d}"
            begun_after = killed.is_set()
            try:
                obs = client.observe(map_id, tiny_frame(i), stream=stream, top_k=1, idempotency_key=key)
            except (CortexlocError, httpx.HTTPError) as e:
                failed[key] = e
                continue
            finally:
                done.append(key)
            acked[map_id][key] = (obs.seq, obs.observation_id, obs.consolidated_into)
            if begun_after:
                after_kill.append(map_id)

    robots = [threading.Thread(target=robot, args=(m, f"{tag}-{s}")) for m in MAPS for s in STREAMS]
    for t in robots:
        t.start()
    deadline = time.monotonic() + 300
    while len(done) < 12 and time.monotonic() < deadline:
        time.sleep(0.05)
    os.kill(pid, signal.SIGKILL)  # no shutdown hook, no flush
    killed.set()
    killed_at = len(done)
    for t in robots:
        t.join(timeout=600)
    assert killed_at < len(MAPS) * len(STREAMS) * FRAMES, f"{tag}: the kill came after the streams ended"
    assert c.pids(victim)[victim] != pid  # Ray replaced the replica (a new process)
    replies = seen.seen[first:]
    problem = "application/problem+json"
    return {"victim": victim, "posts": len(MAPS) * len(STREAMS) * FRAMES, "killed_after": killed_at,
            "acknowledged": len(MAPS) * len(STREAMS) * FRAMES - len(failed), "failed": len(failed),
            "failed_500": sum(getattr(e, "status", None) == 500 for e in failed.values()),
            "seen_503": sum(s == 503 for s, _, _ in replies),
            "seen_app_500": sum(s == 500 and ct == problem for s, ct, _ in replies),
            "seen_proxy_500": sum(s == 500 and ct != problem for s, ct, _ in replies),
            "unavailable_503": [(ct, ra) for s, ct, ra in replies if s == 503],
            "acked_after_kill": dict(Counter(after_kill)),
            "errors": {k: f"{type(e).__name__}: {e}"[:200] for k, e in failed.items()}}


def test_a_replica_of_each_kind_killed_mid_stream_costs_no_frame(cluster):
    """Issue 34, item 5: a shard's, the encoder's and the ingress's replica, each SIGKILLed while 8 robots
    post; every post is acknowledged (the client retries 503s, and the proxy's plain 500 of a keyed post)
    and stored exactly once, and no 500 reaches a robot."""
    c = cluster
    seen = Recording()
    client = Client(c.base, api_key=KEY, retry=RetryPolicy(attempts=200, max_wait_s=3, backoff_s=0.5),
                    timeout=120, transport=seen)
    for m in MAPS:
        assert client.create_map(m, tm=TINY["tm"], slsbh=TINY["slsbh"]).map_id == m
    owners = c.routes()
    assert {owners[m][0] for m in MAPS} == {"shard-0", "shard-1"}  # both shards own test maps
    victim = owners["m0"][0]
    victim_maps = [m for m in MAPS if owners[m][0] == victim]

    acked: dict[str, dict[str, tuple[int, str, int | None]]] = {m: {} for m in MAPS}  # key -> (seq, id, into)
    rounds = {tag: _kill_mid_stream(c, client, seen, acked, tag, deployment)
              for tag, deployment in (("shard", victim), ("encoder", "Encoder"), ("ingress", "Ingress"))}
    print("kill rounds:", json.dumps({t: {k: v for k, v in r.items() if k != "unavailable_503"}
                                      for t, r in rounds.items()}))

    unacknowledged = 0  # rows and visits stored that no robot was told of
    for m in MAPS:
        # Every frame acknowledged once: as a row with its own seq, or (the two streams drive the same
        # frames) as a visit consolidated into a stored row; stored == acknowledged: nothing lost and
        # nothing learned twice (a retry of a committed post was replayed).
        rows = {seq: oid for seq, oid, into in acked[m].values() if into is None}
        visits = [into for seq, oid, into in acked[m].values() if into is not None]
        assert len(rows) + len(visits) == len(acked[m]) and None not in rows, m
        info = client.get_map(m)
        assert info.state == "ready" and info.places is not None, m
        listed = client.list_observations(m, limit=500).observations
        stored = {o.seq: o.observation_id for o in listed if o.joined_to is None}
        # a warm-up row a stream's confident path later explained was joined to that place: turned into a
        # visit of it and its row deleted (map.sqlite schema 12), dropped as `joined`, listed with
        # `joined_to`
        joined = {o.seq for o in listed if o.joined_to is not None}
        assert joined <= set(rows), m
        assert len(joined) <= info.places.dropped, m
        unacknowledged += len(set(stored) - set(rows)) + info.places.visits_logged - len(visits) - len(joined)
        assert all(stored[s] == rows[s] for s in rows if s in stored) and set(visits) <= set(stored), m
    figures = {t: {k: r[k] for k in ("failed", "failed_500", "seen_app_500", "seen_proxy_500")}
               for t, r in rounds.items()}
    print("stored, not acknowledged:", unacknowledged)
    # No post lost, none answered 500 (the app's own 500s are 503 now; the proxy's were retried), and
    # nothing stored that no robot was told of.
    lost = [t for t, r in rounds.items() if r["failed"] or r["seen_app_500"]]
    assert not lost and unacknowledged == 0, (figures, unacknowledged)
    assert sum(len(v) for v in acked.values()) == sum(r["posts"] for r in rounds.values())
    # The shard died mid-stream of its own maps: posts to them begun after the SIGKILL were acknowledged,
    # so its restarted replica served them. What a robot saw meanwhile depends on where its posts were
    # when the replica died: one the ingress had forwarded is answered 503 map-unavailable, a later one
    # may wait in Ray's router for the new replica and be answered 200 (CI saw a round with neither 503
    # nor 500), so no reply is required; any 503 is problem+json with Retry-After.
    after = rounds["shard"]["acked_after_kill"]
    assert all(after.get(m, 0) > 0 for m in victim_maps), (victim_maps, after)
    unavailable = rounds["shard"]["unavailable_503"]
    assert all(ct == "application/problem+json" and ra is not None for ct, ra in unavailable)

    # A retry now is replayed, on a restarted shard's map too.
    key = f"{victim_maps[0]}-shard-left-0000"  # frame 0 of stream `shard-left`, posted as the client did
    seq, _, into = acked[victim_maps[0]][key]
    r = httpx.post(f"{c.base}/v1/maps/{victim_maps[0]}/observations", content=tiny_frame(0),
                   params={"learn": "true", "stream": "shard-left", "top_k": 1}, timeout=60,
                   headers={"X-API-Key": KEY, "Idempotency-Key": key, "Content-Type": "image/jpeg"})
    assert r.status_code == 200 and r.headers["Idempotent-Replayed"] == "true" and r.json()["seq"] == seq
    assert r.json().get("consolidated_into") == into

    # The cluster's views: every map listed once, metrics and readiness of both shards.
    assert sorted(m.map_id for m in client.list_maps()) == ["default", *MAPS]
    metrics = httpx.get(f"{c.base}/metrics", headers={"X-API-Key": KEY}).text
    assert 'shard="shard-0"' in metrics and 'shard="shard-1"' in metrics
    assert set(httpx.get(f"{c.base}/readyz").json()["checks"]) == {"shard-0", "shard-1"}
    assert httpx.post(f"{c.base}/v1/maps/m1/observations", content=tiny_frame(1),
                      headers={"Content-Type": "image/jpeg"}).status_code == 401  # the key, at the ingress

    # `cortexloc ingest` and the viewer, unchanged, against the ingress.
    frames = c.work / "frames"
    frames.mkdir()
    for i in range(3):
        (frames / f"{i:03d}.jpg").write_bytes(tiny_frame(50 + i))
    out = c.cli("ingest", str(frames), "--map", "m3", "--stream", "ingest", "--url", c.base, "--api-key", KEY)
    assert out.returncode == 0, out.stderr[-2000:]
    held = {m: sum(1 for *_, into in acked[m].values() if into is None) for m in MAPS}  # rows made
    assert client.get_map("m3").observations <= held["m3"] + 3
    page = httpx.get(f"{c.base}/ui/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")

    # Moving a map with one command: the same rows on the other shard, the table switched.
    target = "shard-1" if victim == "shard-0" else "shard-0"
    # rows held: the rows made less those the warm-up joins dropped (docs/design/science.md §11.8)
    held_before = client.get_map("m0").observations
    assert held_before <= held["m0"]
    log = f"{c.base}/v1/maps/m0/loop-closures"
    epoch = httpx.get(log, headers={"X-API-Key": KEY}).json()["epoch"]
    out = c.cli("shards", "move", "m0", "--to", target, "--address", c.address)
    assert out.returncode == 0, out.stderr[-2000:]
    moved = json.loads(out.stdout.strip().splitlines()[-1])
    assert moved["from"] == victim and moved["to"] == target and moved["observations"] == held_before
    assert c.routes()["m0"] == (target, "serving")
    assert client.get_map("m0").observations == held_before
    assert httpx.get(log, headers={"X-API-Key": KEY}).json()["epoch"] == epoch  # the same map: same epoch
    after = client.observe("m0", tiny_frame(99), stream="left")  # learning goes on where it stopped
    if after.consolidated_into is None:
        assert after.seq == held["m0"] + 1
    else:
        assert after.consolidated_into <= held["m0"]
    client.close()

    # Offline, after the cluster is gone: every shard's maps replay to their stored winner cells.
    c.stop()
    for shard in ("shard-0", "shard-1"):
        done = c.cli("verify", "--data-dir", str(c.data_dir / shard))
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
        assert "0 with problems" in done.stdout
