"""The per-map stream cap (docs/design/service.md §1.3, issue 19 item 8): a stream that posted within
CORTEXLOC_STREAM_KEEP_SECONDS is never evicted for a new one; the new one is refused (429 stream-limit,
Retry-After) and every robot keeps its context; idle streams are evicted, and counted in /metrics."""

from __future__ import annotations

import re
import time

from tests.service.helpers import frame, make_client, post, state_of


def evictions(c, map_id: str = "default") -> float:
    m = re.search(rf'cortexloc_map_stream_evictions\{{map="{map_id}"\}} (\S+)', c.get("/metrics").text)
    assert m, "no stream eviction metric"
    return float(m.group(1))


def test_a_recent_stream_is_not_evicted_for_a_new_one(tmp_path):
    with make_client(tmp_path / "data", max_streams=2, stream_keep_seconds=1.5) as c:
        for i, robot in enumerate(("robot1", "robot2")):
            assert post(c, frame(i), stream=robot).status_code == 200
        before = state_of(c)
        for learn in ("true", "false"):
            r = post(c, frame(5), stream="intruder", learn=learn)
            assert r.status_code == 429, r.text
            p = r.json()
            assert p["type"] == "urn:cortexloc:problem:stream-limit"
            assert (p["max_streams"], p["keep_seconds"]) == (2, 1.5)
            assert 1 <= int(r.headers["Retry-After"]) == p["retry_after"] <= 2
        assert state_of(c) == before
        assert c.get("/v1/maps/default").json()["streams"] == ["robot1", "robot2"]
        assert evictions(c) == 0
        # Both robots go on in their sequences.
        assert post(c, frame(2), stream="robot1").json()["sequence"]["step"] == 1
        time.sleep(1.6)  # robot2 idle past the window now; robot1 posted since
        assert post(c, frame(3), stream="robot1").status_code == 200
        r = post(c, frame(5), stream="newcomer")
        assert r.status_code == 200, r.text
        assert c.get("/v1/maps/default").json()["streams"] == ["robot1", "newcomer"]
        assert evictions(c) == 1
        assert post(c, frame(4), stream="robot1").json()["sequence"]["step"] == 3  # context kept


def test_without_a_window_the_least_recently_used_stream_goes_at_once(tmp_path):
    with make_client(tmp_path / "data", max_streams=2, stream_keep_seconds=0) as c:
        for i, robot in enumerate(("a", "b", "c")):
            assert post(c, frame(i), stream=robot).status_code == 200
        assert c.get("/v1/maps/default").json()["streams"] == ["b", "c"]
        assert evictions(c) == 1
