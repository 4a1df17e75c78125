"""`cortexloc ingest` in process: the answers of posting the frames one by one; order, retries, errors."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from service import cli
from service.app import create_app
from service.ingest import poster
from service.ingest.sources import open_source
from service.settings import Settings
from tests.service.ingest.data import (
    DAMAGE,
    ROUTE,
    TOPICS,
    comparable,
    stamp,
    write_damaged_bag,
    write_folder,
    write_ros2_bag,
)


def reference(data_dir: Path, map_id: str, bodies: list[bytes], *, labels: list[str | None] | None = None,
              stream: str = "default") -> list[dict[str, Any]]:
    """The answers of posting `bodies` one by one, by hand, to a new map of a fresh service."""
    with TestClient(create_app(Settings(data_dir=data_dir))) as c:
        assert c.post("/v1/maps", json={"map_id": map_id}).status_code == 201
        out = []
        for body, label in zip(bodies, labels or [None] * len(bodies), strict=True):
            ctype = "image/png" if body.startswith(b"\x89PNG") else "image/jpeg"
            params = {"stream": stream, **({"label": label} if label else {})}
            r = c.post(f"/v1/maps/{map_id}/observations", content=body, params=params,
                       headers={"Content-Type": ctype})
            assert r.status_code == 200, r.text
            out.append(r.json())
        return out


def test_cli_ingests_a_folder_in_process_with_the_answers_of_posting_one_by_one(tmp_path, monkeypatch):
    monkeypatch.setenv("CORTEXLOC_API_KEY", "s3cret")  # the in-process app wants it; the ingest sends it
    bodies = write_folder(tmp_path / "frames")
    result = CliRunner().invoke(cli.app, ["ingest", str(tmp_path / "frames"), "--map", "farm", "--stream",
                                          "cam0", "--data-dir", str(tmp_path / "a"), "--json"])
    assert result.exit_code == 0, result.output
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["frame"] for line in lines] == list(range(len(ROUTE)))
    assert all(line["status"] == 200 and line["answer"]["stream"] == "cam0" for line in lines)
    want = reference(tmp_path / "b", "farm", bodies, stream="cam0")
    assert [comparable(line["answer"]) for line in lines] == [comparable(a) for a in want]
    assert lines[6]["answer"]["matches"][0]["seq"] == lines[2]["answer"]["seq"]  # the loop closes
    assert "map created" in result.stderr and f"posted {len(ROUTE)}/{len(ROUTE)} frames" in result.stderr
    assert "revisits" in result.stderr and "latency median" in result.stderr


def test_every_topic_of_a_ros2_bag_answers_as_its_frames_posted_one_by_one(tmp_path):
    bag = write_ros2_bag(tmp_path / "bag")
    labels = [f"{stamp(i) // 10**9}.{stamp(i) % 10**9:09d}" for i in range(len(ROUTE))]
    got: dict[str, list[poster.Record]] = {}

    async def run() -> None:
        settings = Settings(data_dir=tmp_path / "a", log_level="WARNING")
        async with poster.in_process_client(settings) as client:
            for topic in TOPICS:
                got[topic] = []
                opts = poster.Options(map_id=topic.strip("/").replace("/", "-"), label_stamp=True)
                summary = await poster.ingest(client, open_source(bag, topic=topic), opts,
                                              on_record=got[topic].append)
                assert summary.created_map and summary.frames == summary.learned == len(ROUTE)
                # a revisit in the summary is the service's own decision, frame by frame
                assert summary.revisits == sum(bool((r.answer.get("place") or {}).get("revisit"))
                                               for r in got[topic])
                assert summary.errors == 0

    anyio.run(run)
    for topic, (_, body_of) in TOPICS.items():
        want = reference(tmp_path / f"ref{topic.replace('/', '-')}", "m", [body_of(p) for p in ROUTE],
                         labels=labels)
        assert [comparable(r.answer) for r in got[topic]] == [comparable(a) for a in want], topic
        assert [r.stamp_ns for r in got[topic]] == [stamp(i) for i in range(len(ROUTE))]
        assert got[topic][6].answer["matches"][0]["label"] == labels[2]  # the loop closes


def test_bag_messages_that_cannot_be_frames_are_counted_and_the_ingest_goes_on(tmp_path):
    # An outside probe: the first message in an encoding the service does not take (or shorter than its
    # shape) stopped the whole ingest with exit 2, frames already learned; the ROS 2 node skips them.
    import cv2
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from tests.service.ingest.data import image_msg, place_bgr

    ts = get_typestore(Stores.ROS2_HUMBLE)
    bag = tmp_path / "bag"
    with Writer(bag, version=9) as w:
        conn = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(6):
            msg = image_msg(ts, cv2.resize(place_bgr(i), (64, 48)), "rgb8", stamp(i))
            if i == 2:
                msg.encoding = "yuv422"
            if i == 4:
                msg.step = 64  # under 64 pixels x 3 bytes a row
            w.write(conn, stamp(i), ts.serialize_cdr(msg, conn.msgtype))
    records: list[poster.Record] = []

    async def run() -> poster.Summary:
        settings = Settings(data_dir=tmp_path / "a", log_level="WARNING")
        async with poster.in_process_client(settings) as client:
            return await poster.ingest(client, open_source(bag), poster.Options(map_id="m"),
                                       on_record=records.append)

    summary = anyio.run(run)
    assert [r.status for r in records] == [200, 200, 415, 200, 422, 200]
    assert summary.errors == 2 and summary.learned == 4
    assert "yuv422" in records[2].answer["detail"] and records[4].answer["sent"] is False
    out = CliRunner().invoke(cli.app, ["ingest", str(bag), "--map", "n", "--data-dir", str(tmp_path / "b")])
    assert out.exit_code == 1, out.output  # some frame refused: 1, not 2 (the source is usable)


def test_message_stamps_arrive_as_the_observations_stamp(tmp_path):
    bag = write_ros2_bag(tmp_path / "bag", topics=["/cam/bgr"])
    records: list[poster.Record] = []
    stored: list[dict[str, Any]] = []

    async def run() -> None:
        settings = Settings(data_dir=tmp_path / "a", log_level="WARNING")
        async with poster.in_process_client(settings) as client:
            await poster.ingest(client, open_source(bag), poster.Options(map_id="m", stream="robot1/cam0"),
                                on_record=records.append)
            r = await client.get("/v1/maps/m/observations", params={"limit": 100})
            stored.extend(r.json()["observations"])

    anyio.run(run)
    stamps = [stamp(i) / 1e9 for i in range(len(ROUTE))]  # header.stamp, in seconds
    assert [r.answer["metadata"]["stamp"] for r in records] == stamps
    assert [o["metadata"]["stamp"] for o in stored] == stamps
    # exact, as the ROS 2 node posts it (an outside probe: seconds as a float lose the last digits)
    assert [int(o["metadata"]["stamp_ns"]) for o in stored] == [stamp(i) for i in range(len(ROUTE))]
    assert {o["stream"] for o in stored} == {"robot1/cam0"}
    assert records[6].answer["matches"][0]["metadata"]["stamp"] == stamps[2]  # where the loop closes


def test_bad_sources_and_options_exit_2_with_the_reason(tmp_path):
    bag = write_ros2_bag(tmp_path / "bag", topics=["/cam/rgb", "/cam/mono"])
    run = CliRunner().invoke
    r = run(cli.app, ["ingest", str(bag), "--map", "m", "--data-dir", str(tmp_path / "a")])
    assert r.exit_code == 2 and "2 image topics, choose one with --topic: /cam/mono, /cam/rgb" in r.stderr
    r = run(cli.app, ["ingest", str(bag), "--map", "m", "--topic", "/nope", "--data-dir", str(tmp_path)])
    assert r.exit_code == 2 and "no topic '/nope'" in r.stderr
    r = run(cli.app, ["ingest", str(bag), "--map", "m", "--url", "http://x", "--data-dir", str(tmp_path)])
    assert r.exit_code == 2 and "--data-dir" in r.stderr
    for url in ("localhost:8012", "ftp://x", "http://"):  # found from outside: exit 1 after "posted 0/30"
        r = run(cli.app, ["ingest", str(bag), "--map", "m", "--topic", "/cam/rgb", "--url", url])
        assert r.exit_code == 2 and "no http:// or https:// URL" in r.stderr and "posted" not in r.output
    assert not (tmp_path / "a").exists()  # nothing started


@pytest.mark.parametrize("kind", DAMAGE)
def test_a_damaged_bag_exits_2_with_one_line(tmp_path, kind):
    """Found from outside: a truncated or random bag printed a 43-line traceback and exited 1."""
    bag = write_damaged_bag(kind, tmp_path)
    r = CliRunner().invoke(cli.app, ["ingest", str(bag), "--map", "m", "--data-dir", str(tmp_path / "a")])
    assert r.exit_code == 2, (r.exit_code, r.output, r.exception)
    assert r.stderr.startswith("error: ") and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "cannot read the bag" in r.stderr and "Traceback" not in r.output


def test_an_in_process_ingest_beside_a_server_on_its_data_directory_says_so_in_one_line(tmp_path):
    write_folder(tmp_path / "frames")
    with TestClient(create_app(Settings(data_dir=tmp_path / "a"))):  # the server holding the directory
        r = CliRunner().invoke(cli.app, ["ingest", str(tmp_path / "frames"), "--map", "m", "--data-dir",
                                         str(tmp_path / "a")])  # at once: no wait for the lock
    assert r.exit_code == 1, (r.exit_code, r.output, r.exception)
    last = r.stderr.strip().splitlines()[-1]  # (after the source's header and the app's log line)
    assert last.startswith("error: ") and "in use by another cortexloc process" in last and "--url" in last
    assert "Traceback" not in r.output


# ----------------------------------------------------------------- against a scripted service


class Scripted:
    """A fake service: GET map -> 200; observation posts answered by `answers` in turn (then 200)."""

    def __init__(self, answers: list[tuple[int, dict[str, str]] | httpx.Response | Exception] | None = None
                 ) -> None:
        self.answers = list(answers or [])
        self.bodies: list[bytes] = []
        self.keys: set[str | None] = set()
        self.idempotency_keys: list[str | None] = []  # of each post, in order
        self.in_flight = self.max_in_flight = 0

    async def __call__(self, request: httpx.Request) -> httpx.Response:
        self.keys.add(request.headers.get("X-API-Key"))
        if request.method == "GET":
            return httpx.Response(200, json={"map_id": "m"})
        self.in_flight += 1
        self.max_in_flight = max(self.max_in_flight, self.in_flight)
        # Every other task runs until it waits: a second post the ingest had ready would now be in here.
        await anyio.wait_all_tasks_blocked()
        self.in_flight -= 1
        self.bodies.append(request.content)
        self.idempotency_keys.append(request.headers.get("Idempotency-Key"))
        answer = self.answers.pop(0) if self.answers else (200, {})
        if isinstance(answer, Exception):
            raise answer
        if isinstance(answer, httpx.Response):
            return answer
        status, headers = answer
        body = {"learned": True, "matches": []} if status == 200 else {"title": "T", "detail": f"d{status}"}
        return httpx.Response(status, json=body, headers=headers)


Service = Callable[[httpx.Request], Awaitable[httpx.Response]]


def _ingest(tmp_path: Path, service: Service, *, prefetch: int = 4, api_key: str | None = None,
            map_id: str = "m"):
    bodies = write_folder(tmp_path / "frames")
    sleeps: list[float] = []

    async def sleep(s: float) -> None:
        sleeps.append(s)

    async def run() -> poster.Summary:
        async with httpx.AsyncClient(transport=httpx.MockTransport(service), base_url="http://svc") as c:
            src = open_source(tmp_path / "frames")
            opts = poster.Options(map_id, prefetch=prefetch, api_key=api_key)
            return await poster.ingest(c, src, opts, sleep=sleep)

    return bodies, sleeps, run


def test_posts_go_one_at_a_time_in_source_order_whatever_the_prefetch(tmp_path):
    service = Scripted()
    bodies, _, run = _ingest(tmp_path, service, prefetch=8, api_key="k")
    summary = anyio.run(run)
    assert service.bodies == bodies and service.max_in_flight == 1 and service.keys == {"k"}
    assert summary.frames == len(ROUTE) and summary.errors == 0


def test_503_is_retried_after_retry_after_and_the_frame_is_posted_once_answered(tmp_path):
    service = Scripted([(503, {"Retry-After": "3"}), (503, {}), (200, {})])
    bodies, sleeps, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert sleeps == [3.0, 2.0]  # the header's delay, then backoff (attempt 1: 2 s)
    assert service.bodies == [bodies[0]] * 3 + bodies[1:]
    assert summary.retries == 2 and summary.frames == len(ROUTE)
    assert poster.retry_after_s("3600", 0) == poster.MAX_WAIT_S
    # A proxy's header that is no delay (an outside probe: `nan` reached asyncio.sleep): the backoff.
    for value in ("nan", "inf", "-inf", "-5", "Wed, 21 Oct 2015 07:28:00 GMT"):
        assert poster.retry_after_s(value, 2) == 4.0, value


def test_a_post_a_restore_rolled_back_is_sent_again_with_its_key(tmp_path):
    """409 `map-restored`: the service kept nothing of the post, so it is sent again (the same key), not
    counted as a refusal that stops the ingest."""
    rolled_back = httpx.Response(409, json={"type": "urn:cortexloc:problem:map-restored", "detail": "d"},
                                 headers={"Content-Type": "application/problem+json"})
    service = Scripted([rolled_back, (200, {})])
    bodies, _, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert service.bodies[:2] == [bodies[0]] * 2 and len(set(service.idempotency_keys[:2])) == 1
    assert summary.retries == 1 and summary.errors == 0 and summary.frames == len(ROUTE)


def test_retries_are_bounded(tmp_path):
    service = Scripted([(503, {"Retry-After": "1"})] * (poster.MAX_RETRIES + 1))
    _, sleeps, run = _ingest(tmp_path, service)
    with pytest.raises(poster.IngestError, match=r"frame frame_0000\.png: 503 T: d503") as e:
        anyio.run(run)
    assert sleeps == [1.0] * poster.MAX_RETRIES and e.value.summary.errors == 1


def test_a_proxys_plain_500_and_a_lost_connection_are_retried_with_the_frames_key(tmp_path):
    """Ray Serve's proxy answers a plain-text 500 for a post whose ingress replica died with it, and a
    connection may break mid-request: the frame is sent again with the same Idempotency-Key (the service
    replays it if it was learned), within the retry budget (issue 34, item 5)."""
    plain = httpx.Response(500, text="Internal Server Error", headers={"Content-Type": "text/plain"})
    service = Scripted([plain, httpx.ReadError("connection reset"), (200, {})])
    bodies, sleeps, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert service.bodies == [bodies[0]] * 3 + bodies[1:] and sleeps == [1.0, 2.0]  # the backoff
    first = service.idempotency_keys[0]
    assert first and service.idempotency_keys[:3] == [first] * 3  # the same key on every attempt
    others = service.idempotency_keys[3:]
    assert None not in others and len({first, *others}) == len(ROUTE)  # each frame its own key
    assert summary.retries == 2 and summary.frames == len(ROUTE) and summary.errors == 0


def test_a_proxys_html_502_and_504_are_retried_with_the_frames_key(tmp_path):
    """nginx in front of a restarting service answers an HTML 502, or 504 for a slow upstream: like its
    plain 500, the frame is sent again with its key (the typed client does the same)."""
    page = {"Content-Type": "text/html"}
    service = Scripted([httpx.Response(502, text="<html>Bad Gateway</html>", headers=page),
                        httpx.Response(504, text="<html>Gateway Timeout</html>", headers=page), (200, {})])
    bodies, _, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert service.bodies == [bodies[0]] * 3 + bodies[1:]
    assert service.idempotency_keys[:3] == [service.idempotency_keys[0]] * 3 and service.idempotency_keys[0]
    assert summary.retries == 2 and summary.frames == len(ROUTE) and summary.errors == 0


def portal_page() -> httpx.Response:
    return httpx.Response(200, text="<html>Please log in</html>", headers={"Content-Type": "text/html"})


def test_a_captive_portals_200_page_is_no_answer_the_frame_is_sent_again_with_its_key(tmp_path):
    """An outside probe: a portal that never forwarded a frame answered 200 text/html; the ingest counted
    it answered (errors 0, exit 0) and the frame was never stored. A 200 that is not the service's answer
    (a page, JSON without an answer's members) is a reply lost on the way: sent again with the key."""
    cut = httpx.Response(200, content=b'{"learned": tr', headers={"Content-Type": "application/json"})
    service = Scripted([portal_page(), cut, (200, {})])
    bodies, _, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert service.bodies == [bodies[0]] * 3 + bodies[1:]
    assert service.idempotency_keys[:3] == [service.idempotency_keys[0]] * 3
    assert summary.retries == 2 and summary.errors == 0 and summary.frames == len(ROUTE)
    # the retries spent on pages: the ingest stops with an error, not a frame counted answered
    service = Scripted([portal_page()] * (poster.MAX_RETRIES + 1))
    _, _, run = _ingest(tmp_path / "spent", service)
    with pytest.raises(poster.IngestError, match="not the service's answer") as e:
        anyio.run(run)
    assert e.value.summary.errors == 1 and e.value.summary.frames == 0


def test_a_portals_page_for_the_map_stops_the_ingest_before_any_post(tmp_path):
    posts = []

    async def portal(request: httpx.Request) -> httpx.Response:
        if request.method == "POST":
            posts.append(request)
        return portal_page()

    _, _, run = _ingest(tmp_path, portal)
    with pytest.raises(poster.IngestError, match="map 'm': 200"):
        anyio.run(run)
    assert posts == []


def test_the_services_own_500_is_not_retried(tmp_path):
    """A problem+json 500 is the service's answer (a bug), not a proxy's: the ingest stops there."""
    problem = httpx.Response(500, json={"title": "Internal error", "detail": "quote request id r"},
                             headers={"Content-Type": "application/problem+json"})
    service = Scripted([problem])
    _, sleeps, run = _ingest(tmp_path, service)
    with pytest.raises(poster.IngestError, match=r"frame frame_0000\.png: 500 Internal error"):
        anyio.run(run)
    assert len(service.bodies) == 1 and sleeps == []
    service = Scripted([httpx.Response(500, text="down", headers={"Content-Type": "text/plain"})]
                       * (poster.MAX_RETRIES + 1))
    _, sleeps, run = _ingest(tmp_path / "again", service)
    with pytest.raises(poster.IngestError, match="500"):  # a proxy's 500 too, once the retries are spent
        anyio.run(run)
    assert len(service.bodies) == poster.MAX_RETRIES + 1 and len(set(service.idempotency_keys)) == 1


def test_a_refused_frame_is_counted_and_the_ingest_goes_on_but_a_refused_map_stops_it(tmp_path):
    service = Scripted([(200, {}), (422, {})])
    bodies, _, run = _ingest(tmp_path, service)
    summary = anyio.run(run)
    assert summary.errors == 1 and summary.frames == len(ROUTE) - 1 and service.bodies == bodies
    service = Scripted([(200, {}), (404, {})])
    _, _, run = _ingest(tmp_path / "again", service)
    with pytest.raises(poster.IngestError, match=r"frame frame_0001\.jpg: 404"):
        anyio.run(run)
    assert len(service.bodies) == 2


def test_a_map_made_by_another_ingest_between_the_look_and_the_creation_is_used(tmp_path):
    """Two ingests started on one new map both find it missing; the second's creation is answered 409
    `map-exists` and it posts into the map the first made, as if it had found it (it stopped there)."""
    service = Scripted()
    made = []

    async def racing(request: httpx.Request) -> httpx.Response:
        if request.method == "GET" and not made:
            return httpx.Response(404, json={"type": "urn:cortexloc:problem:map-not-found", "detail": "d"},
                                  headers={"Content-Type": "application/problem+json"})
        if request.url.path == "/v1/maps":
            made.append(json.loads(request.content))
            return httpx.Response(409, json={"type": "urn:cortexloc:problem:map-exists", "detail": "d"},
                                  headers={"Content-Type": "application/problem+json"})
        return await service(request)

    bodies, _, run = _ingest(tmp_path, racing)
    summary = anyio.run(run)
    assert made == [{"map_id": "m"}] and not summary.created_map
    assert service.bodies == bodies and summary.frames == len(ROUTE) and summary.errors == 0
    # Another 409 (the map limit), or a map-exists whose map is not served after all, still stops it.
    full = httpx.Response(409, json={"type": "urn:cortexloc:problem:map-limit", "title": "Map limit",
                                     "detail": "d"}, headers={"Content-Type": "application/problem+json"})

    async def limited(request: httpx.Request) -> httpx.Response:
        made.clear()
        return await racing(request) if request.method == "GET" else full

    _, _, run = _ingest(tmp_path / "again", limited)
    with pytest.raises(poster.IngestError, match="409 Map limit"):
        anyio.run(run)

    async def unlisted(request: httpx.Request) -> httpx.Response:
        made.clear()  # every look finds no map
        return await racing(request)

    _, _, run = _ingest(tmp_path / "unlisted", unlisted)
    with pytest.raises(poster.IngestError, match="map 'm': 409"):
        anyio.run(run)


@pytest.mark.parametrize("map_id", ["..", "m/..", "m/snapshots", "", "m\n"])
def test_a_map_id_that_is_not_one_is_refused_before_any_request(tmp_path, map_id):
    """The id goes into the path as it is: "m/.." would post to another resource."""
    service = Scripted()
    _, _, run = _ingest(tmp_path, service, map_id=map_id)
    with pytest.raises(poster.IngestError, match="is not a map id"):
        anyio.run(run)
    assert service.keys == set()  # nothing was sent


def test_the_cli_refuses_a_map_id_that_is_not_one_before_it_starts_the_service(tmp_path):
    """Found in review: in process, the refusal came after the service had started (its encoder loaded,
    its maps replayed, its directory locked), with exit 1; like `repair`, it is a usage error first."""
    (tmp_path / "frames").mkdir()
    out = CliRunner().invoke(cli.app, ["ingest", str(tmp_path / "frames"), "--map", "m/..",
                                       "--data-dir", str(tmp_path / "data")])
    assert out.exit_code == 2 and "is not a map id" in out.output, out.output
    assert not (tmp_path / "data").exists()  # no service started on it


def test_registering_ingest_keeps_cv2_out_of_the_cli_start():
    """`cortexloc serve` sets OpenCV's pixel guard before cv2 is imported; the readers import cv2 lazily."""
    import subprocess
    import sys

    code = ("import sys, service.cli; "
            "print(sorted(m for m in ('cv2', 'torch', 'rosbags') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=Path(__file__).resolve().parents[3])
    assert out.stdout.strip() == "[]"


def test_a_file_that_cannot_be_read_is_counted_and_the_folder_ingest_goes_on(tmp_path, monkeypatch):
    """An outside probe: one unreadable file (no permission, an I/O error) or one deleted after the folder
    was listed ended the ingest with a traceback and no summary, frames already learned."""
    write_folder(tmp_path / "frames")
    names = sorted(p.name for p in (tmp_path / "frames").iterdir())
    source = open_source(tmp_path / "frames")
    (tmp_path / "frames" / names[3]).unlink()  # gone between the listing and its read
    read_bytes = Path.read_bytes

    def failing(self: Path) -> bytes:
        if self.name == names[5]:
            raise PermissionError(13, "Permission denied")
        return read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", failing)
    got: list[poster.Record] = []

    async def run() -> poster.Summary:
        async with poster.in_process_client(Settings(data_dir=tmp_path / "a", log_level="WARNING")) as client:
            return await poster.ingest(client, source, poster.Options(map_id="farm"), on_record=got.append)

    summary = anyio.run(run)
    assert [r.status for r in got] == [200] * 3 + [0] + [200] + [0] + [200] * (len(ROUTE) - 6)
    assert "No such file" in got[3].answer["detail"] and "Permission denied" in got[5].answer["detail"]
    assert summary.errors == 2 and summary.frames == summary.learned == len(ROUTE) - 2
    assert f"posted {len(ROUTE) - 2}/{len(ROUTE)} frames" in summary.text()
