"""Smaller defects at the HTTP edge (issue 11, items 10 and 11): a client that goes away mid-upload,
the 405's `Allow`, repeated query parameters, unparseable requests below the app, and what /readyz says
about snapshots a recovery skipped."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

import pytest
import uvicorn
from fastapi.testclient import TestClient

from service.errors import PROBLEM_MEDIA_TYPE
from service.limits import HEAD_MAX_BYTES
from service.routes import MAX_QUERY_PARAMETERS
from service.server import BACKLOG, FD_RESERVE, ProblemHttpToolsProtocol, connection_cap
from tests.service.helpers import frame, make_app, make_client, post, served


@pytest.fixture
def client(tmp_path):
    with make_client(tmp_path / "data") as c:
        yield c


def _gone_mid_body(c: TestClient, method: str, path: str, ctype: str, part: bytes, declared: int) -> int:
    """Send the headers and `part` of a `declared`-byte body, then disconnect; the status the app sent."""
    sent: list[int] = []

    async def call() -> None:
        messages = [{"type": "http.request", "body": part, "more_body": True}, {"type": "http.disconnect"}]

        async def receive() -> dict:
            return messages.pop(0) if messages else {"type": "http.disconnect"}

        async def send(message: dict) -> None:
            if message["type"] == "http.response.start":
                sent.append(message["status"])

        headers = [(b"content-type", ctype.encode()), (b"content-length", str(declared).encode())]
        await c.app({"type": "http", "asgi": {"version": "3.0", "spec_version": "2.3"}, "http_version": "1.1",
                     "method": method, "scheme": "http", "path": path, "raw_path": path.encode(),
                     "root_path": "", "query_string": b"", "headers": headers, "client": ("127.0.0.1", 1),
                     "server": ("testserver", 80)}, receive, send)

    c.portal.call(call)
    return sent[0]


def test_a_client_gone_mid_upload_is_no_server_error(client, caplog):
    body = frame(1)
    with caplog.at_level(logging.INFO):
        status = _gone_mid_body(client, "POST", "/v1/maps/default/observations", "image/png", body[:100],
                                len(body))
        json_status = _gone_mid_body(client, "POST", "/v1/maps", "application/json", b'{"map_id": ',
                                     200)
    assert status == json_status == 499
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    assert not [r for r in caplog.records if r.exc_info]
    assert any("went away" in r.getMessage() and r.levelno == logging.INFO for r in caplog.records)
    metrics = client.get("/metrics").text
    assert 'route="/v1/maps/{map_id}/observations",status="499"} 1.0' in metrics
    assert 'route="/v1/maps",status="499"} 1.0' in metrics
    assert 'status="500"' not in metrics
    assert client.app.state.registry.get("default").store.count() == 0


@pytest.mark.parametrize(("method", "path", "allowed"), [
    ("PUT", "/v1/maps/default", ["DELETE", "GET", "HEAD", "PATCH"]),
    ("PATCH", "/v1/maps", ["GET", "HEAD", "POST"]),
    ("DELETE", "/v1/maps/default/snapshots", ["GET", "HEAD", "POST"]),
])
def test_405_lists_every_method_of_the_path(client, method, path, allowed):
    r = client.request(method, path)
    assert r.status_code == 405 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    assert r.headers["allow"] == ", ".join(allowed) and r.json()["allowed"] == allowed


@pytest.mark.parametrize("path", [
    "/healthz", "/readyz", "/metrics", "/v1/maps", "/v1/maps/default", "/v1/maps/default/memory",
    "/v1/maps/default/loop-closures/export?format=csv", "/ui/", "/openapi.json", "/v1/maps/nothing-here"])
def test_every_get_answers_head_with_its_status_and_headers_and_no_body(client, path):
    """RFC 9110 §9.3.2: HEAD is GET without the body; FastAPI alone answers it 405."""
    got, head = client.get(path), client.head(path)
    assert head.status_code == got.status_code and head.content == b""
    same = ("content-type", "x-content-type-options", "cache-control")
    if path != "/metrics":  # its text counts the requests before it
        same += ("content-length",)
    assert {k: head.headers.get(k) for k in same} == {k: got.headers.get(k) for k in same}
    assert head.headers.get("x-request-id") not in (None, got.headers.get("x-request-id"))


def test_head_is_counted_as_head_and_a_post_only_path_refuses_it(client):
    assert client.head("/healthz").status_code == 200
    r = client.head("/v1/maps/default/streams/default/reset")
    assert r.status_code == 405 and r.content == b"" and r.headers["allow"] == "POST"
    metrics = client.get("/metrics").text
    assert 'method="HEAD",route="/healthz",status="200"} 1.0' in metrics
    assert 'method="HEAD",route="/v1/maps/{map_id}/streams/{stream:path}/reset",status="405"} 1.0' in metrics
    assert client.app.state.registry.get("default").store.count() == 0


def test_repeated_query_parameters_are_refused(client):
    r = client.post("/v1/maps/default/observations?learn=false&learn=true&top_k=1&top_k=1",
                    content=frame(1), headers={"Content-Type": "image/png"})
    assert r.status_code == 400 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    body = r.json()
    assert body["type"].endswith("invalid-parameter")
    assert [e["name"] for e in body["errors"]] == ["learn", "top_k"]
    assert client.app.state.registry.get("default").store.count() == 0
    assert client.get("/v1/maps/default/observations?after_seq=0&limit=5").status_code == 200  # distinct


@pytest.mark.parametrize("path", ["observations?limit={}", "observations?after_seq={}", "observations/{}",
                                  "loop-closures?after={}", "recent?limit={}"])
@pytest.mark.parametrize("value", ["1_0", "%201", "1%20", "+1", "01"])
def test_an_integer_parameter_is_plain_decimal_digits(client, path, value):
    """Found from outside: `limit=1_0` returned 10 rows and `/observations/1_0` read seq 10 (Python's int()
    reads underscores, signs, spaces and leading zeros); each now names the parameter."""
    post(client, frame(1))
    path = "/v1/maps/default/" + path
    r = client.get(path.format(value))
    assert r.status_code == 400 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE), r.text
    assert r.json()["type"].endswith("invalid-parameter") and "plain decimal digits" in r.json()["detail"]
    assert r.json()["errors"][0]["message"].startswith("must be an integer")  # its words, not pydantic's
    assert client.get(path.format("1")).status_code == 200


@pytest.mark.parametrize("query", ["Learn=false", "learning=false", "learn%20=false", "topk=1",
                                   "learn=false&top_k=1&lmit=2"])
def test_an_unknown_query_parameter_is_refused_and_learns_nothing(client, query):
    """Found from outside: a misspelt `learn=false` was ignored, so the frame was LEARNED (200)."""
    r = client.post(f"/v1/maps/default/observations?{query}", content=frame(1),
                    headers={"Content-Type": "image/png"})
    assert r.status_code == 400 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE), r.text
    body = r.json()
    unknown = [field.split("=")[0].replace("%20", " ") for field in query.split("&")
               if field.split("=")[0] not in ("learn", "top_k")]
    assert body["type"].endswith("invalid-parameter") and [e["name"] for e in body["errors"]] == unknown
    # the accepted names come from the route's declarations, not a list kept by hand
    assert body["accepted"] == sorted(["learn", "top_k", "stream", "label", "encoding", "width", "height",
                                       "metadata"])
    assert client.app.state.registry.get("default").store.count() == 0


@pytest.mark.parametrize("path", ["/v1/maps?foo=1", "/v1/maps/default/observations?lmit=1",
                                  "/v1/maps/default/loop-closures/export?fmt=g2o", "/metrics?x=1",
                                  "/v1/maps/default/recent?limit=1&strem=a"])
def test_every_route_refuses_unknown_query_parameters(client, path):
    """GET `.../export?fmt=g2o` answered CSV; each read route now names the stray parameter."""
    r = client.get(path)
    assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter"), r.text
    stray = path.rsplit("&", 1)[-1].rsplit("?", 1)[-1].split("=")[0]
    assert [e["name"] for e in r.json()["errors"]] == [stray] and stray in r.json()["detail"]
    assert client.get(path.split("?")[0] + ("?format=jsonl" if "export" in path else "")).status_code == 200


@pytest.mark.parametrize("coding", ["gzip", "br", "gzip, identity", "x-unknown"])
def test_a_compressed_body_is_415_naming_the_coding_and_stores_nothing(client, coding):
    """Found from outside: a gzip body was read as sent, so a frame was refused as 'not an image' and a
    map's options as bad JSON: the wrong reason. The service decodes no content coding (RFC 7694)."""
    import gzip

    r = client.post("/v1/maps/default/observations", content=gzip.compress(frame(1)),
                    headers={"Content-Type": "image/png", "Content-Encoding": coding})
    created = client.post("/v1/maps", content=gzip.compress(b'{"map_id": "lab"}'),
                          headers={"Content-Type": "application/json", "Content-Encoding": coding})
    for reply in (r, created):
        assert reply.status_code == 415 and reply.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
        assert reply.headers["accept-encoding"] == "identity"
        assert reply.json()["allowed"] == ["identity"] and "Content-Encoding" in reply.json()["detail"]
    assert client.app.state.registry.get("default").store.count() == 0
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]
    plain = client.post("/v1/maps/default/observations", content=frame(1),
                        headers={"Content-Type": "image/png", "Content-Encoding": "identity"})
    assert plain.status_code == 200, plain.text


@pytest.mark.parametrize("ctype", ["text/plain", None, "application/x-www-form-urlencoded"])
def test_json_sent_as_another_type_is_415_saying_which_type_and_changes_nothing(client, ctype):
    """Found from outside: `curl -d` sends form type, and the 400 said the body was 'no object'."""
    headers = {"Content-Type": ctype} if ctype else {}
    created = client.post("/v1/maps", content=b'{"map_id": "lab"}', headers=headers)
    patched = client.patch("/v1/maps/default", content=b'{"revisit_threshold": 0.5}', headers=headers)
    for reply in (created, patched):
        assert reply.status_code == 415 and reply.json()["allowed"] == ["application/json"], reply.text
        assert "application/json" in reply.json()["detail"]
    assert [m["map_id"] for m in client.get("/v1/maps").json()["maps"]] == ["default"]
    assert client.get("/v1/maps/default").json()["revisit_threshold"] != 0.5
    assert client.post("/v1/maps", json={"map_id": "lab"}).status_code == 201
    assert client.post("/v1/maps/default/snapshots").status_code == 201  # no body: no type needed


def test_a_body_sent_to_a_route_that_takes_none_is_refused_and_changes_nothing(client):
    """Found from outside: `POST .../repair` with `{"dry_run": true}` ignored the body and ran the repair
    (200, rows re-made, closures retracted); `POST .../snapshots` dropped `{"label": "x"}` silently. A
    route whose options are query parameters takes no body; an empty one (`{}`, whitespace) says nothing."""
    post(client, frame(1), stream="s", learn="true")
    snapshots = client.get("/v1/maps/default/snapshots").json()["snapshots"]
    for body in (b'{"dry_run": true}', b"not json at all", b'{"label": "x"}', b"[]", b"x" * 10_000):
        for path in ("/v1/maps/default/repair", "/v1/maps/default/snapshots",
                     "/v1/maps/default/streams/s/reset"):
            r = client.post(path, content=body, headers={"Content-Type": "application/json"})
            assert r.status_code == 400, (path, body[:20], r.text)
            assert r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
            assert r.json()["errors"] == [{"location": "body", "name": "", "message": "no body is accepted"}]
    assert client.get("/v1/maps/default/snapshots").json()["snapshots"] == snapshots
    for empty in (b"{}", b" \n", b""):
        assert client.post("/v1/maps/default/snapshots", content=empty,
                           headers={"Content-Type": "application/json"}).status_code == 201
    assert client.post("/v1/maps/default/repair", json={}).status_code == 200


def test_the_probes_endpoints_take_a_stray_parameter(client):
    """A liveness or readiness check that adds a cache-busting parameter must not fail a healthy service."""
    assert client.get("/healthz?cache=1").status_code == 200
    assert client.get("/readyz?cache=1").status_code == 200


def test_a_query_value_that_is_not_utf8_is_refused_and_stores_nothing(client):
    """Found from outside: `label=caf%E9` and metadata with `caf%E9` were stored as `caf\ufffd`."""
    r = client.post("/v1/maps/default/observations?metadata=%7B%22name%22%3A%22caf%E9%22%7D&label=caf%E9"
                    "&stream=ok", content=frame(1), headers={"Content-Type": "image/png"})
    assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter"), r.text
    assert [e["name"] for e in r.json()["errors"]] == ["metadata", "label"]
    assert client.app.state.registry.get("default").store.count() == 0
    # UTF-8 escapes (and a '+' for a space) are still read as sent
    r = client.post("/v1/maps/default/observations?label=caf%C3%A9+au+lait", content=frame(1),
                    headers={"Content-Type": "image/png"})
    assert r.status_code == 200, r.text
    assert client.get(f"/v1/maps/default/observations/{r.json()['seq']}").json()["label"] == "café au lait"


def test_a_query_of_many_names_is_refused_at_once_and_its_reply_echoes_few(client):
    """Found in review: the rules run before the write key, and a 16 KiB query of thousands of distinct
    names cost seconds of CPU (a quadratic count) and its 400 listed every name back."""
    many = "&".join(f"n{i}=1" for i in range(MAX_QUERY_PARAMETERS + 1))
    r = client.post(f"/v1/maps/default/observations?{many}", content=frame(1),
                    headers={"Content-Type": "image/png"})
    assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter"), r.text
    assert str(MAX_QUERY_PARAMETERS) in r.json()["detail"] and len(r.content) < 1000
    unknown = "&".join(f"n{i}=1" for i in range(MAX_QUERY_PARAMETERS - 1))  # under the cap: all unknown
    r = client.get(f"/v1/maps/default/recent?{unknown}")
    assert r.status_code == 400 and len(r.json()["errors"]) == 10, r.text
    assert f"and {MAX_QUERY_PARAMETERS - 1 - 10} more" in r.json()["detail"]
    assert client.app.state.registry.get("default").store.count() == 0


def test_two_idempotency_keys_are_refused(client):
    """Found from outside: two `Idempotency-Key` headers were accepted and the first bound the reply."""
    headers = [("Content-Type", "image/png"), ("Idempotency-Key", "key-aaaaaaaa"),
               ("Idempotency-Key", "key-bbbbbbbb")]
    r = client.post("/v1/maps/default/observations", content=frame(1), headers=headers)
    assert r.status_code == 400 and r.json()["type"].endswith("invalid-parameter"), r.text
    assert r.json()["errors"] == [{"location": "header", "name": "idempotency-key",
                                   "message": "given more than once"}]
    assert client.app.state.registry.get("default").store.count() == 0
    # neither key was bound: each alone is a first post
    for key in ("key-aaaaaaaa", "key-bbbbbbbb"):
        r = client.post("/v1/maps/default/observations", content=frame(1),
                        headers={"Content-Type": "image/png", "Idempotency-Key": key})
        assert r.status_code == 200 and "idempotent-replayed" not in r.headers, r.text


def test_readyz_reports_the_damaged_snapshots_recovery_skipped(tmp_path):
    with make_client(tmp_path / "data") as c:
        for p in range(3):
            c.post("/v1/maps/default/observations", content=frame(p), headers={"Content-Type": "image/png"})
        sid = c.post("/v1/maps/default/snapshots").json()["snapshot_id"]
        snap = c.app.state.registry.get("default").snapshot_dir(sid)
        assert "skipped_snapshots" not in c.get("/readyz").json()["checks"]["maps"]["maps"]["default"]
    data = bytearray((snap / "memory.npz").read_bytes())
    data[len(data) // 2] ^= 1
    (snap / "memory.npz").write_bytes(bytes(data))
    with make_client(tmp_path / "data", snapshot_every=0) as c:  # no shutdown snapshot hides it
        r = c.get("/readyz")
        assert r.status_code == 200
        check = r.json()["checks"]["maps"]
        entry = check["maps"]["default"]
        assert entry["state"] == "ready"
        assert [s["snapshot_id"] for s in entry["skipped_snapshots"]] == [sid]
        assert "checksum" in entry["skipped_snapshots"][0]["reason"]
        assert check["status"] == "warn" and "default" in check["warning"]
        assert any("damaged snapshot" in w for w in r.json()["warnings"])


def test_unparseable_requests_get_problem_json_from_the_protocol():
    # uvicorn answers these itself, before the app; `cortexloc serve` runs it with ProblemHttpToolsProtocol.
    async def app(scope, receive, send):  # reached only by the pipelined case's valid first request
        if scope["type"] == "http" and scope["path"] == "/a":
            await send({"type": "http.response.start", "status": 200, "headers": []})
            await send({"type": "http.response.body", "body": b""})
            return
        raise AssertionError("the app saw an unparseable request")

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, http=ProblemHttpToolsProtocol,
                                           lifespan="off", log_level="critical"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not server.started and time.monotonic() < deadline:
            time.sleep(0.02)
        # Headers past the 16 KiB limit still unfinished (a whole one reaches the app, which refuses it:
        # test_oversized_headers_are_refused_however_they_arrive), a malformed header line, a malformed
        # request line.
        def answer(raw: bytes) -> tuple[bytes, dict]:
            with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
                conn.sendall(raw)
                reply = b""
                while chunk := conn.recv(65536):
                    reply += chunk
            head, _, body = reply.partition(b"\r\n\r\n")
            assert b"content-type: application/problem+json" in head.lower()
            problem = json.loads(body)
            assert problem["request_id"] in head.decode()
            return head, problem

        for raw in (b"GET / HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 40_000,
                    b"GET / HTTP/1.1\r\nHost: x\r\nno colon in this header\r\n\r\n",
                    b"GET /\x00 HTTP/1.1\r\nHost: x\r\n\r\n",
                    b"G@T / HTTP/1.1\r\nHost: x\r\n\r\n",  # not a method token at all: malformed
                    # CONNECT, a method llhttp knows (its peek raised an upgrade: no answer, a review)
                    b"CONNECT x:443 HTTP/1.1\r\nHost: x\r\nno colon\r\n\r\n"):
            head, problem = answer(raw)
            assert head.startswith(b"HTTP/1.1 400 ")
            assert problem["type"] == "urn:cortexloc:problem:invalid-parameter" and problem["status"] == 400
            assert problem["errors"]
        # a pipelined request's bad header, its read starting inside its head, is no unknown method
        with socket.create_connection(("127.0.0.1", port), timeout=10) as conn:
            conn.sendall(b"GET /a HTTP/1.1\r\nHost: x\r\n\r\nGET /b HTTP/1.1\r\nX-A: a")
            time.sleep(0.3)
            conn.sendall(b"b c\r\nno colon\r\n\r\n")
            reply = b""
            while chunk := conn.recv(65536):
                reply += chunk
        assert b"HTTP/1.1 400 " in reply and b"method-not-implemented" not in reply, reply[-600:]
        # a well-formed token that is no method llhttp knows (methods are case-sensitive): RFC 9110 §9.1
        for method in (b"FOO", b"get", b"BREW"):
            head, problem = answer(method + b" /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 501 "), head
            assert problem["type"] == "urn:cortexloc:problem:method-not-implemented"
            assert problem["method"] == method.decode() and method.decode() in problem["detail"]
    finally:
        server.should_exit = True
        thread.join(timeout=10)


def test_connections_past_the_cap_are_answered_503_and_closed_as_they_open(tmp_path):
    # An outside probe: idle connections past the descriptor limit made accepts fail (a traceback each,
    # a log flood) and the maps' own file operations too, so committed posts were answered 500.
    import httpx

    app = make_app(tmp_path / "var", max_connections=3)
    with served(app, http=ProblemHttpToolsProtocol) as base:
        port = int(base.rsplit(":", 1)[1])
        idle = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        try:
            time.sleep(0.2)  # the server has taken all three
            with socket.create_connection(("127.0.0.1", port), timeout=10) as extra:
                reply = b""
                while chunk := extra.recv(65536):  # it is closed after the answer
                    reply += chunk
            head, _, body = reply.partition(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 503 ") and b"retry-after: 1" in head.lower()
            problem = json.loads(body)
            assert problem["type"] == "urn:cortexloc:problem:overloaded" and problem["max_connections"] == 3
        finally:
            for sock in idle:
                sock.close()
        time.sleep(0.2)
        assert httpx.get(f"{base}/healthz", timeout=10).status_code == 200  # room again


def test_the_cap_fits_the_descriptor_limit_and_serve_raises_a_low_soft_limit(monkeypatch, tmp_path):
    import resource

    from service import cli
    from service.cli.serve import _file_limit

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    low = FD_RESERVE + 100
    if hard != resource.RLIM_INFINITY and hard < 2 * low:
        pytest.skip(f"the hard descriptor limit ({hard}) leaves no room to test")
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (low, hard))
        connection_cap.cache_clear()
        assert connection_cap(1000) == 100  # what the limit leaves after the service's own files
        assert _file_limit(low) == low  # raised to fit, up to the hard limit
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] == low + FD_RESERVE
        resource.setrlimit(resource.RLIMIT_NOFILE, (low, hard))
        monkeypatch.setattr(uvicorn, "run", lambda app, **kw: None)
        monkeypatch.setenv("CORTEXLOC_DATA_DIR", str(tmp_path))
        monkeypatch.setenv("CORTEXLOC_MAX_CONNECTIONS", "300")
        cli.serve(host=None, port=0, data_dir=None)
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] >= 300 + FD_RESERVE
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
        connection_cap.cache_clear()


def test_the_serve_command_uses_the_problem_protocol(monkeypatch, tmp_path):
    from service import cli

    seen = {}
    monkeypatch.setattr(uvicorn, "run", lambda app, **kw: seen.update(kw))
    monkeypatch.setenv("CORTEXLOC_DATA_DIR", str(tmp_path))
    cli.serve(host=None, port=0, data_dir=None)
    assert seen["http"] is ProblemHttpToolsProtocol
    assert seen["loop"] == "asyncio"  # not uvloop, which the `ray` extra installs (issue 26)
    assert seen["backlog"] == BACKLOG  # a burst of accepts stays within the descriptors kept (FD_RESERVE)


def test_oversized_headers_are_refused_however_they_arrive(client):
    # The protocol refuses a head over the limit as it parses it; under the test client (no protocol)
    # the app refuses it the same way.
    r = client.get("/healthz", headers={"X-Big": "a" * HEAD_MAX_BYTES})
    assert r.status_code == 400 and r.headers["content-type"].startswith(PROBLEM_MEDIA_TYPE)
    assert r.json()["type"].endswith("invalid-parameter") and str(HEAD_MAX_BYTES) in r.json()["detail"]
    assert client.get("/healthz", headers={"X-Big": "a" * (HEAD_MAX_BYTES - 1000)}).status_code == 200


def test_requests_answered_before_routing_are_counted_under_their_route(tmp_path):
    # A 413 is answered by the upload-limit middleware before routing; its route template is still found
    # (the routes of included routers are searched too).
    with make_client(tmp_path / "data", max_upload_bytes=100) as c:
        r = c.post("/v1/maps/default/observations", content=frame(1), headers={"Content-Type": "image/png"})
        assert r.status_code == 413
        assert 'route="/v1/maps/{map_id}/observations",status="413"} 1.0' in c.get("/metrics").text


def test_a_transfer_coding_other_than_chunked_is_501_and_stores_nothing(tmp_path):
    """(Found from outside.) `Transfer-Encoding: gzip, chunked` was dechunked and read as sent: a gzipped
    frame was refused as 'not an image', and a plain one under a coding it does not carry was learned.
    The server decodes no transfer coding but chunked (RFC 9112 §6.1: 501)."""
    import gzip

    app = make_app(tmp_path / "var")
    with served(app, http=ProblemHttpToolsProtocol) as base:
        port = int(base.rsplit(":", 1)[1])

        def send(coding: str, body: bytes) -> tuple[int, dict]:
            with socket.create_connection(("127.0.0.1", port), timeout=20) as s:
                s.sendall(f"POST /v1/maps/default/observations HTTP/1.1\r\nHost: t\r\nContent-Type: image/png"
                          f"\r\nConnection: close\r\nTransfer-Encoding: {coding}\r\n\r\n".encode()
                          + b"%x\r\n" % len(body) + body + b"\r\n0\r\n\r\n")
                raw = b""
                while chunk := s.recv(65536):
                    raw += chunk
            head, _, rest = raw.partition(b"\r\n\r\n")
            return int(head.split(b" ", 2)[1]), json.loads(rest) if rest.startswith(b"{") else {}

        for coding, body in (("gzip, chunked", gzip.compress(frame(1))), ("gzip, chunked", frame(1)),
                             ("x-unknown, chunked", frame(1))):
            status, problem = send(coding, body)
            assert status == 501, (coding, problem)
            assert problem["type"].endswith("transfer-coding-not-implemented"), problem
            assert problem["allowed"] == ["chunked"]
        assert app.state.registry.get("default").store.count() == 0
        assert send("chunked", frame(1))[0] == 200
