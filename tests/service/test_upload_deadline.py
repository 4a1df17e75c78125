"""Stalled and oversized uploads against a real uvicorn server on loopback (issue 19 items 2 and 3;
docs/design/service.md §3), with small settings so that each test runs in seconds: a half-sent body
is answered 408 and its connection closed at the deadline; uploads past the in-flight byte budget are
answered 503 before their body is read; a body over the limit gets its 413 although the client is still
sending it (a reset connection instead stopped `cortexloc ingest`)."""

from __future__ import annotations

import json
import re
import socket
import time
from collections.abc import AsyncIterator, Iterator

import anyio
import cv2
import httpx
import numpy as np
import pytest

from service.server import ProblemHttpToolsProtocol
from service.settings import ConfigError, Settings
from tests.service.helpers import frame, make_app, served

LIMIT = 100_000
DEADLINE_S = 2.0
BUDGET = 250_000  # two uploads of the largest size


@pytest.fixture
def live(tmp_path) -> Iterator[str]:
    """`cortexloc serve`'s uvicorn (its protocol and head limit) in a thread; yields the base URL."""
    app = make_app(tmp_path / "var", max_upload_bytes=LIMIT, body_timeout_s=DEADLINE_S,
                   max_inflight_upload_bytes=BUDGET)
    with served(app, http=ProblemHttpToolsProtocol) as base:
        yield base


def half_sent(base: str, declared: int, sent: int, map_id: str = "default") -> socket.socket:
    """A connection that sent the head of an observation post to `map_id` declaring `declared` bytes,
    then `sent`."""
    port = int(base.rsplit(":", 1)[1])
    sock = socket.create_connection(("127.0.0.1", port))
    head = (b"POST /v1/maps/%s/observations HTTP/1.1\r\nHost: t\r\nContent-Type: image/png\r\n"
            b"Content-Length: %d\r\n\r\n" % (map_id.encode(), declared))
    sock.sendall(head + b"\x89PNG" + b"\0" * (sent - 4))
    return sock


def answer(sock: socket.socket, timeout: float) -> tuple[bytes, bool]:
    """What the server sent until it closed the connection or `timeout` passed: (bytes, closed)."""
    sock.settimeout(timeout)
    got = b""
    try:
        while chunk := sock.recv(65536):
            got += chunk
    except TimeoutError:
        return got, False
    except ConnectionResetError:
        return got, True
    return got, True


def status_and_problem(raw: bytes) -> tuple[int, dict, str]:
    head, _, body = raw.partition(b"\r\n\r\n")
    status = int(head.split(b" ", 2)[1])
    return status, json.loads(body) if body else {}, head.decode("latin-1").lower()


def metric(base: str, line: str) -> float:
    text = httpx.get(f"{base}/metrics").text
    found = re.search("^" + re.escape(line) + r" (\S+)$", text, re.M)
    return float(found.group(1)) if found else 0.0


def test_half_sent_uploads_are_answered_408_and_closed_at_the_deadline(live):
    """Slow-loris style: the head and 1 KB of a declared 7 KB body, then nothing, on 20 connections
    (140 KB reserved: within the budget and one map's share, so only the deadline ends them)."""
    t0 = time.monotonic()
    socks = [half_sent(live, 7_000, 1_000) for _ in range(20)]
    for sock in socks:
        raw, closed = answer(sock, DEADLINE_S + 10)
        elapsed = time.monotonic() - t0
        assert closed and raw, f"still open after {elapsed:.1f} s"
        status, problem, head = status_and_problem(raw)
        assert status == 408 and problem["type"].endswith("request-timeout"), raw[:300]
        assert problem["received_bytes"] == 1_000 and problem["timeout_s"] == DEADLINE_S
        assert "connection: close" in head
        sock.close()
    assert DEADLINE_S * 0.9 <= time.monotonic() - t0 <= DEADLINE_S + 8
    assert metric(live, 'cortexloc_upload_refusals_total{reason="timeout"}') == 20
    assert metric(live, "cortexloc_upload_inflight_bytes") == 0


def test_uploads_past_the_in_flight_budget_are_503_before_their_body(live):
    # 200 KB reserved of 250, by two maps (one map may hold 150: the budget less one largest upload)
    assert httpx.post(f"{live}/v1/maps", json={"map_id": "other"}).status_code == 201
    held = [half_sent(live, LIMIT, 1_000), half_sent(live, LIMIT, 1_000, map_id="other")]
    deadline = time.monotonic() + 10  # until the server has read both heads (no fixed sleep)
    while metric(live, "cortexloc_upload_inflight_bytes") < 2 * LIMIT and time.monotonic() < deadline:
        time.sleep(0.05)
    assert metric(live, "cortexloc_upload_inflight_bytes") == 2 * LIMIT
    third = half_sent(live, LIMIT, 4)  # its body never comes: it is refused without being read
    raw, closed = answer(third, DEADLINE_S + 5)
    status, problem, head = status_and_problem(raw)
    assert closed and status == 503 and problem["type"].endswith("overloaded") and "retry-after: 1" in head
    for sock in held:  # at once, not at the deadline: the held uploads are not answered yet
        sock.setblocking(False)
        with pytest.raises(BlockingIOError):
            sock.recv(1)
        sock.setblocking(True)
    assert (problem["requested_bytes"], problem["inflight_bytes"], problem["max_inflight_bytes"]) == (
        LIMIT, 2 * LIMIT, BUDGET)
    small = httpx.post(f"{live}/v1/maps/default/observations", content=frame(1),
                       headers={"Content-Type": "image/png"})
    assert small.status_code == 200  # a small upload still fits beside them
    for sock in held:  # they time out, and their reservations go with them
        assert status_and_problem(answer(sock, DEADLINE_S + 10)[0])[0] == 408
        sock.close()
    assert metric(live, "cortexloc_upload_inflight_bytes") == 0
    assert metric(live, 'cortexloc_upload_refusals_total{reason="budget"}') == 1
    big = httpx.post(f"{live}/v1/maps/default/observations", content=frame(2) + b"\0" * (LIMIT - 30_000),
                     headers={"Content-Type": "image/png"})
    assert big.status_code != 503, big.text


def test_one_maps_largest_uploads_leave_another_map_room(live):
    """A client sending its largest bodies to one map holds at most the budget less one largest upload
    (150 of 250 KB here): its next is 503 while the budget still has room, and another map's robot gets
    in. Before, the flood took the whole budget and every other map's post was 503."""
    flood = half_sent(live, LIMIT, 1_000)
    deadline = time.monotonic() + 10
    while metric(live, "cortexloc_upload_inflight_bytes") < LIMIT and time.monotonic() < deadline:
        time.sleep(0.05)
    more = half_sent(live, LIMIT, 4)  # 200 KB for one map: within the budget, past its share
    raw, closed = answer(more, DEADLINE_S + 5)
    status, problem, head = status_and_problem(raw)
    assert closed and status == 503 and problem["type"].endswith("overloaded") and "retry-after: 1" in head
    assert (problem["map_inflight_bytes"], problem["map_share_bytes"], problem["requested_bytes"]) == (
        LIMIT, BUDGET - LIMIT, LIMIT)
    assert "this map" in problem["detail"]
    assert httpx.post(f"{live}/v1/maps", json={"map_id": "other"}).status_code == 201
    noise = np.random.default_rng(0).integers(0, 256, (120, 180, 3), dtype=np.uint8)
    robot_frame = cv2.imencode(".png", noise)[1].tobytes()
    assert 50_000 < len(robot_frame) < LIMIT  # past the budget's room had the flood held 200 KB
    assert metric(live, "cortexloc_upload_inflight_bytes") == LIMIT  # the flood still holds its upload
    robot = httpx.post(f"{live}/v1/maps/other/observations", content=robot_frame,
                       headers={"Content-Type": "image/png"})
    assert robot.status_code == 200, robot.text
    small = httpx.post(f"{live}/v1/maps/default/observations", content=frame(2),
                       headers={"Content-Type": "image/png"})
    assert small.status_code == 200  # the flooding map's own small frame still fits its share
    assert status_and_problem(answer(flood, DEADLINE_S + 10)[0])[0] == 408
    flood.close()
    assert metric(live, "cortexloc_upload_inflight_bytes") == 0


def test_with_a_key_stalled_uploads_without_it_are_401_at_once_and_hold_no_budget(tmp_path):
    # The budget is reserved by declared length (§3): stalled bodies could hold it until their deadline.
    # With a key, one that lacks it is answered without its body being waited for, so only a key
    # holder can hold the budget.
    app = make_app(tmp_path / "var", max_upload_bytes=LIMIT, body_timeout_s=30.0,
                   max_inflight_upload_bytes=BUDGET, api_key="robot-key")
    with served(app, http=ProblemHttpToolsProtocol) as base:
        stalled = []
        for _ in range(3):  # 300 KB declared in all, over the 250 KB budget: the third is no 503
            stalled.append(half_sent(base, LIMIT, 4))
            raw, _ = answer(stalled[-1], 2.0)  # far under the 30 s deadline
            assert status_and_problem(raw)[0] == 401
        assert metric(base, "cortexloc_upload_inflight_bytes") == 0  # their connections still open
        keyed = httpx.post(f"{base}/v1/maps/default/observations", content=frame(1),
                           headers={"Content-Type": "image/png", "Authorization": "Bearer robot-key"})
        assert keyed.status_code == 200, keyed.text
        for sock in stalled:
            sock.close()


@pytest.mark.parametrize("chunked", [False, True])
def test_a_body_over_the_limit_gets_its_413_while_the_client_is_still_sending(live, chunked):
    """The 12 MB frame of the issue, posted as `cortexloc ingest` posts (httpx's async client): before,
    each post ended in `ReadError` (the connection reset on the unread body), 5 times out of 5."""
    body = b"\xff\xd8\xff\xe0" + b"\0" * (12 * 2**20)

    async def chunks() -> AsyncIterator[bytes]:
        for i in range(0, len(body), 2**20):
            yield body[i:i + 2**20]

    async def posts() -> list[int | str]:
        out: list[int | str] = []
        async with httpx.AsyncClient(base_url=live, timeout=60) as c:
            for _ in range(3):
                content = chunks() if chunked else body
                try:
                    r = await c.post("/v1/maps/default/observations", content=content,
                                     headers={"Content-Type": "image/jpeg"})
                except httpx.TransportError as e:
                    out.append(repr(e))
                else:
                    assert r.json()["max_bytes"] == LIMIT, r.text
                    out.append(r.status_code)
        return out

    assert anyio.run(posts) == [413, 413, 413]
    assert metric(live, 'cortexloc_upload_refusals_total{reason="too-large"}') == 3


def test_the_budget_must_hold_one_upload_of_the_largest_size():
    with pytest.raises(ConfigError, match="CORTEXLOC_MAX_INFLIGHT_UPLOAD_BYTES"):
        Settings.from_env({"CORTEXLOC_MAX_UPLOAD_BYTES": "1000",
                           "CORTEXLOC_MAX_INFLIGHT_UPLOAD_BYTES": "999"})
    with pytest.raises(ConfigError, match="CORTEXLOC_BODY_TIMEOUT_S"):
        Settings.from_env({"CORTEXLOC_BODY_TIMEOUT_S": "0"})


@pytest.mark.parametrize("keep_alive_first", [False, True])
def test_a_head_sent_a_byte_at_a_time_is_answered_408_and_closed(live, keep_alive_first):
    """The same for the head (uvicorn bounds only idle keep-alive connections, and any byte resets that):
    on a new connection, and after a first request answered on it."""
    port = int(live.rsplit(":", 1)[1])
    sock = socket.create_connection(("127.0.0.1", port))
    if keep_alive_first:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: t\r\n\r\n")
        assert sock.recv(65536).startswith(b"HTTP/1.1 200")
    t0 = time.monotonic()
    sock.settimeout(0.25)
    raw = b""
    for byte in b"POST /v1/maps/default/observations HTTP/1.1\r\nHost: t\r\nX-Slow: " + b"a" * 200:
        if time.monotonic() - t0 > DEADLINE_S + 8:
            break
        try:
            sock.send(bytes([byte]))
            chunk = sock.recv(65536)
        except TimeoutError:
            continue
        except (BrokenPipeError, ConnectionResetError):
            break
        if not chunk:
            break
        raw += chunk
    elapsed = time.monotonic() - t0
    status, problem, head = status_and_problem(raw + answer(sock, 5)[0])
    assert status == 408 and problem["type"].endswith("request-timeout") and "connection: close" in head
    assert DEADLINE_S * 0.9 <= elapsed <= DEADLINE_S + 5
    sock.close()


def test_a_client_that_reads_none_of_its_replies_is_cut_off_at_the_deadline(live):
    """An outside probe: a client that never read its replies (here 40 pipelined GETs of /openapi.json, 5
    MB, more than the kernel's buffers take) held its connection for as long as it kept it open; a
    graceful close never ends while unsent bytes wait. Its writes stalled for the deadline, it is
    aborted."""
    port = int(live.rsplit(":", 1)[1])
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # before connecting: a small window
    sock.connect(("127.0.0.1", port))
    try:
        sock.sendall(b"GET /openapi.json HTTP/1.1\r\nHost: t\r\n\r\n" * 40)
        time.sleep(DEADLINE_S * 2.5)  # read nothing meanwhile
        got, closed = answer(sock, DEADLINE_S * 3)  # reading now: before, every reply came (then a 408)
        assert closed and got.count(b"HTTP/1.1 200 ") < 40
    finally:
        sock.close()
    assert httpx.get(f"{live}/healthz", timeout=10).status_code == 200


def test_an_answer_its_client_does_not_read_holds_no_upload_budget():
    """An outside probe: an upload's reservation was released only once its reply was sent, so clients
    that did not read their replies (a 401 or a 408 stuck behind a large reply they never took) held the
    whole budget, and every robot got 503. It is released as the answer starts: the app is done with the
    body then."""
    from service.limits import UploadLimitMiddleware

    sent_start, seen = anyio.Event(), []

    async def app(scope, receive, send):
        while (await receive()).get("more_body"):
            pass
        seen.append(mw.inflight)  # reserved while the app holds the body
        await send({"type": "http.response.start", "status": 401, "headers": []})
        await send({"type": "http.response.body", "body": b"x" * 10})

    mw = UploadLimitMiddleware(app)
    scope = {"type": "http", "method": "POST", "path": "/v1/maps/default/observations", "query_string": b"",
             "headers": [(b"content-type", b"image/png"), (b"content-length", b"1000")]}

    async def receive():
        return {"type": "http.request", "body": b"\0" * 1000, "more_body": False}

    async def send(message):
        if message["type"] == "http.response.start":
            sent_start.set()
            return
        await anyio.sleep_forever()  # the client reads nothing: the body's send never returns

    async def main() -> None:
        async with anyio.create_task_group() as tg:
            tg.start_soon(mw, scope, receive, send)
            await sent_start.wait()
            await anyio.sleep(0.1)  # the body's send waits for the client
            seen.append(mw.inflight)
            tg.cancel_scope.cancel()
        seen.append(mw.inflight)

    anyio.run(main)
    assert seen == [1000, 0, 0]


class _SlowLink(ProblemHttpToolsProtocol):
    """The protocol on a slow link: the kernel keeps tens of KiB of a reply, not loopback's megabytes,
    so a reply written at once waits in the transport while its client reads."""

    def connection_made(self, transport):  # type: ignore[override]
        transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 32 * 1024)
        super().connection_made(transport)


def test_a_client_reading_its_reply_slowly_but_steadily_is_served_whole(tmp_path):
    """A review: writes resume only near the transport's low-water mark, so a reply written at once stayed
    paused while a steady slow reader took it, and the stall deadline cut it (160 KiB/s of a 1 MiB reply,
    cut at 3 s of 6.4). A piece a timeout read is reading: the clock starts again."""
    from fastapi.responses import Response

    size = 1024 * 1024
    app = make_app(tmp_path / "var", body_timeout_s=DEADLINE_S)

    async def big() -> Response:
        return Response(b"x" * size, media_type="application/octet-stream")

    app.router.add_api_route("/big", big, methods=["GET"])
    with served(app, http=_SlowLink) as base:
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 65536)
        sock.connect(("127.0.0.1", int(base.rsplit(":", 1)[1])))
        sock.settimeout(5)
        got = b""
        try:
            sock.sendall(b"GET /big HTTP/1.1\r\nHost: t\r\n\r\n")
            while len(got) < size:  # 160 KiB a second: a piece every 0.4 s
                want = 160 * 1024
                while want > 0 and (chunk := sock.recv(min(want, 65536))):
                    got += chunk
                    want -= len(chunk)
                if want > 0:  # closed
                    break
                time.sleep(1.0)
        finally:
            sock.close()
        head, _, body = got.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 200 ") and body[:size] == b"x" * size  # (then the next head's 408)
