"""GET /v1/maps/{map_id}/recent: the observation replies as they were sent, newest last, in memory only."""

from __future__ import annotations

from service.maps.runtime.recent import RECENT_CAPACITY
from tests.service.helpers import frame, make_client, post


def test_recent_gives_back_each_reply_as_sent_in_arrival_order(tmp_path):
    with make_client(tmp_path / "var") as c:
        sent = [post(c, frame(p), learn="true", stream="cam0", label=f"p{p}").json() for p in range(3)]
        sent.append(post(c, frame(1), learn="false", stream="cam1").json())
        r = c.get("/v1/maps/default/recent")
        assert r.status_code == 200
        body = r.json()
        assert body["map_id"] == "default" and body["capacity"] == RECENT_CAPACITY
        top_only = [{**reply, "matches": reply["matches"][:1]} for reply in sent]
        assert [a["reply"] for a in body["answers"]] == top_only  # every field as sent, the top match only
        times = [a["received_at"] for a in body["answers"]]
        assert times == sorted(times)

        assert [a["reply"]["seq"] for a in c.get("/v1/maps/default/recent?limit=2").json()["answers"]] == \
            [sent[2]["seq"], None]
        cam1 = c.get("/v1/maps/default/recent?stream=cam1").json()["answers"]
        assert [a["reply"] for a in cam1] == [top_only[3]]


def test_recent_refuses_bad_parameters_and_unknown_maps(tmp_path):
    with make_client(tmp_path / "var") as c:
        for query in ("limit=0", f"limit={RECENT_CAPACITY + 1}", "stream=a%20b"):
            r = c.get(f"/v1/maps/default/recent?{query}")
            assert r.status_code == 400 and r.headers["content-type"] == "application/problem+json", query
        assert c.get("/v1/maps/nope/recent").json()["type"].endswith(":map-not-found")


def test_recent_is_in_memory_only_and_follows_the_read_key_rule(tmp_path):
    with make_client(tmp_path / "var", api_key="k3y", api_key_reads=True) as c:
        assert post(c, frame(0), learn="true").status_code == 401  # writes need the key anyway
        assert c.post("/v1/maps/default/observations", content=frame(0), headers={
            "Content-Type": "image/png", "X-API-Key": "k3y"}).status_code == 200
        assert c.get("/v1/maps/default/recent").status_code == 401
        assert c.get("/v1/maps/default/recent/1/thumbnail").status_code == 401  # a frame is map content
        assert len(c.get("/v1/maps/default/recent", headers={"X-API-Key": "k3y"}).json()["answers"]) == 1
    with make_client(tmp_path / "var", api_key="k3y") as c:  # restarted; reads open without the setting
        assert c.get("/v1/maps/default/recent").json()["answers"] == []
        assert c.get("/v1/maps/default").json()["observations"] == 1


def test_recent_takes_the_same_stream_names_as_posts(tmp_path):
    """A ROS-style stream name ('/') is accepted wherever a stream is named (one pattern)."""
    with make_client(tmp_path) as c:
        assert post(c, frame(1), stream="robot1/cam0").status_code == 200
        r = c.get("/v1/maps/default/recent", params={"stream": "robot1/cam0"})
        assert r.status_code == 200, r.text
        assert [a["reply"]["stream"] for a in r.json()["answers"]] == ["robot1/cam0"]


def test_the_window_keeps_the_top_match_only_and_a_restore_empties_it(tmp_path):
    with make_client(tmp_path) as c:
        for i in range(3):
            assert post(c, frame(i)).status_code == 200
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        sent = post(c, frame(1), learn="false", top_k=3).json()
        assert len(sent["matches"]) == 3
        kept = c.get("/v1/maps/default/recent").json()["answers"][-1]["reply"]
        assert kept["matches"] == sent["matches"][:1] and kept["place"] == sent["place"]
        assert c.post(f"/v1/maps/default/snapshots/{sid}/restore").status_code == 200
        assert c.get("/v1/maps/default/recent").json()["answers"] == []


def test_the_query_frame_thumbnail_is_kept_with_its_answer(tmp_path):
    """A localised frame's image is stored nowhere: the ring keeps its thumbnail, for the viewer."""
    with make_client(tmp_path) as c:
        assert c.post("/v1/maps", json={"map_id": "album", "thumbnails": True}).status_code == 201
        learned = post(c, frame(1), map_id="album").json()
        post(c, frame(2), map_id="album", learn="false")
        keyed = {"Content-Type": "image/png", "Idempotency-Key": "key-0001"}
        for _ in range(2):  # a keyed post keeps its thumbnail too; its replay adds no answer
            assert c.post("/v1/maps/album/observations?learn=false", content=frame(3),
                          headers=keyed).status_code == 200
        post(c, frame(2), learn="false")  # a map without thumbnails keeps none
        answers = c.get("/v1/maps/album/recent").json()["answers"]
        assert [a["has_thumbnail"] for a in answers] == [True, True, True]
        first, second, _ = (c.get(f"/v1/maps/album/recent/{a['answer_id']}/thumbnail") for a in answers)
        assert first.status_code == second.status_code == 200
        assert first.headers["content-type"] == "image/jpeg" and second.content[:3] == b"\xff\xd8\xff"
        # The learned frame's is the one stored with its row; the localised frame's differs from it.
        assert first.content == c.get(f"/v1/maps/album/observations/{learned['seq']}/thumbnail").content
        assert second.content != first.content
        plain = c.get("/v1/maps/default/recent").json()["answers"]
        assert [a["has_thumbnail"] for a in plain] == [False]
        gone = c.get(f"/v1/maps/default/recent/{plain[0]['answer_id']}/thumbnail")
        assert gone.status_code == 404 and gone.json()["type"].endswith(":recent-answer-not-found")
        assert gone.json()["answer_id"] == plain[0]["answer_id"]
        assert c.get("/v1/maps/album/recent/0/thumbnail").status_code == 400


def test_the_key_cache_is_bounded_by_reply_text_too():
    from service.maps.runtime import idempotency
    from storage.mapschema import KeyRecord

    cache = idempotency.KeyCache(1000)
    big = "x" * (idempotency.CACHE_MAX_CHARS // 3)
    for i in range(5):
        cache.put(KeyRecord(f"key-{i}", "f", big))
    assert cache.get("key-0") is None and cache.get("key-4") is not None
