"""Retries, idempotency keys and request shapes, against `httpx.MockTransport` (no server): what is sent
again, after how long, with which key; what is never sent again."""

from __future__ import annotations

import asyncio
import json
from datetime import datetime, timezone

import httpx
import numpy as np
import pytest

from cortexloc_client import (
    AsyncClient,
    Client,
    ConflictError,
    CortexlocError,
    InvalidResponseError,
    RetryPolicy,
    ServerError,
    ServiceUnavailableError,
    aio,
    client,
)
from cortexloc_client.errors import retry_after_seconds

OBSERVATION = {"map_id": "lab", "stream": "default", "learned": True, "observation_id": "o-1", "seq": 1,
               "sequence": {"step": 0, "active_columns": 8, "predicted_columns": 0, "bursting_columns": 8,
                            "winner_cells": 8},
               "matches": [], "timings_ms": {"total": 1.0},
               "versions": {"api": "v1", "code": "0", "encoder": "e", "weights": "random",
                            "projection": "sha256:0", "map_seq": 1}}
SNAPSHOT = {"snapshot_id": "s1", "seq": 1, "kind": "manual", "created_at": "now", "bytes": 1,
            "manifest_sha256": "0"}
OVERLOADED = {"type": "urn:cortexloc:problem:overloaded", "title": "Overloaded", "status": 503,
              "detail": "the encoder queue is full", "instance": "/v1/maps/lab/observations",
              "request_id": "r-1", "retry_after": 2}
JPEG = b"\xff\xd8\xff\xe0 not really a jpeg"


class Script:
    """A MockTransport handler answering from a list (the last answer repeats); records the requests."""

    def __init__(self, *answers: httpx.Response | Exception) -> None:
        self.answers = list(answers)
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        answer = self.answers.pop(0) if len(self.answers) > 1 else self.answers[0]
        if isinstance(answer, Exception):
            raise answer
        return answer

    def keys(self) -> list[str | None]:
        return [r.headers.get("Idempotency-Key") for r in self.requests]


def busy(retry_after: str | None = "2") -> httpx.Response:
    headers = {"Retry-After": retry_after} if retry_after is not None else {}
    return httpx.Response(503, json=OVERLOADED,
                          headers={**headers, "Content-Type": "application/problem+json"})


@pytest.fixture
def waits(monkeypatch: pytest.MonkeyPatch) -> list[float]:
    """The client's sleeps, recorded instead of slept (sync and async)."""
    out: list[float] = []

    async def asleep(s: float) -> None:
        out.append(s)

    monkeypatch.setattr(client, "sleep", out.append)
    monkeypatch.setattr(aio, "sleep", asleep)
    return out


def make(script: Script, **kw) -> Client:
    return Client("http://cortexloc.test", transport=httpx.MockTransport(script), **kw)


def test_a_503_is_retried_after_retry_after_with_the_same_idempotency_key(waits) -> None:
    script = Script(busy("2"), busy("3"), httpx.Response(200, json=OBSERVATION))
    answer = make(script).observe("lab", JPEG)
    assert answer.seq == 1
    assert waits == [2.0, 3.0]
    keys = script.keys()
    assert len(keys) == 3 and keys[0] and len(set(keys)) == 1
    assert all(r.content == JPEG and r.headers["Content-Type"] == "image/jpeg" for r in script.requests)


def test_a_post_a_restore_rolled_back_is_sent_again_with_the_same_key(waits) -> None:
    """409 `map-restored`: the service kept nothing of the post (a restore rolled it back before it was
    durable), so it is sent again, as after a 503; another 409 is raised at once."""
    rolled_back = httpx.Response(409, json={"type": "urn:cortexloc:problem:map-restored", "status": 409,
                                            "detail": "d", "map_id": "lab"},
                                 headers={"Content-Type": "application/problem+json"})
    script = Script(rolled_back, httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG).seq == 1
    keys = script.keys()
    assert len(keys) == 2 and keys[0] and len(set(keys)) == 1
    exists = httpx.Response(409, json={"type": "urn:cortexloc:problem:map-exists", "status": 409,
                                       "detail": "d"}, headers={"Content-Type": "application/problem+json"})
    script = Script(exists)
    with pytest.raises(ConflictError):
        make(script).create_map("lab")
    assert len(script.requests) == 1


def test_each_post_has_its_own_key_unless_given_or_turned_off(waits) -> None:
    script = Script(httpx.Response(200, json=OBSERVATION))
    c = make(script)
    c.observe("lab", JPEG)
    c.observe("lab", JPEG)
    c.observe("lab", JPEG, idempotency_key="frame-0042")
    make(script, idempotency_keys=False).observe("lab", JPEG)
    first, second, given, off = script.keys()
    assert first and second and first != second
    assert (given, off) == ("frame-0042", None)


MAP = {"map_id": "map-0123456789ab", "created_at": "now", "state": "ready", "encoder": "e",
       "params": {"tm": {}, "slsbh": {}, "seed": 42}, "projection_sha256": "0", "observations": 0,
       "last_seq": 0, "streams": []}


def test_a_map_creation_whose_reply_was_lost_is_sent_again_with_its_key(waits) -> None:
    # The service answers a keyed creation's retry with the map its first try made (200, replayed), so a
    # reply lost in transport no longer leaves the caller with an error and a map it does not know of.
    replayed = httpx.Response(200, json=MAP, headers={"Idempotent-Replayed": "true"})
    script = Script(httpx.ReadTimeout("lost"), replayed)
    assert make(script).create_map().map_id == "map-0123456789ab"
    keys = script.keys()
    assert len(keys) == 2 and keys[0] and len(set(keys)) == 1
    assert [json.loads(r.content) for r in script.requests] == [{}, {}]
    script = Script(httpx.ReadTimeout("lost"), replayed)
    make(script).create_map("lab", seed=3, idempotency_key="lab-create-1")
    assert script.keys() == ["lab-create-1", "lab-create-1"]
    script = Script(httpx.ReadTimeout("lost"), replayed)  # without keys: it may have been made, not resent
    with pytest.raises(httpx.ReadTimeout):
        make(script, idempotency_keys=False).create_map()
    assert script.keys() == [None]


def test_waits_are_capped_and_attempts_bounded(waits) -> None:
    script = Script(busy("3600"))
    with pytest.raises(ServiceUnavailableError) as e:
        make(script, retry=RetryPolicy(attempts=3, max_wait_s=5.0)).create_snapshot("lab")
    assert len(script.requests) == 3 and waits == [5.0, 5.0]
    assert (e.value.status, e.value.slug, e.value.retry_after) == (503, "overloaded", 3600.0)
    assert e.value.extra["retry_after"] == 2 and e.value.request_id == "r-1"


def test_without_retry_after_the_waits_back_off(waits) -> None:
    script = Script(busy(None), busy("soon"), busy(None), httpx.Response(200, json=SNAPSHOT))
    make(script, retry=RetryPolicy(backoff_s=0.5)).create_snapshot("lab")
    assert waits == [0.5, 1.0, 2.0]


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "-5", "NaN", "soon"])
def test_a_retry_after_that_is_no_wait_is_ignored_for_the_backoff(waits, value: str) -> None:
    # An outside probe: `Retry-After: nan` reached `time.sleep(nan)` (an untyped ValueError out of the
    # client; the ROS node's `Event.wait(nan)` returns at once: a tight retry loop), and -5 waited 0.
    script = Script(busy(value), busy(value), httpx.Response(201, json=SNAPSHOT))
    make(script, retry=RetryPolicy(backoff_s=0.5)).create_snapshot("lab")
    assert waits == [0.5, 1.0]
    script = Script(busy(value))
    with pytest.raises(ServiceUnavailableError) as e:
        make(script, retry=RetryPolicy(attempts=1)).create_snapshot("lab")
    assert e.value.retry_after is None


def test_a_retry_after_http_date_is_waited_for_capped_as_seconds_are(waits) -> None:
    now = datetime(2030, 1, 1, 12, 0, 0, tzinfo=timezone.utc)
    assert retry_after_seconds("Tue, 01 Jan 2030 12:00:07 GMT", now) == 7.0
    assert retry_after_seconds("Tue, 01 Jan 2030 11:00:00 GMT", now) == 0.0  # past: now
    assert retry_after_seconds("Tue, 01 Jan 2030 12:00:03 -0000", now) == 3.0
    assert retry_after_seconds("3", now) == 3.0 and retry_after_seconds("0", now) == 0.0
    assert retry_after_seconds("Tue, 99 Foo 2030", now) is None and retry_after_seconds(None) is None
    # far off, as a proxy may say: waited for at most max_wait_s, as "3600" is
    script = Script(busy("Wed, 21 Oct 2099 07:28:00 GMT"), httpx.Response(201, json=SNAPSHOT))
    make(script, retry=RetryPolicy(max_wait_s=5.0)).create_snapshot("lab")
    assert waits == [5.0]


def test_other_refusals_and_readiness_are_not_retried(waits) -> None:
    script = Script(httpx.Response(409, json={**OVERLOADED, "type": "urn:cortexloc:problem:map-full",
                                              "status": 409}))
    with pytest.raises(CortexlocError) as e:
        make(script).observe("lab", JPEG)
    assert e.value.status == 409 and len(script.requests) == 1
    script = Script(busy("1"))
    with pytest.raises(ServiceUnavailableError):
        make(script).ready()
    assert len(script.requests) == 1 and waits == []


def test_a_failed_map_is_raised_at_once_and_a_recovering_one_retried(waits) -> None:
    failed = {**OVERLOADED, "type": "urn:cortexloc:problem:map-unavailable", "state": "failed",
              "state_reason": "memory-budget", "detail": "map 'lab' is failed (memory-budget): raise ..."}
    script = Script(httpx.Response(503, json=failed, headers={"Content-Type": "application/problem+json"}))
    with pytest.raises(ServiceUnavailableError) as e:
        make(script).observe("lab", JPEG)
    assert len(script.requests) == 1 and waits == [] and e.value.extra["state"] == "failed"
    recovering = {**failed, "state": "recovering", "state_reason": None}
    script = Script(httpx.Response(503, json=recovering, headers={"Content-Type": "application/problem+json",
                                                                 "Retry-After": "1"}),
                    httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG).seq == 1 and waits == [1.0]


def test_transport_failures_are_retried_only_where_safe(waits) -> None:
    reset = httpx.ReadError("connection reset")
    refused = httpx.ConnectError("connection refused")
    # A GET, and an observation with its key, may be sent again after the connection broke mid-way.
    script = Script(reset, httpx.Response(200, json={"snapshots": [SNAPSHOT]}))
    assert make(script).list_snapshots("lab")[0].snapshot_id == "s1"
    assert len(script.requests) == 2
    script = Script(reset, httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG).seq == 1
    assert len(script.requests) == 2 and len(set(script.keys())) == 1
    # A POST without a key may have been done: never sent twice...
    script = Script(reset)
    with pytest.raises(httpx.ReadError):
        make(script).create_snapshot("lab")
    assert len(script.requests) == 1
    script = Script(reset)
    with pytest.raises(httpx.ReadError):
        make(script, idempotency_keys=False).observe("lab", JPEG)
    assert len(script.requests) == 1
    # ...unless it never left: a refused connection is retried for any request.
    script = Script(refused, httpx.Response(201, json=SNAPSHOT))
    assert make(script).create_snapshot("lab").snapshot_id == "s1"
    assert len(script.requests) == 2


def proxy_500() -> httpx.Response:
    """What Ray Serve's proxy answers for a request whose ingress replica died with it."""
    return httpx.Response(500, text="Internal Server Error", headers={"Content-Type": "text/plain"})


def internal_500() -> httpx.Response:
    """The service's own 500: problem+json `internal-error`."""
    return httpx.Response(500, json={**OVERLOADED, "type": "urn:cortexloc:problem:internal-error",
                                     "title": "Internal error", "status": 500},
                          headers={"Content-Type": "application/problem+json"})


def test_a_proxys_plain_500_is_retried_for_a_keyed_post_with_the_same_key(waits) -> None:
    script = Script(proxy_500(), proxy_500(), httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG, idempotency_key="frame-0001").seq == 1
    assert script.keys() == ["frame-0001"] * 3 and waits == [0.5, 1.0]  # the backoff: no Retry-After
    assert all(r.content == JPEG for r in script.requests)
    # ...with the key the client made, too; and a read (idempotent) likewise.
    script = Script(proxy_500(), httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG).seq == 1
    assert len(script.requests) == 2 and script.keys()[0] and len(set(script.keys())) == 1
    script = Script(proxy_500(), httpx.Response(200, json={"snapshots": [SNAPSHOT]}))
    assert make(script).list_snapshots("lab")[0].snapshot_id == "s1" and len(script.requests) == 2


def test_an_unkeyed_post_or_the_services_own_500_is_not_retried(waits) -> None:
    # Without a key the post may have been learned before the replica died: never sent twice.
    script = Script(proxy_500(), httpx.Response(200, json=OBSERVATION))
    with pytest.raises(ServerError) as e:
        make(script, idempotency_keys=False).observe("lab", JPEG)
    assert e.value.status == 500 and e.value.problem is None and len(script.requests) == 1
    script = Script(proxy_500(), httpx.Response(201, json=SNAPSHOT))
    with pytest.raises(ServerError):
        make(script).create_snapshot("lab")
    assert len(script.requests) == 1
    # A problem+json 500 is the service's answer (a bug, quote its request id), not a lost request.
    script = Script(internal_500(), httpx.Response(200, json=OBSERVATION))
    with pytest.raises(ServerError) as e:
        make(script).observe("lab", JPEG)
    assert e.value.slug == "internal-error" and e.value.request_id == "r-1" and len(script.requests) == 1
    assert waits == []


def test_the_async_client_retries_a_proxys_500_alike(waits) -> None:
    script = Script(proxy_500(), httpx.Response(200, json=OBSERVATION))

    async def post(**kw) -> str | None:
        async with AsyncClient("http://cortexloc.test", transport=httpx.MockTransport(script), **kw) as c:
            return (await c.observe("lab", JPEG)).observation_id

    assert asyncio.run(post()) == "o-1"
    assert waits == [0.5] and len(script.requests) == 2 and len(set(script.keys())) == 1
    script = Script(proxy_500(), httpx.Response(200, json=OBSERVATION))
    with pytest.raises(ServerError):
        asyncio.run(post(idempotency_keys=False))
    assert len(script.requests) == 1


def proxy_page(status: int) -> httpx.Response:
    """nginx's (or a load balancer's) HTML page for an upstream that failed or was slow."""
    return httpx.Response(status, text=f"<html><body><h1>{status}</h1></body></html>",
                          headers={"Content-Type": "text/html"})


@pytest.mark.parametrize("status", [502, 503, 504])
def test_a_proxys_html_502_503_or_504_is_retried_where_safe_sync_and_async(waits, status: int) -> None:
    script = Script(proxy_page(status), proxy_page(status), httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG, idempotency_key="frame-0001").seq == 1
    assert script.keys() == ["frame-0001"] * 3 and waits == [0.5, 1.0]
    script = Script(proxy_page(status), httpx.Response(200, json={"snapshots": [SNAPSHOT]}))
    assert make(script).list_snapshots("lab")[0].snapshot_id == "s1" and len(script.requests) == 2
    # the service may have done the work behind the proxy: a post without a key is never sent twice
    for unsafe in (lambda c: c.observe("lab", JPEG), lambda c: c.create_snapshot("lab")):
        script = Script(proxy_page(status), httpx.Response(201, json=SNAPSHOT))
        with pytest.raises(ServerError if status != 503 else ServiceUnavailableError) as e:
            unsafe(make(script, idempotency_keys=False))
        assert e.value.status == status and e.value.problem is None and len(script.requests) == 1
    script = Script(proxy_page(status), httpx.Response(200, json=OBSERVATION))

    async def post() -> str | None:
        async with AsyncClient("http://cortexloc.test", transport=httpx.MockTransport(script)) as c:
            return (await c.observe("lab", JPEG)).observation_id

    assert asyncio.run(post()) == "o-1" and len(script.requests) == 2 and len(set(script.keys())) == 1


def test_a_reply_that_is_not_a_problem_still_raises(waits) -> None:
    script = Script(httpx.Response(502, text="<html>Bad Gateway</html>"))
    with pytest.raises(ServerError) as e:
        make(script, retry=RetryPolicy(attempts=1)).get_map("lab")
    assert e.value.status == 502 and e.value.slug is None and e.value.problem is None
    assert "Bad Gateway" in e.value.detail


#: Success replies that are not the route's answer, as (Content-Type, body): a proxy's or captive portal's
#: page sent with 200, JSON cut short, JSON without the members the route answers.
UNREADABLE = {"html": ("text/html", b"<html><body>502 upstream hiccup</body></html>"),
              "truncated": ("application/json", b'{"map_id": "lab", "stre'),
              "missing-fields": ("application/json", b'{"map_id": "lab"}')}


@pytest.mark.parametrize("kind", UNREADABLE)
def test_a_success_reply_that_is_not_the_answer_is_a_typed_error_retried_where_safe(waits, kind: str) -> None:
    # An outside probe: pydantic's ValidationError came out of the client untyped, and ended the ROS node's
    # poster thread for good. Now an InvalidResponseError (a CortexlocError), and a reply lost on the way
    # as far as retries go: a keyed post is sent again with its key (answered from the store if learned).
    content_type, body = UNREADABLE[kind]

    def reply() -> httpx.Response:
        return httpx.Response(200, content=body, headers={"Content-Type": content_type})

    script = Script(reply(), reply(), httpx.Response(200, json=OBSERVATION))
    assert make(script).observe("lab", JPEG, idempotency_key="frame-0001").seq == 1
    assert script.keys() == ["frame-0001"] * 3 and waits == [0.5, 1.0]
    script = Script(reply(), httpx.Response(200, json={"snapshots": [SNAPSHOT]}))  # a read, likewise
    assert make(script).list_snapshots("lab")[0].snapshot_id == "s1" and len(script.requests) == 2
    # spent retries: raised typed, with the status and what the body began with
    script = Script(reply())
    with pytest.raises(CortexlocError) as e:
        make(script, retry=RetryPolicy(attempts=2)).observe("lab", JPEG)
    assert isinstance(e.value, InvalidResponseError) and len(script.requests) == 2
    assert (e.value.status, e.value.slug, e.value.problem) == (200, None, None)
    assert e.value.excerpt == body.decode() and repr(e.value.excerpt) in e.value.detail
    assert e.value.content_type == content_type and e.value.reason
    assert str(e.value).startswith("200 invalid response: a reply the client cannot read (")
    # what may have been done and has no key is never sent again: a post without a key, a new snapshot
    for unsafe in (lambda c: c.observe("lab", JPEG), lambda c: c.create_snapshot("lab")):
        script = Script(reply(), httpx.Response(201, json=SNAPSHOT))
        with pytest.raises(InvalidResponseError):
            unsafe(make(script, idempotency_keys=False))
        assert len(script.requests) == 1
    script = Script(reply(), httpx.Response(200, json=OBSERVATION))

    async def post() -> str | None:
        async with AsyncClient("http://cortexloc.test", transport=httpx.MockTransport(script)) as c:
            return (await c.observe("lab", JPEG)).observation_id

    assert asyncio.run(post()) == "o-1" and len(script.requests) == 2 and len(set(script.keys())) == 1


def test_a_snapshot_download_still_streams_through_the_retry_loop(waits, tmp_path) -> None:
    script = Script(httpx.ReadError("reset"), httpx.Response(200, content=b"tar" * 1000, headers=TAR))
    path = make(script).download_snapshot("lab", "s1", tmp_path / "lab.tar")
    assert path.read_bytes() == b"tar" * 1000 and len(script.requests) == 2


TAR = {"Content-Type": "application/x-tar"}
PORTAL = b"<html><body>Please log in to the hotel network</body></html>"


def portal() -> httpx.Response:
    return httpx.Response(200, content=PORTAL, headers={"Content-Type": "text/html; charset=utf-8"})


#: each byte route, its real reply (the service's media type, `charset` and case aside), and what it gives
BYTE_ROUTES = {
    "csv": (lambda c, d: c.export_loop_closures("lab", "csv"), "text/csv; charset=utf-8", b"stamp,seq\n"),
    "jsonl": (lambda c, d: c.export_loop_closures("lab", "jsonl"), "application/jsonl", b'{"id": 1}\n'),
    "g2o": (lambda c, d: c.export_loop_closures("lab", "g2o"), "Text/Plain; charset=utf-8", b"EDGE_SE3:QUAT"),
    "thumbnail": (lambda c, d: c.thumbnail("lab", 1), "image/jpeg", b"\xff\xd8\xff"),
    "recent-thumbnail": (lambda c, d: c.recent_thumbnail("lab", 1), "image/jpeg", b"\xff\xd8\xff"),
    "download": (lambda c, d: c.download_snapshot("lab", "s1", d / "lab.tar").read_bytes(),
                 "application/x-tar", b"tar" * 100),
}


@pytest.mark.parametrize("route", BYTE_ROUTES)
def test_a_byte_routes_reply_of_another_type_is_a_page_not_the_answer(waits, tmp_path, route: str) -> None:
    # An outside probe: a captive portal's 200 HTML page came back as the export, the thumbnail, and as the
    # snapshot's .tar on disk, with no error and no retry, where a JSON route raised InvalidResponseError.
    ask, media_type, body = BYTE_ROUTES[route]
    script = Script(portal(), httpx.Response(200, content=body, headers={"Content-Type": media_type}))
    assert ask(make(script), tmp_path) == body and len(script.requests) == 2 and waits == [0.5]
    script, spent = Script(portal()), tmp_path / "spent"
    spent.mkdir()
    with pytest.raises(InvalidResponseError) as e:
        ask(make(script, retry=RetryPolicy(attempts=2)), spent)
    assert len(script.requests) == 2 and e.value.content_type.startswith("text/html")
    assert e.value.reason == f"Content-Type 'text/html', not {media_type.split(';')[0].lower()!r}"
    assert not list(spent.iterdir())  # no page saved as a snapshot, nor its .part


def problem_404(slug: str) -> httpx.Response:
    return httpx.Response(404, json={"type": f"urn:cortexloc:problem:{slug}", "status": 404, "detail": "d"},
                          headers={"Content-Type": "application/problem+json"})


DELETES = {"map": (lambda c: c.delete_map("lab"), "map-not-found"),
           "snapshot": (lambda c: c.delete_snapshot("lab", "s1"), "snapshot-not-found")}
LOST = {"reset": lambda: httpx.ReadError("connection reset"),
        "proxy-502": lambda: httpx.Response(502, text="<html>Bad Gateway</html>",
                                            headers={"Content-Type": "text/html"}),
        "portal-200": portal}


@pytest.mark.parametrize("what", DELETES)
@pytest.mark.parametrize("lost", LOST)
def test_a_delete_whose_reply_was_lost_is_done_when_its_retry_finds_nothing(waits, what, lost) -> None:
    # An outside probe: the delete reached the service and its reply was lost; the retry's 404 was raised as
    # NotFoundError although the map (the snapshot) was deleted. A delete's goal is that it is gone.
    delete, slug = DELETES[what]
    script = Script(LOST[lost](), problem_404(slug))
    assert delete(make(script)) is None and len(script.requests) == 2

    async def adelete() -> None:
        async with AsyncClient("http://cortexloc.test", transport=httpx.MockTransport(script)) as c:
            await (c.delete_map("lab") if what == "map" else c.delete_snapshot("lab", "s1"))

    script = Script(LOST[lost](), problem_404(slug))
    assert asyncio.run(adelete()) is None and len(script.requests) == 2


def test_only_its_targets_404_after_an_unsure_try_is_a_deletes_success(waits) -> None:
    # a review: any problem+json 404 counted; one that is not about the map or the snapshot (a route's
    # `not-found`) says nothing of whether the delete was done
    other = problem_404("not-found")
    script = Script(httpx.ReadError("reset"), other)
    with pytest.raises(CortexlocError) as e:
        make(script).delete_map("lab")
    assert e.value.status == 404 and len(script.requests) == 2
    # the scale-out's 503 that says the shard took the request: unsure, so the retry's 404 is done
    unknown = httpx.Response(503, json={**OVERLOADED, "type": "urn:cortexloc:problem:map-unavailable",
                                        "outcome_unknown": True},
                             headers={"Content-Type": "application/problem+json", "Retry-After": "2"})
    script = Script(unknown, problem_404("map-not-found"))
    assert make(script).delete_map("lab") is None and waits[-1] == 2.0
    # and a request that is not safe to repeat is not sent again after it
    script = Script(unknown, httpx.Response(201, json=SNAPSHOT))
    with pytest.raises(ServiceUnavailableError):
        make(script).create_snapshot("lab")
    assert len(script.requests) == 1


@pytest.mark.parametrize("first", ["none", "refused", "own-503", "proxy-404"])
def test_a_delete_of_nothing_there_is_still_not_found(waits, first: str) -> None:
    # A first try's 404, or one after tries the service surely did not do (a connection never opened, its
    # own 503 refusal), says the name was not there: NotFoundError, as before. A proxy's 404 page is no
    # answer of the service's.
    before = {"none": [], "refused": [httpx.ConnectError("refused")], "own-503": [busy("1")],
              "proxy-404": []}[first]
    last = httpx.Response(404, text="Not Found", headers={"Content-Type": "text/plain"}) \
        if first == "proxy-404" else problem_404("map-not-found")
    script = Script(*before, last)
    with pytest.raises(CortexlocError) as e:
        make(script).delete_map("lab")
    assert e.value.status == 404 and len(script.requests) == len(before) + 1


def test_the_api_key_and_the_metadata_are_sent(waits) -> None:
    script = Script(httpx.Response(200, json=OBSERVATION))
    make(script, api_key="k3y").observe("lab", JPEG, stream="robot1/cam0", label="dock",
                                        metadata={"stamp": 12.5, "pose": {"x": 1, "y": 2, "yaw": 0.5}})
    sent = script.requests[0]
    assert sent.headers["X-API-Key"] == "k3y"
    assert sent.url.params["stream"] == "robot1/cam0" and sent.url.params["label"] == "dock"
    assert json.loads(sent.url.params["metadata"]) == {"stamp": 12.5, "pose": {"x": 1, "y": 2, "yaw": 0.5}}


@pytest.mark.parametrize(("array", "colour", "encoding"), [
    (np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3), "rgb8", "rgb8"),
    (np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3), "bgr8", "bgr8"),
    (np.arange(6, dtype=np.uint8).reshape(2, 3), "rgb8", "mono8"),
    (np.arange(6, dtype=np.uint16).reshape(2, 3) * 1000, "rgb8", "mono16"),
    (np.arange(6, dtype=">u2").reshape(2, 3) * 1000, "rgb8", "mono16"),
    (np.arange(2 * 3 * 3, dtype=np.uint8).reshape(3, 2, 3).transpose(1, 0, 2), "rgb8", "rgb8"),
])
def test_an_array_is_sent_as_a_raw_frame(waits, array: np.ndarray, colour, encoding: str) -> None:
    expected = np.ascontiguousarray(array.astype("<u2") if array.dtype.itemsize == 2 else array).tobytes()
    assert _sent(array, colour) == (encoding, expected)


def _sent(array: np.ndarray, colour) -> tuple[str, bytes]:
    """(encoding, body) of the raw frame `observe` posts for a 2 x 3 `array`."""
    script = Script(httpx.Response(200, json=OBSERVATION))
    make(script).observe("lab", array, colour=colour)
    sent = script.requests[0]
    assert sent.headers["Content-Type"] == "application/octet-stream"
    params = sent.url.params
    assert (params["width"], params["height"]) == ("3", "2")
    return params["encoding"], sent.content


RGBA = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
GREY = np.arange(6, dtype=np.uint8).reshape(2, 3)


@pytest.mark.parametrize(("array", "colour", "same_as"), [
    (GREY[:, :, None], "rgb8", (GREY, "rgb8")),  # (H, W, 1): cv_bridge's mono8, OpenCV's grey
    (GREY[:, :, None].astype(">u2") * 1000, "rgb8", (GREY.astype(np.uint16) * 1000, "rgb8")),
    (RGBA, "rgb8", (RGBA[:, :, :3], "rgb8")),  # alpha dropped, the colour order kept
    (RGBA, "rgba8", (RGBA[:, :, :3], "rgb8")),  # ROS encoding names are accepted as they are
    (RGBA, "bgra8", (RGBA[:, :, :3], "bgr8")),
    (RGBA, "bgr8", (RGBA[:, :, :3], "bgr8")),
    (RGBA[:, :, :3], "bgra8", (RGBA[:, :, :3], "bgr8")),
])
def test_one_channel_and_alpha_arrays_are_sent_as_the_frame_they_show(waits, array: np.ndarray, colour,
                                                                       same_as) -> None:
    assert _sent(array, colour) == _sent(*same_as)


@pytest.mark.parametrize("array", [np.zeros((2, 3, 2), np.uint8), np.zeros((2, 3), np.float32),
                                   np.zeros((2, 3, 3), np.uint16), np.zeros((2, 3, 4), np.uint16),
                                   np.zeros((2, 3, 1, 1), np.uint8)])
def test_an_array_of_another_shape_or_type_is_refused_before_sending(waits, array: np.ndarray) -> None:
    script = Script(httpx.Response(200, json=OBSERVATION))
    with pytest.raises(ValueError, match="frame is an"):
        make(script).observe("lab", array)
    assert script.requests == []


@pytest.mark.parametrize("array", [np.zeros((0, 0, 3), np.uint8), np.zeros((32, 0), np.uint8),
                                   np.zeros((0, 5), np.uint16), np.zeros((0, 4, 1), np.uint8)])
def test_an_array_without_pixels_is_refused_before_sending(waits, array: np.ndarray) -> None:
    # Before, it was sent, and the service's 400 spoke of the query parameter `width`.
    script = Script(httpx.Response(200, json=OBSERVATION))
    with pytest.raises(ValueError, match="a frame has at least one pixel"):
        make(script).observe("lab", array)
    assert script.requests == []


def test_colour_is_checked_for_a_one_channel_array_where_it_is_ignored(waits) -> None:
    # Before, any value passed unseen beside a mono array: a typo surfaced only with the first colour frame.
    script = Script(httpx.Response(200, json=OBSERVATION))
    for bad in ("rgb", "BGR8", "yuv422"):
        with pytest.raises(ValueError, match="colour must be one of"):
            make(script).observe("lab", GREY, colour=bad)
    assert script.requests == []
    # a colour order or a mono encoding's name (`colour=msg.encoding`) is taken, and changes nothing
    for ok in ("bgr8", "mono8", "mono16"):
        assert _sent(GREY, ok) == _sent(GREY, "rgb8")


def test_the_async_client_retries_alike(waits) -> None:
    script = Script(busy("1"), httpx.ReadError("reset"), httpx.Response(200, json=OBSERVATION))

    async def post() -> str | None:
        async with AsyncClient("http://cortexloc.test", transport=httpx.MockTransport(script)) as c:
            return (await c.observe("lab", JPEG)).observation_id

    assert asyncio.run(post()) == "o-1"
    assert waits == [1.0, 1.0]  # Retry-After, then the second backoff step (0.5 x 2)
    keys = script.keys()
    assert len(keys) == 3 and keys[0] and len(set(keys)) == 1

