"""The scale-out's ingress, shard set and shard host in one process (issue 26, items 1-3), Ray left out:
two shards (the single-process app each, on its own data directory) behind the ingress app, with the
encoder deployment's work (`EmbeddingService`) called directly. tests/e2e/test_scaleout.py runs the
same on a real Ray cluster with a shard killed."""

from __future__ import annotations

import asyncio
import inspect
import json
import time
from collections.abc import Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.maps.ids import new_map_id
from service.routes.health import UNNAMED_ERROR
from service.scaleout.embedding import EmbeddingService
from service.scaleout.ingress import create_ingress_app
from service.scaleout.shard import ShardHost
from service.scaleout.shards import MoveFailed, ShardSet
from service.settings import Settings
from storage.shardtable import ShardTable
from tests.service.helpers import frame

TINY = {"tm": {"columnDimensions": 128, "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16,
               "maxNewSynapseCount": 8, "activationThreshold": 4, "minThreshold": 2}, "slsbh": {"k": 64}}


class Cluster:
    """Two `ShardHost`s started on first use in the ingress's event loop; `dead` shards do not answer."""

    def __init__(self, root: Path, **settings) -> None:
        self.root = root
        self.settings = {"backbone": "alexnet", "runtime": "torch", **settings}
        self.encoder = EmbeddingService(Settings(data_dir=root, **self.settings))
        self.hosts: dict[str, ShardHost] = {}
        self.starting: dict[str, asyncio.Task] = {}  # one start per shard, as Ray starts one replica
        self.dead: set[str] = set()
        self.failures: dict[str, BaseException] = {}  # shard -> what a call to it raises (Ray's errors)
        self.embed_failure: BaseException | None = None  # what the encoder deployment's call raises
        self.shards: ShardSet | None = None

    def _embed(self, req):
        f: Future = Future()
        if self.embed_failure is not None:
            f.set_exception(self.embed_failure)
        else:
            f.set_result(self.encoder.embed_batch([req])[0])
        return f

    async def call(self, shard: str, method: str, *args):
        if shard in self.dead:
            raise ConnectionError(f"{shard} is dead")
        if shard in self.failures:
            raise self.failures[shard]
        host = self.hosts.get(shard)
        if host is None:  # concurrent first calls (the ingress's probe and a request) share one start
            if shard not in self.starting:
                self.starting[shard] = asyncio.ensure_future(self._start(shard))
            host = await asyncio.shield(self.starting[shard])
        out = getattr(host, method)(*args)
        return await out if inspect.isawaitable(out) else out

    async def _start(self, shard: str) -> ShardHost:
        settings = Settings(data_dir=self.root / shard, **self.settings)
        host = ShardHost(settings, self.encoder.info, self._embed)
        await host.start()
        self.hosts[shard] = host
        return host

    def make_shards(self) -> ShardSet:
        self.shards = ShardSet(["shard-0", "shard-1"], self.call, self.root / "shards.sqlite", down_s=0.2)
        return self.shards

    @contextmanager
    def client(self, **settings) -> Iterator[TestClient]:
        """The ingress app's client, once its routes are read (unless a shard is dead), its shards
        stopped after (also on failure)."""
        app = create_ingress_app(Settings(data_dir=self.root, **self.settings, **settings), self.make_shards)
        with TestClient(app) as c:
            try:
                deadline = time.monotonic() + 60
                while not self.dead and not self.shards.reconciled and time.monotonic() < deadline:
                    time.sleep(0.05)
                yield c
            finally:
                self.stop(c.portal)

    def stop(self, portal) -> None:
        for host in self.hosts.values():
            portal.call(host.stop)
        self.hosts.clear()
        self.starting.clear()


@pytest.fixture
def cluster(tmp_path):
    return Cluster(tmp_path)


def post(c: TestClient, map_id: str, place: int, key: str | None = None, **params):
    headers = {"Content-Type": "image/png", **({"Idempotency-Key": key} if key else {})}
    return c.post(f"/v1/maps/{map_id}/observations", content=frame(place), headers=headers,
                  params={"learn": "true", **params})


def test_maps_spread_over_shards_and_are_served_through_the_ingress(cluster):
    with cluster.client() as c:
        for m in ("m0", "m1", "m2"):
            r = c.post("/v1/maps", json={"map_id": m, **TINY})
            assert r.status_code == 201, r.text
        owners = {r.map_id: r.shard for r in cluster.shards.table.all()}
        # `default` (made by shard-0 at its first start) is routed where it was found; the new maps go
        # to the shard with fewer maps each time.
        assert owners == {"default": "shard-0", "m0": "shard-1", "m1": "shard-0", "m2": "shard-1"}
        assert sorted(cluster.hosts["shard-1"].map_ids()) == ["default", "m0", "m2"]  # its own default
        for i in range(3):
            r = post(c, "m0", i)
            assert r.status_code == 200 and r.json()["seq"] == i + 1
        # One list over both shards, each map once (shard-1's own `default` is not routed: not listed).
        listed = c.get("/v1/maps").json()["maps"]
        assert [m["map_id"] for m in listed] == ["default", "m0", "m1", "m2"]
        assert next(m for m in listed if m["map_id"] == "m0")["observations"] == 3
        # Reads of one map, the viewer's pages and an id without a route.
        assert c.get("/v1/maps/m0/observations").json()["observations"][0]["seq"] == 1
        assert c.get("/ui/").status_code == 200
        r = c.get("/v1/maps/nowhere")
        assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json"
        assert r.json()["type"] == "urn:cortexloc:problem:map-not-found"
        # A second create of a routed id goes to its owner, which refuses it.
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 409
        # Deleting a map removes its route.
        assert c.delete("/v1/maps/m2").status_code == 204
        assert cluster.shards.table.get("m2") is None
        # A keyed creation without an id: the ingress picks the id a shard would (the key's), so its
        # retry reaches the map's owner and is answered that map, not made a second time elsewhere.
        made = c.post("/v1/maps", json=TINY, headers={"Idempotency-Key": "ingress-create-1"})
        assert made.status_code == 201, made.text
        again = c.post("/v1/maps", json=TINY, headers={"Idempotency-Key": "ingress-create-1"})
        assert again.status_code == 200 and again.headers["Idempotent-Replayed"] == "true", again.text
        assert again.json()["map_id"] == made.json()["map_id"]
        # the key again with other options: the key was reused (as from one process), nothing made
        reused = c.post("/v1/maps", json={**TINY, "seed": 9}, headers={"Idempotency-Key": "ingress-create-1"})
        assert reused.status_code == 422, reused.text
        assert reused.json()["type"].endswith("idempotency-key-reused")
        assert len(c.get("/v1/maps").json()["maps"]) == 4


def test_metrics_readiness_and_memory_cover_every_shard(cluster):
    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201
        assert post(c, "m0", 1).status_code == 200
        text = c.get("/metrics").text
        assert 'shard="shard-0"' in text and 'shard="shard-1"' in text
        assert text.count("# TYPE cortexloc_requests_total counter") == 1  # one family, both shards
        ready = c.get("/readyz")
        assert ready.status_code == 200 and set(ready.json()["checks"]) == {"shard-0", "shard-1"}
        budget = c.get("/v1/memory").json()
        assert {m["map_id"] for m in budget["maps"]} == {"default", "m0"}
        cluster.dead.add("shard-1")
        r = c.get("/readyz")
        assert r.status_code == 503 and r.json()["checks"]["shard-1"]["status"] == "fail"


def test_a_creation_whose_reply_was_lost_is_routed_by_its_retry_and_made_once(cluster):
    """The shard made the map and its reply was lost (503 to the client): the retry goes to that shard,
    not to the one least loaded by then (a second map of the id), and its answer routes the map."""
    calls = cluster.call
    lose: set[str] = set()  # map ids whose next creation's reply is lost after the shard made it

    async def losing(shard: str, method: str, *args):
        reply = await calls(shard, method, *args)
        made = method == "request" and args[:2] == ("POST", "/v1/maps") and reply[0] == 201
        if made and (map_id := json.loads(reply[2])["map_id"]) in lose:
            lose.discard(map_id)
            raise ConnectionError("the reply was lost")
        return reply

    cluster.call = losing

    def held_by(map_id: str) -> list[str]:
        return [name for name, host in cluster.hosts.items() if map_id in host.map_ids()]

    with cluster.client() as c:
        key = {"Idempotency-Key": "lost-create-1"}
        keyed = new_map_id(key["Idempotency-Key"])
        lose.update({keyed, "lab"})
        assert c.post("/v1/maps", json=TINY, headers=key).status_code == 503  # made on shard-1
        assert held_by(keyed) == ["shard-1"] and cluster.shards.table.get(keyed) is None
        # another map fills shard-1: shard-0 is the least loaded now
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201
        assert cluster.shards.table.get("m0").shard == "shard-1"
        again = c.post("/v1/maps", json=TINY, headers=key)
        assert again.status_code == 200 and again.headers["Idempotent-Replayed"] == "true", again.text
        assert held_by(keyed) == ["shard-1"] and cluster.shards.table.get(keyed).shard == "shard-1"
        wait_until_serving(c, keyed)
        assert c.get(f"/v1/maps/{keyed}").status_code == 200
        # without a key: the retry is refused as from one process (409), and the map is routed
        assert c.post("/v1/maps", json={"map_id": "lab", **TINY}).status_code == 503
        shard = held_by("lab")
        retry = c.post("/v1/maps", json={"map_id": "lab", **TINY})
        assert retry.status_code == 409 and retry.json()["type"].endswith("map-exists"), retry.text
        assert held_by("lab") == shard and cluster.shards.table.get("lab").shard == shard[0]
        wait_until_serving(c, "lab")
        assert c.get("/v1/maps/lab").status_code == 200


def test_a_dead_shard_answers_503_with_retry_after_and_a_retry_is_replayed(cluster):
    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201  # on shard-1
        first = post(c, "m0", 1, key="key-00000001")
        assert first.status_code == 200
        cluster.dead.add("shard-1")
        r = post(c, "m0", 2, key="key-00000002")
        assert r.status_code == 503 and r.headers["Retry-After"] == "2"
        assert r.headers["content-type"] == "application/problem+json"
        body = r.json()
        assert body["type"] == "urn:cortexloc:problem:map-unavailable" and body["shard"] == "shard-1"
        # Marked down for a while: the next request is answered without trying the shard.
        assert c.get("/v1/maps/m0").status_code == 503
        # The shard comes back (as Ray restarts it): the same key is replayed, not learned twice.
        cluster.dead.clear()
        cluster.stop(c.portal)  # a restarted replica opens its data directory again
        wait_until_serving(c, "m0")
        again = post(c, "m0", 1, key="key-00000001")
        assert again.status_code == 200 and again.headers["Idempotent-Replayed"] == "true"
        assert again.json()["observation_id"] == first.json()["observation_id"]
        assert c.get("/v1/maps/m0").json()["observations"] == 1


def wait_until_serving(c, map_id: str, within_s: float = 30.0) -> None:
    """Until the ingress's probe finds the map's (restarted) shard serving: its start (opening the maps)
    takes as long as the machine lets it, so no fixed sleep; a shard that never comes back fails the
    caller's next assertion."""
    deadline = time.monotonic() + within_s
    while c.get(f"/v1/maps/{map_id}").status_code == 503 and time.monotonic() < deadline:
        time.sleep(0.05)


def test_a_replica_that_dies_with_a_call_answers_503_never_500(cluster):
    """Issue 34, item 5: what Ray raises for a replica that died with the call (the encoder's, seen by a
    shard; a shard's, seen by the ingress) is a 503 problem+json with Retry-After, which clients retry
    with the same key, never the app's 500 `internal-error`; nothing is stored meanwhile."""
    pytest.importorskip("ray")
    from ray.exceptions import ActorDiedError
    from ray.serve.exceptions import RayServeException, ReplicaUnavailableError

    def refused(r, slug: str) -> None:
        assert r.status_code == 503 and r.headers["Retry-After"] == "2", r.text
        assert r.headers["content-type"] == "application/problem+json"
        assert r.json()["type"] == f"urn:cortexloc:problem:{slug}" and r.json()["retry_after"] == 2

    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201  # on shard-1
        # The encoder deployment's replica dies with the frame in its batch.
        cluster.embed_failure = ActorDiedError()
        refused(post(c, "m0", 1, key="key-00000001"), "not-ready")
        assert c.get("/v1/maps/m0").json()["observations"] == 0
        cluster.embed_failure = None
        r = post(c, "m0", 1, key="key-00000001")
        assert r.status_code == 200 and r.json()["seq"] == 1
        # The shard's replica: Serve's errors for a replica gone, and for an upstream actor that died.
        for error in (ReplicaUnavailableError("shard-1#x"), RayServeException("an upstream actor died")):
            cluster.failures["shard-1"] = error
            refused(post(c, "m0", 2, key="key-00000002"), "map-unavailable")
            cluster.failures.clear()
            wait_until_serving(c, "m0")
        assert c.get("/v1/maps/m0").json()["observations"] == 1
        assert post(c, "m0", 2, key="key-00000002").json()["seq"] == 2


def test_the_edge_rules_hold_at_the_ingress(cluster):
    """API keys, upload limits: refused at the ingress, before any shard is asked."""
    with cluster.client(api_key="s3cret-key", max_upload_bytes=100_000) as c:
        r = c.post("/v1/maps", json={"map_id": "m0", **TINY})
        assert r.status_code == 401 and r.headers["content-type"] == "application/problem+json"
        r = c.post("/v1/maps", json={"map_id": "m0", **TINY}, headers={"X-API-Key": "s3cret-key"})
        assert r.status_code == 201
        assert post(c, "m0", 1).status_code == 401
        big = c.post("/v1/maps/m0/observations", content=b"\xff" * 200_000,
                     headers={"Content-Type": "image/jpeg", "X-API-Key": "s3cret-key"})
        assert big.status_code == 413 and big.json()["type"] == "urn:cortexloc:problem:payload-too-large"


def test_the_query_rules_hold_through_the_ingress(cluster):
    """Unknown, repeated and non-UTF-8 query parameters and a doubled Idempotency-Key are refused as by
    one process (docs/design/service.md §2): on the ingress's own routes, and on a map's, forwarded as
    sent (re-encoded, `caf%E9` reached the shard as U+FFFD and was stored)."""
    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201
        for path in ("/v1/maps?foo=1", "/v1/memory?foo=1", "/metrics?foo=1"):
            r = c.get(path)
            assert r.status_code == 400 and r.json()["errors"][0]["name"] == "foo", (path, r.text)
        assert c.get("/healthz?foo=1").status_code == 200  # a probe's stray parameter fails nothing
        for query in ("Learn=false", "label=caf%E9", "learn=true&learn=false"):
            r = c.post(f"/v1/maps/m0/observations?{query}", content=frame(1),
                       headers={"Content-Type": "image/png"})
            assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter"), (query, r.text)
        two = [("Content-Type", "image/png"), ("Idempotency-Key", "key-aaaaaaaa"),
               ("Idempotency-Key", "key-bbbbbbbb")]
        r = c.post("/v1/maps/m0/observations", content=frame(1), headers=two)
        assert r.status_code == 400, r.text
        assert c.get("/v1/maps/m0").json()["last_seq"] == 0
        # a JSON member given twice (found in review: without a `map_id` the ingress parsed the body
        # itself, kept the last and forwarded it re-written, so the shard never saw the repeat)
        tiny = json.dumps(TINY)[1:-1]
        for twice in ('"seed": 3, "seed": 4', '"map_id": "lab", "map_id": ""'):
            body = "{" + twice + ", " + tiny + "}"
            r = c.post("/v1/maps", content=body, headers={"Content-Type": "application/json"})
            assert r.status_code == 400 and "more than once" in r.json()["detail"], (body, r.text)
        assert [m["map_id"] for m in c.get("/v1/maps").json()["maps"]] == ["default", "m0"]  # no new map


async def raw_delete(app, path: str) -> tuple[int, bytes]:
    """DELETE `path` on the ASGI `app` exactly as a client may send it (curl --path-as-is)."""
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "DELETE",
             "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(b"host", b"testserver")], "client": ("127.0.0.1", 1), "server": ("testserver", 80)}
    sent: list[dict] = []

    async def receive() -> dict:
        return {"type": "http.request", "body": b"", "more_body": False}

    async def send(message: dict) -> None:
        sent.append(message)

    await app(scope, receive, send)
    return sent[0]["status"], b"".join(m.get("body", b"") for m in sent[1:])


def test_a_dot_segment_reaches_the_shard_as_one_segment_never_another_resource(cluster):
    """Found in review: the ingress forwarded the decoded path, so the typed client's
    `delete_snapshot(m0, "..")` (`…/snapshots/%2E%2E`) became DELETE /v1/maps/m0 on the shard, and the
    table kept routing to the deleted map; a bare `..` reached another map past the table."""
    with cluster.client() as c:
        for m in ("m0", "m1"):
            assert c.post("/v1/maps", json={"map_id": m, **TINY}).status_code == 201
        assert post(c, "m0", 1).status_code == 200
        r = c.delete("/v1/maps/m0/snapshots/%2E%2E")
        assert r.status_code in (400, 404) and r.json()["type"].endswith(("invalid-parameter", "not-found"))
        r = c.post("/v1/maps/m0/streams/%2E%2E/reset")  # a stream named ".." is one segment, its own
        assert r.status_code != 404 or "stream" in r.json()["detail"], r.text
        for bare in ("/v1/maps/m0/a/../../m1", "/v1/maps/m0/snapshots/.."):
            status, body = c.portal.call(raw_delete, c.app, bare)  # httpx would resolve the dots first
            assert status == 400 and json.loads(body)["type"].endswith("invalid-parameter"), (bare, body)
        assert c.get("/v1/maps/m0").json()["last_seq"] == 1 and c.get("/v1/maps/m1").status_code == 200
        assert {m["map_id"] for m in c.get("/v1/maps").json()["maps"]} >= {"m0", "m1"}
        r = post(c, "m0", 1, label="caf\u00e9 au lait", top_k=1)
        assert r.status_code == 200, r.text
        assert c.get(f"/v1/maps/m0/observations/{r.json()['seq']}").json()["label"] == "caf\u00e9 au lait"


def test_moving_a_map_keeps_every_row_and_switches_the_route(cluster):
    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201  # shard-1
        acked = [post(c, "m0", i, key=f"move-key-{i:04d}").json()["observation_id"] for i in range(4)]
        epoch = c.get("/v1/maps/m0/loop-closures").json()["epoch"]
        out = c.portal.call(cluster.shards.move, "m0", "shard-0", [])
        assert out["from"] == "shard-1" and out["to"] == "shard-0" and out["observations"] == 4
        assert cluster.shards.table.get("m0").shard == "shard-0"
        assert "m0" not in cluster.hosts["shard-1"].map_ids()
        rows = c.get("/v1/maps/m0/observations").json()["observations"]
        assert [r["observation_id"] for r in rows] == acked
        # the same map, its log and rows in the same epoch: a back end's cursor stays good
        assert c.get("/v1/maps/m0/loop-closures").json()["epoch"] == epoch
        # The moved map learns on: the next seq, and a key of before the move is still replayed.
        assert post(c, "m0", 9).json()["seq"] == 5
        assert post(c, "m0", 0, key="move-key-0000").headers["Idempotent-Replayed"] == "true"
        with pytest.raises(MoveFailed):
            c.portal.call(cluster.shards.move, "m0", "shard-0", [])
        with pytest.raises(MoveFailed):
            c.portal.call(cluster.shards.move, "m0", "shard-9", [])


def test_the_map_table_is_durable(tmp_path):
    t = ShardTable(tmp_path / "shards.sqlite")
    t.set("a", "shard-1")
    assert t.add_missing("a", "shard-0") is False and t.add_missing("b", "shard-0") is True
    t.set("a", "shard-1", "moving")
    t.close()
    t = ShardTable(tmp_path / "shards.sqlite")
    assert [tuple(r) for r in t.all()] == [("a", "shard-1", "moving"), ("b", "shard-0", "serving")]
    t.close()


def test_the_ingress_lists_only_what_the_table_routes(cluster):
    """A map found on two shards (a move cut short before its old copy went) is served by its route."""
    with cluster.client() as c:
        listed = [m["map_id"] for m in c.get("/v1/maps").json()["maps"]]
        assert listed == ["default"] and cluster.shards.table.get("default").shard == "shard-0"
        assert json.loads(c.get("/readyz").text)["status"] == "ready"


def test_the_encoder_deployment_fails_only_the_bad_image_of_a_batch(cluster):
    """One undecodable upload among good ones (batched together by `@serve.batch`) fails only itself,
    and a shard's `RemoteEmbedder` raises it as the `ImageError` that the routes answer with a 4xx."""
    from models.frontend.images import ImageError
    from service.scaleout.embedding import RemoteEmbedder

    enc = cluster.encoder
    backbone = enc.encoders.default
    replies = enc.embed_batch([(backbone, None, frame(1), False), (backbone, None, b"not an image", False),
                               (backbone, "squash", frame(2), True)])
    assert [r[0] for r in replies] == ["ok", "error", "ok"]
    assert replies[0][1].shape == (1, enc.info(backbone)["feature_dim"]) and replies[2][2] is not None
    remote = RemoteEmbedder(enc.info(backbone), cluster._embed)
    out = remote.embed([frame(1), frame(2)])
    assert out.features.shape == (2, remote.feature_dim) and set(out.timings_ms) >= {"decode", "backbone"}
    # the frames' contrast crosses the process boundary: the low-information rule holds on shards too
    local = enc.encoders.get(backbone).embed([frame(1), frame(2)])
    assert out.contrast is not None and out.contrast.tolist() == pytest.approx(local.contrast.tolist())
    assert remote.identity_for("squash") == enc.encoders.get(backbone).identity_for("squash")
    with pytest.raises(ImageError):
        remote.embed([frame(1), b"not an image"])
    with cluster.client() as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201
        r = c.post("/v1/maps/m0/observations", content=b"not an image", headers={"Content-Type": "image/png"})
        assert r.status_code in (400, 415, 422) and r.headers["content-type"] == "application/problem+json"
        assert c.get("/v1/maps/m0").json()["observations"] == 0
        assert c.get("/openapi.json").json()["paths"]["/v1/maps/{map_id}/observations"]


def test_a_shard_down_at_the_ingress_start_is_read_when_it_answers(cluster):
    """Until every shard's maps are in the table, an id without a route is 503 (it may be on the shard
    not read yet), not 404; the ingress keeps trying and is ready once the shard answers."""
    cluster.dead.add("shard-1")
    with cluster.client() as c:
        r = c.get("/readyz")
        assert r.status_code == 503 and "routes" in r.json()["checks"]
        r = c.get("/v1/maps/anything")
        assert r.status_code == 503 and r.headers["Retry-After"] == "2"
        cluster.dead.clear()
        deadline = time.monotonic() + 30
        while c.get("/readyz").status_code != 200 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert c.get("/readyz").status_code == 200
        assert c.get("/v1/maps/anything").status_code == 404


def test_where_reads_need_the_key_the_ingress_readiness_names_no_file_of_the_host(cluster):
    # the reason the ingress gives itself for routes it could not read is any exception's text (Ray's
    # words may name its session's files); the shards hide their own (tests/service/test_read_key.py)
    secret = f"{cluster.root}/ray/session_latest/logs/raylet.err"
    cluster.dead.add("shard-1")
    for reads, shown in ((True, False), (False, True)):
        with cluster.client(api_key="k3y", api_key_reads=reads) as c:
            deadline = time.monotonic() + 30
            while c.app.state.shards_error is None and time.monotonic() < deadline:  # its first try failed
                time.sleep(0.05)
            c.app.state.shards_error = f"the shards' maps could not be read: RuntimeError: see {secret}"
            r = c.get("/readyz")
            assert r.status_code == 503 and {"routes", "shard-1"} <= set(r.json()["checks"]), r.text
            assert (secret in r.text) is shown
            assert (r.json()["checks"]["routes"]["error"] == UNNAMED_ERROR) is not shown
            assert "shard-1" in r.json()["checks"]["shard-1"]["error"]  # which shard, said either way


def test_a_stalled_body_meets_the_deadline_at_the_ingress(cluster):
    """A body that stops arriving is answered 408 by the ingress at CORTEXLOC_BODY_TIMEOUT_S, before any
    shard is asked: the ingress holds no request longer than the single process would."""
    import anyio

    with cluster.client(body_timeout_s=1.0) as c:
        assert c.post("/v1/maps", json={"map_id": "m0", **TINY}).status_code == 201
        sent: list[dict] = []
        first = [{"type": "http.request", "body": b"\x89PNG" + b"\0" * 60, "more_body": True}]

        async def receive() -> dict:
            if first:
                return first.pop()
            await anyio.sleep(30)  # the rest never comes
            return {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            sent.append(message)

        async def drive() -> None:
            path = "/v1/maps/m0/observations"
            scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
                     "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"learn=true",
                     "root_path": "", "client": ("127.0.0.1", 1), "server": ("t", 80),
                     "headers": [(b"host", b"t"), (b"content-type", b"image/png"),
                                 (b"content-length", b"5000")]}
            with anyio.fail_after(15):
                await c.app(scope, receive, send)

        t0 = time.monotonic()
        c.portal.call(drive)
        start = next(m for m in sent if m["type"] == "http.response.start")
        assert start["status"] == 408 and time.monotonic() - t0 < 10
        assert c.get("/v1/maps/m0").json()["observations"] == 0


def test_a_request_its_shard_took_and_did_not_answer_is_of_unknown_outcome(tmp_path):
    """A review: the ingress answered a request its shard took and did not answer (its replica died with
    it, or it passed `call_timeout_s`) with the same 503 as one never sent, which clients read as "nothing
    was done" and send again whatever it is. The shard had deleted the map: the typed client's retry got
    404 and raised NotFoundError, and the ingress kept routing the deleted map. Now the 503 says
    `outcome_unknown`, the client retries only what is safe (a delete, finding it gone, is done), and a
    delete the owner answers 404 `map-not-found` drops the route."""
    import httpx

    from cortexloc_client import AsyncClient, RetryPolicy
    from cortexloc_client.errors import ServiceUnavailableError

    maps, seen = {"lab"}, []

    async def shard_call(shard, method, *args):
        if method == "map_ids":
            return sorted(maps)
        verb, path = args[0], args[1]
        seen.append((verb, path))
        if verb == "DELETE":
            if "lab" in maps:
                maps.discard("lab")  # the shard deletes the map, and its answer is late
                await asyncio.sleep(1.0)
                return 204, [], b""
            body = json.dumps({"type": "urn:cortexloc:problem:map-not-found", "status": 404,
                               "detail": "no map 'lab'"}).encode()
            return 404, [("content-type", "application/problem+json")], body
        await asyncio.sleep(1.0)  # a snapshot taken, its answer late
        return 201, [], b"{}"

    async def main() -> None:
        app = create_ingress_app(Settings(data_dir=tmp_path / "var"), lambda: None)
        shards = ShardSet(["shard-0"], shard_call, tmp_path / "shards.sqlite", call_timeout_s=0.2,
                          down_s=0.05)
        await shards.reconcile()
        app.state.shards, app.state.shards_error = shards, None
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://ingress.test") as raw:
            r = await raw.post("/v1/maps/lab/snapshots")
            assert r.status_code == 503 and r.json()["outcome_unknown"] is True
            await asyncio.sleep(0.3)  # the shard answers its probe again
            assert (await raw.get("/v1/maps/nosuch")).status_code == 404
        async with AsyncClient("http://ingress.test", transport=transport,
                               retry=RetryPolicy(attempts=4, max_wait_s=0.3)) as c:
            with pytest.raises(ServiceUnavailableError):  # not sent again: a second snapshot
                await c.create_snapshot("lab")
            assert [v for v, _ in seen].count("POST") == 2  # the raw one, and this one once
            await asyncio.sleep(0.3)
            assert await c.delete_map("lab") is None
        assert shards.table.get("lab") is None and maps == set()
        assert seen.count(("DELETE", "/v1/maps/lab")) == 2

    asyncio.run(main())
