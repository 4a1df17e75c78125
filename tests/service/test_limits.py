"""Upload limits before routing and parsing (docs/design/service.md §3): 413 problem+json, pure ASGI."""

from __future__ import annotations

import json
from types import SimpleNamespace

import anyio
import pytest
from fastapi import Request
from fastapi.testclient import TestClient
from pydantic import BaseModel

from service.errors import PROBLEM_MEDIA_TYPE
from service.limits import DRAIN_MAX_BYTES, JSON_MAX_BYTES, ReadStreamingResponse, UploadLimitMiddleware
from service.settings import Settings
from tests.service.helpers import make_app

LIMIT = 1000


class Doc(BaseModel):
    text: str


@pytest.fixture
def app_and_calls(tmp_path):
    app = make_app(tmp_path / "data", max_upload_bytes=LIMIT)
    calls: list[str] = []

    @app.post("/test/upload")
    async def upload(request: Request) -> dict:
        calls.append("upload")
        data = await request.body()
        return {"bytes": len(data)}

    @app.post("/test/json")
    def post_json(doc: Doc) -> dict:
        calls.append("json")
        return {"chars": len(doc.text)}

    return app, calls


@pytest.fixture
def client(app_and_calls):
    with TestClient(app_and_calls[0]) as c:
        yield c


def assert_413(r, max_bytes: int) -> dict:
    assert r.status_code == 413, r.text
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert body["type"] == "urn:cortexloc:problem:payload-too-large"
    assert body["max_bytes"] == max_bytes
    assert body["received_bytes"] > max_bytes
    assert body["request_id"] == r.headers["x-request-id"]
    assert r.headers["connection"] == "close"
    return body


def test_body_within_the_limit_passes(client):
    r = client.post("/test/upload", content=b"x" * LIMIT)
    assert r.status_code == 200 and r.json() == {"bytes": LIMIT}


def test_content_length_over_the_limit_is_refused_before_the_route(client, app_and_calls):
    r = client.post("/test/upload", content=b"x" * (LIMIT + 1))
    body = assert_413(r, LIMIT)
    assert body["received_bytes"] == LIMIT + 1
    assert app_and_calls[1] == []  # the route never ran
    # before routing: an unknown path with a big body is also a 413, not a 404
    assert_413(client.post("/nowhere", content=b"x" * 5000), LIMIT)


def test_chunked_body_over_the_limit_is_cut_off(client, app_and_calls):
    def chunks():
        for _ in range(10):
            yield b"y" * 300

    r = client.post("/test/upload", content=chunks())
    assert "content-length" not in {k.lower() for k in r.request.headers}
    assert r.request.headers["transfer-encoding"] == "chunked"
    assert_413(r, LIMIT)
    assert app_and_calls[1] == ["upload"]  # the route started reading; its reply was replaced

    r = client.post("/test/upload", content=(b"z" * 100 for _ in range(10)))  # exactly the limit
    assert r.status_code == 200 and r.json() == {"bytes": 1000}


def test_json_bodies_are_limited_to_64_kib(tmp_path):
    app = make_app(tmp_path / "data")

    @app.post("/test/json")
    def post_json(doc: Doc) -> dict:
        return {"chars": len(doc.text)}

    @app.post("/test/upload")
    async def upload(request: Request) -> dict:
        return {"bytes": len(await request.body())}

    with TestClient(app) as c:
        small = json.dumps({"text": "a" * (JSON_MAX_BYTES - 100)}).encode()
        r = c.post("/test/json", content=small, headers={"content-type": "application/json"})
        assert r.status_code == 200
        big = json.dumps({"text": "a" * JSON_MAX_BYTES}).encode()
        assert_413(c.post("/test/json", content=big, headers={"content-type": "application/json"}),
                   JSON_MAX_BYTES)
        assert_413(c.post("/test/json", content=(big[i:i + 4096] for i in range(0, len(big), 4096)),
                          headers={"content-type": "application/json; charset=utf-8"}), JSON_MAX_BYTES)
        # the same size as a frame's body is read: 64 KiB applies to JSON and to every other route
        r = c.post("/v1/maps/default/observations", content=big, headers={"content-type": "image/png"})
        assert r.status_code == 415 and r.json()["type"].endswith("unsupported-media-type")  # read, sniffed
        assert_413(c.post("/test/upload", content=big, headers={"content-type": "application/octet-stream"}),
                   JSON_MAX_BYTES)


def test_limit_metrics_record_the_route(client):
    client.post("/test/upload", content=b"x" * (LIMIT + 1))
    text = client.get("/metrics").text
    assert 'cortexloc_requests_total{method="POST",route="/test/upload",status="413"} 1.0' in text


# ------------------------------------------------------------------ the middleware alone (raw ASGI)


class _State:
    settings = Settings(max_upload_bytes=LIMIT)


class _App:
    state = _State()


def _scope(headers: list[tuple[bytes, bytes]]) -> dict:
    return {"type": "http", "method": "POST", "path": "/x", "raw_path": b"/x", "query_string": b"",
            "headers": headers, "app": _App(), "scheme": "http", "server": ("test", 80), "root_path": "",
            "http_version": "1.1"}


def _run(middleware, scope, messages):
    sent: list[dict] = []
    received: list[int] = []
    queue = list(messages)

    async def receive():
        if not queue:
            raise AssertionError("receive() called after the last message")
        received.append(1)
        return queue.pop(0)

    async def send(message):
        sent.append(message)

    anyio.run(middleware, scope, receive, send)
    return sent, len(received)


def _reader_app(got: list[int]):
    async def app(scope, receive, send):
        total = 0
        while True:
            message = await receive()
            total += len(message.get("body", b""))
            got.append(total)
            if not message.get("more_body"):
                break
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": str(total).encode()})
    return app


def test_declared_length_is_refused_before_the_app_and_the_body_dropped_unheld():
    """The body is read and dropped before the 413 (a client still sending gets the answer, not a reset:
    issue 19 item 3); past DRAIN_MAX_BYTES it is not read at all."""
    async def app(scope, receive, send):  # pragma: no cover - must not run
        raise AssertionError("the app ran")

    body = [{"type": "http.request", "body": b"x" * 250_000, "more_body": i < 3} for i in range(4)]
    sent, reads = _run(UploadLimitMiddleware(app), _scope([(b"content-length", b"1000000")]), body)
    assert reads == 4 and sent[0]["status"] == 413
    assert json.loads(sent[1]["body"])["received_bytes"] == 1_000_000
    huge = str(DRAIN_MAX_BYTES + 1).encode()
    sent, reads = _run(UploadLimitMiddleware(app), _scope([(b"content-length", huge)]), body)
    assert reads == 0 and sent[0]["status"] == 413
    # a client that waits for 100 Continue is told at once: reading would have the server send it the 100
    sent, reads = _run(UploadLimitMiddleware(app), _scope([(b"content-length", b"1000000"),
                                                           (b"expect", b"100-continue")]), body)
    assert reads == 0 and sent[0]["status"] == 413


def test_chunks_are_counted_and_cut_at_the_limit():
    got: list[int] = []
    chunks = [{"type": "http.request", "body": b"a" * 400, "more_body": i < 9} for i in range(10)]
    sent, reads = _run(UploadLimitMiddleware(_reader_app(got)), _scope([]), chunks)
    assert reads == 10  # the third chunk crosses 1000 bytes; the rest is dropped before the 413
    assert got == [400, 800]  # the app never saw the chunk that crossed the limit
    assert sent[0]["status"] == 413 and len(sent) == 2
    body = json.loads(sent[1]["body"])
    assert (body["max_bytes"], body["received_bytes"]) == (LIMIT, 1200)
    assert body["instance"] == "/x"


def test_small_chunked_body_reaches_the_app():
    got: list[int] = []
    chunks = [{"type": "http.request", "body": b"a" * 250, "more_body": i < 3} for i in range(4)]
    sent, _ = _run(UploadLimitMiddleware(_reader_app(got)), _scope([]), chunks)
    assert sent[0]["status"] == 200 and sent[1]["body"] == b"1000"


def test_invalid_content_length_is_400():
    async def app(scope, receive, send):  # pragma: no cover - must not run
        raise AssertionError("the app ran")

    sent, reads = _run(UploadLimitMiddleware(app), _scope([(b"content-length", b"12abc")]), [])
    assert reads == 0 and sent[0]["status"] == 400
    assert json.loads(sent[1]["body"])["type"] == "urn:cortexloc:problem:invalid-parameter"


def test_a_body_whose_last_chunk_crosses_the_limit_is_answered_at_once():
    """Nothing is left to drop: a further receive() would wait for the client to go away (the deadline)."""
    got: list[int] = []
    chunks = [{"type": "http.request", "body": b"a" * 600, "more_body": i < 1} for i in range(2)]
    sent, reads = _run(UploadLimitMiddleware(_reader_app(got)), _scope([]), chunks)
    assert reads == 2 and sent[0]["status"] == 413


def _reply_scope(stall_s: float, spec: str) -> dict:
    state = SimpleNamespace(settings=SimpleNamespace(body_timeout_s=stall_s))
    return {"type": "http", "asgi": {"spec_version": spec}, "method": "GET", "path": "/download",
            "app": SimpleNamespace(state=state)}


class _Reply(ReadStreamingResponse):
    closed = 0

    def on_close(self) -> None:
        type(self).closed += 1


@pytest.mark.parametrize("spec", ["2.3", "2.4"])  # uvicorn's protocols say 2.3: Starlette's other path
@pytest.mark.parametrize("reads", ["stops", "slowly"])
def test_a_streamed_reply_is_cut_when_its_client_stops_reading_never_when_it_reads_slowly(reads, spec):
    """Found from outside: downloads that stopped reading held a deleted snapshot's files on disk
    open for as long as their connections stayed. A chunk the client does not take within the body
    timeout now ends the reply and releases what it holds; a reader that takes each piece in time is not
    cut, however long the whole takes."""
    sent: list[dict] = []

    async def send(message: dict) -> None:
        sent.append(message)
        if message["type"] == "http.response.body":
            await (anyio.sleep_forever() if reads == "stops" else anyio.sleep(0.05))

    async def receive() -> dict:
        await anyio.sleep_forever()
        return {}

    async def run() -> None:
        with anyio.fail_after(10):
            reply = _Reply(iter([b"a" * 10] * 4), media_type="application/x-tar")
            await reply(_reply_scope(0.3, spec), receive, send)

    _Reply.closed = 0
    anyio.run(run)
    bodies = [m for m in sent if m["type"] == "http.response.body"]
    assert _Reply.closed == 1
    assert len(bodies) == (1 if reads == "stops" else 5)  # 4 chunks and the closing empty one


def test_only_a_frame_post_takes_a_body_past_64_kib(tmp_path):
    """(From review.) Every route but the frame post takes a small JSON body or none: a large body sent
    elsewhere (a keyless PATCH is read before its key check) is 413 at once, so it never holds more than
    64 KiB of the in-flight budget."""
    with TestClient(make_app(tmp_path / "data", api_key="k")) as c:
        big = b"\0" * (JSON_MAX_BYTES + 1)
        for method, path in (("PATCH", "/v1/maps/default"), ("POST", "/v1/maps/default/snapshots"),
                             ("POST", "/v1/maps/default/streams/s/reset")):
            r = c.request(method, path, content=big, headers={"Content-Type": "application/octet-stream"})
            assert r.status_code == 413 and r.json()["max_bytes"] == JSON_MAX_BYTES, (method, path, r.text)
        frame_post = c.post("/v1/maps/default/observations", content=big,
                            headers={"Content-Type": "image/png", "Authorization": "Bearer k"})
        assert frame_post.status_code == 415  # read whole and sniffed (not an image): no 413 for a frame
