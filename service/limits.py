"""Request body limits, before routing and parsing (docs/design/service.md §3).

`UploadLimitMiddleware` is a pure ASGI middleware (no `BaseHTTPMiddleware`, which would buffer and run
the app in another task):

- a `Content-Length` above the limit is answered 413 `payload-too-large` before the app runs; the body
  is read and dropped first (never held) when it is at most `DRAIN_MAX_BYTES`, within the body deadline,
  so that a client still sending receives the answer instead of a reset connection (what stopped
  `cortexloc ingest` at a 12 MB frame); a larger one is answered at once, and so is one whose client
  sent `Expect: 100-continue` (curl does over 1 MiB): it waits for the server's word before sending,
  and gets the 413 instead of a 100 Continue;
- otherwise the body is counted as it arrives (chunked uploads too): the chunk that crosses the limit is
  not handed to the app, which sees `BodyTooLargeError` from `receive()`; whatever the app then does, its
  response is replaced by the 413 (a route that already started streaming its reply is only cut off);
- **deadline**: the whole body must arrive within `CORTEXLOC_BODY_TIMEOUT_S` of the request's start; a
  `receive()` past it raises `BodyTimeoutError` and the answer is 408 `request-timeout` (a half-sent
  upload no longer holds its connection and bytes for ever);
- **in-flight budget**: a request with a body reserves its declared length (a chunked one: its limit)
  until its answer starts (the app is done with the body then; a reply its client does not read holds
  no budget, and `cortexloc serve` closes its connection, `service.server`); one that would take the
  reservations of all requests past `CORTEXLOC_MAX_INFLIGHT_UPLOAD_BYTES` is answered 503 `overloaded`
  with `Retry-After` before its body is read (50 uploads of 9 MB held 450 MB before). **One map's
  share**: the requests for one map (the path's `/v1/maps/{id}/`; other paths count as one map) reserve
  at most the budget less one largest upload (`CORTEXLOC_MAX_UPLOAD_BYTES`), and never less than one
  largest upload, so a client sending its largest bodies to one map cannot take the whole budget, and
  another map's robot still gets in. With frames of a few hundred kB no map comes near it (128 MiB
  holds hundreds). It bounds one map, it is no fair share: a client with two maps can still take the
  whole budget.

The limit is `CORTEXLOC_MAX_UPLOAD_BYTES`, read per request from `app.state.settings`, for a frame (`POST
/v1/maps/{id}/observations`, the one route that takes an image), and 64 KiB for every other body and for
JSON bodies (`application/json` or `application/*+json`): every other route takes a small JSON body or
none, and a body some route reads before its key check (FastAPI parses a body before its dependencies)
can then hold no more than that. 413, 408 and 503 responses carry
`Connection: close` because the rest of the body is left unread. Metrics (`app.state.metrics`):
`cortexloc_upload_inflight_bytes` (reserved now) and `cortexloc_upload_refusals_total{reason}`
(`too-large`, `timeout`, `budget`).

A body sent with a content coding (`Content-Encoding` other than identity) is answered 415
`unsupported-media-type` with `Accept-Encoding: identity` before it is read (RFC 7694), and one with a
transfer coding other than chunked (`Transfer-Encoding: gzip, chunked`) 501
`transfer-coding-not-implemented` (RFC 9112 §6.1): the server dechunks and decodes nothing else.

The request line and headers are limited to `HEAD_MAX_BYTES` (16 KiB): the protocol `cortexloc serve`
runs (`service.server.ProblemHttpToolsProtocol`) refuses a longer head as it parses it; here it is
refused too (an app served by another server, the test client), with the same 400 `invalid-parameter`.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from typing import Any

import anyio
from starlette.datastructures import Headers
from starlette.requests import ClientDisconnect, Request
from starlette.responses import JSONResponse, StreamingResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import problem_response
from service.routing import sent_head
from service.settings import Settings

__all__ = [
    "DRAIN_MAX_BYTES",
    "HEAD_MAX_BYTES",
    "JSON_MAX_BYTES",
    "REPLY_CHUNK_BYTES",
    "BodyTimeoutError",
    "BodyTooLargeError",
    "ReadStreamingResponse",
    "UploadLimitMiddleware",
    "body_limit",
    "head_bytes",
]

log = logging.getLogger("cortexloc.service")

JSON_MAX_BYTES = 64 * 1024
HEAD_MAX_BYTES = 16 * 1024
#: A refused body up to this size is read and dropped before the 413, so the client gets the answer:
#: closing on unread bytes resets the connection, and the client loses the reply with it. Larger ones
#: (no camera frame is near it) are answered at once.
DRAIN_MAX_BYTES = 64 * 1024 * 1024


class BodyTooLargeError(Exception):
    """Raised from `receive()` once the body passed its limit."""

    def __init__(self, max_bytes: int, received_bytes: int) -> None:
        super().__init__(f"request body exceeds {max_bytes} bytes")
        self.max_bytes = max_bytes
        self.received_bytes = received_bytes


class BodyTimeoutError(ClientDisconnect):
    """Raised from `receive()` once the body-read deadline passed: from the app's side, the rest of the
    body is never coming (as with a client that went away; the middleware answers 408)."""

    def __init__(self, timeout_s: float, received_bytes: int) -> None:
        super().__init__(f"request body not received within {timeout_s:g} s")
        self.timeout_s = timeout_s
        self.received_bytes = received_bytes


def is_json(content_type: str | None) -> bool:
    """Whether a Content-Type is JSON's (`application/json`, `application/*+json`, any parameters)."""
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


def _state(scope: Scope, name: str) -> Any:
    return getattr(getattr(scope.get("app"), "state", None), name, None)


def _setting(scope: Scope, name: str) -> Any:
    """A setting of the app serving `scope` (its default before startup or without an app)."""
    return getattr(_state(scope, "settings"), name, Settings.model_fields[name].default)


#: The pieces a streamed reply is sent in (`ReadStreamingResponse`): a client must take one within
#: `CORTEXLOC_BODY_TIMEOUT_S`, so this over the timeout is the slowest reading kept (64 KiB / 60 s, about
#: 1 KiB/s; with 1 MiB pieces a robot reading steadily on a poor link was cut, a review found).
REPLY_CHUNK_BYTES = 64 * 1024


class ReadStreamingResponse(StreamingResponse):
    """A streamed reply (a snapshot download, a loop-closure export) that its client must keep reading:
    a piece (at most `REPLY_CHUNK_BYTES`) that waits `CORTEXLOC_BODY_TIMEOUT_S` for the client to take it
    ends the reply and closes the connection (`on_close` runs however it ends; uvicorn logs the reply as
    unfinished). Before, a client that stopped reading held the reply's files open for as long as it
    kept the connection: stalled downloads kept a deleted snapshot's files on disk. Not a total
    deadline: a large download on a slow link is cut only below a piece per timeout."""

    def on_close(self) -> None:
        """What the reply holds, released: sent, client gone, stalled or failed."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if sent_head(scope):  # the GET's checks ran (a snapshot's checksums): its headers, no stream
            try:
                await send({"type": "http.response.start", "status": self.status_code,
                            "headers": self.raw_headers})
                await send({"type": "http.response.body", "body": b"", "more_body": False})
            finally:
                self.on_close()
            return
        stall_s = float(_setting(scope, "body_timeout_s"))
        stalled = False

        async def read_or_cut(message: Message) -> None:
            nonlocal stalled
            with anyio.move_on_after(stall_s) as waited:
                await send(message)
            if waited.cancelled_caught:
                stalled = True
                raise ClientDisconnect(f"the client read nothing for {stall_s:g} s")

        try:
            await super().__call__(scope, receive, read_or_cut)
        except ClientDisconnect:
            if not stalled:
                raise
            # the reply started: its connection is closed with the app's return, unfinished
            log.warning("%s %s: the client read nothing for %g s; the reply is cut", scope.get("method"),
                        scope.get("path"), stall_s)
        finally:
            self.on_close()


def body_limit(scope: Scope, headers: Headers) -> int:
    """The byte limit of this request's body (the module docstring)."""
    limit = int(_setting(scope, "max_upload_bytes"))
    frame = scope.get("method") == "POST" and _FRAME_PATH.match(scope.get("path", "")) is not None
    if not frame or is_json(headers.get("content-type")):
        limit = min(limit, JSON_MAX_BYTES)
    return limit


_FRAME_PATH = re.compile(r"^/v1/maps/[^/]+/observations/?$")


def head_bytes(scope: Scope) -> int:
    """Bytes of the request line and headers as sent (`METHOD target HTTP/x.y`, `name: value`, CRLFs)."""
    target = len(scope.get("raw_path") or scope["path"].encode()) + len(scope.get("query_string") or b"")
    line = len(scope.get("method", "")) + target + 1 + 12
    return line + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ())) + 2


async def _drain(receive: Receive, max_bytes: int, deadline: float) -> None:
    """Read and drop the body (at most `max_bytes` of it, until `deadline`): nothing is held."""
    got = 0
    with anyio.move_on_after(max(deadline - anyio.current_time(), 0.0)):
        while got <= max_bytes:
            message = await receive()
            if message["type"] != "http.request":
                return
            got += len(message.get("body", b""))
            if not message.get("more_body", False):
                return


def _count(scope: Scope, reason: str) -> None:
    metrics = _state(scope, "metrics")
    if metrics is not None:
        metrics.upload_refusals.labels(reason=reason).inc()


def _too_large(scope: Scope, max_bytes: int, received: int, *, declared: bool) -> JSONResponse:
    what = f"Content-Length: {received}" if declared else f"cut off after {received} bytes"
    detail = f"request body is larger than the limit of {max_bytes} bytes ({what})"
    return problem_response(Request(scope), 413, "payload-too-large", detail, headers={"Connection": "close"},
                            max_bytes=max_bytes, received_bytes=received)


def _timed_out(scope: Scope, e: BodyTimeoutError) -> JSONResponse:
    return problem_response(Request(scope), 408, "request-timeout",
                            f"the request body did not arrive within {e.timeout_s:g} s ({e.received_bytes} "
                            "bytes came)", headers={"Connection": "close"}, timeout_s=e.timeout_s,
                            received_bytes=e.received_bytes)


def _over_budget(scope: Scope, asked: int, held: int, budget: int) -> JSONResponse:
    return problem_response(Request(scope), 503, "overloaded",
                            f"uploads in flight hold {held} bytes; this one would take {asked} more, past "
                            f"the limit of {budget}; retry shortly",
                            headers={"Retry-After": "1", "Connection": "close"}, retry_after=1,
                            requested_bytes=asked, inflight_bytes=held, max_inflight_bytes=budget)


def _map_of(scope: Scope) -> str | None:
    """The map a request is for (`/v1/maps/{id}/...`), the key of its budget share; None otherwise."""
    found = _MAP_PATH.match(scope.get("path", ""))
    return found.group(1) if found else None


_MAP_PATH = re.compile(r"^/v1/maps/([^/]+)/")


class UploadLimitMiddleware:
    """Pure ASGI body limit, deadline and in-flight budget; see the module docstring."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app
        self.inflight = 0  # bytes reserved by the requests being read or served (one event loop: no lock)
        self._held: dict[str | None, int] = {}  # of those, by map (`_map_of`)

    def _refusal(self, scope: Scope, reserve: int) -> JSONResponse | None:
        """The 503 for a request that would reserve `reserve` more bytes past the budget, or past its
        map's share of it (the module docstring); None: it fits."""
        budget = int(_setting(scope, "max_inflight_upload_bytes"))
        largest = int(_setting(scope, "max_upload_bytes"))
        share = budget - min(largest, budget - largest)
        held = self._held.get(_map_of(scope), 0)
        if self.inflight + reserve > budget:
            return _over_budget(scope, reserve, self.inflight, budget)
        if held + reserve > share:
            return problem_response(
                Request(scope), 503, "overloaded",
                f"uploads in flight to this map hold {held} bytes; this one would take {reserve} more, past "
                f"one map's share of {share} (the rest is kept for other maps); retry shortly",
                headers={"Retry-After": "1", "Connection": "close"}, retry_after=1, requested_bytes=reserve,
                inflight_bytes=self.inflight, max_inflight_bytes=budget, map_inflight_bytes=held,
                map_share_bytes=share)
        return None

    def _reserve(self, scope: Scope, key: str | None, n: int) -> None:
        self.inflight += n
        held = self._held.get(key, 0) + n
        if held:
            self._held[key] = held
        else:
            self._held.pop(key, None)
        metrics = _state(scope, "metrics")
        if metrics is not None:
            metrics.upload_inflight_bytes.set(self.inflight)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        head = head_bytes(scope)
        if head > HEAD_MAX_BYTES:
            response = problem_response(
                Request(scope), 400, "invalid-parameter",
                f"the request line and headers are {head} bytes, more than the limit of {HEAD_MAX_BYTES}",
                headers={"Connection": "close"},
                errors=[{"location": "header", "name": "", "message": f"at most {HEAD_MAX_BYTES} bytes"}])
            await response(scope, receive, send)
            return
        headers = Headers(scope=scope)
        coded = [c.strip() for v in headers.getlist("content-encoding") for c in v.split(",")
                 if c.strip() and c.strip().lower() != "identity"]
        if coded:
            # Read as sent, a gzip body is refused for its bytes (not an image, bad JSON): the wrong
            # reason. An image is compressed already, so the service decodes no content coding (RFC 7694).
            response = problem_response(
                Request(scope), 415, "unsupported-media-type",
                f"Content-Encoding {', '.join(map(repr, coded[:4]))} is not accepted: send the body "
                f"uncompressed", headers={"Accept-Encoding": "identity", "Connection": "close"},
                allowed=["identity"])
            await response(scope, receive, send)
            return
        # A transfer coding other than chunked (`gzip, chunked`): the server dechunks but decodes nothing
        # else, so the body would be judged on bytes the client did not mean (RFC 9112 §6.1: 501).
        transfer = [c.strip() for v in headers.getlist("transfer-encoding") for c in v.split(",")
                    if c.strip()]
        if any(c.lower() != "chunked" for c in transfer):
            response = problem_response(
                Request(scope), 501, "transfer-coding-not-implemented",
                f"Transfer-Encoding {', '.join(map(repr, transfer[:4]))}: only chunked is understood; send "
                "the body as it is", headers={"Connection": "close"}, allowed=["chunked"])
            await response(scope, receive, send)
            return
        limit = body_limit(scope, headers)
        timeout_s = float(_setting(scope, "body_timeout_s"))
        deadline = anyio.current_time() + timeout_s
        declared = headers.get("content-length")
        length = None
        if declared is not None:
            try:
                length = int(declared)
                if length < 0:
                    raise ValueError(declared)
            except ValueError:
                request = Request(scope)
                response = problem_response(
                    request, 400, "invalid-parameter", f"invalid Content-Length header {declared!r}",
                    headers={"Connection": "close"},
                    errors=[{"location": "header", "name": "content-length",
                             "message": "must be a non-negative integer"}])
                await response(scope, receive, send)
                return
            if length > limit:
                _count(scope, "too-large")
                # A client that asked `Expect: 100-continue` sends nothing until told to: answered at
                # once, it never uploads the body (reading it would tell the server to send 100 first).
                waits = headers.get("expect", "").lower() == "100-continue"
                if length <= DRAIN_MAX_BYTES and not waits:
                    await _drain(receive, length, deadline)
                await _too_large(scope, limit, length, declared=True)(scope, receive, send)
                return
        chunked = "chunked" in headers.get("transfer-encoding", "").lower()
        reserve = length if length is not None else (limit if chunked else 0)
        key = _map_of(scope)
        if reserve and (refusal := self._refusal(scope, reserve)) is not None:
            _count(scope, "budget")
            await refusal(scope, receive, send)
            return
        self._reserve(scope, key, reserve)
        held = reserve

        def release() -> None:
            nonlocal held
            self._reserve(scope, key, -held)
            held = 0

        try:
            await self._limited(scope, receive, send, limit, timeout_s, deadline, release)
        finally:
            release()

    async def _limited(self, scope: Scope, receive: Receive, send: Send, limit: int, timeout_s: float,
                       deadline: float, release: Callable[[], None]) -> None:
        """The app, its `receive()` cut at the limit and the deadline, its reply replaced then. The
        reservation is `release`d as the reply starts: the app is done with the body then (read, or
        never to be: a 401 before it), and a client that does not read its reply must not hold the
        budget while the reply waits for it (an outside probe: a few such connections held all of it)."""
        received = 0
        exceeded: BodyTooLargeError | BodyTimeoutError | None = None
        app_started = body_done = False

        async def limited_receive() -> Message:
            nonlocal received, exceeded, body_done
            if exceeded is not None:
                raise exceeded
            if body_done:  # waiting for a disconnect (a streamed reply): no deadline on that
                return await receive()
            try:
                with anyio.fail_after(max(deadline - anyio.current_time(), 0.0)):
                    message = await receive()
            except TimeoutError:
                exceeded = BodyTimeoutError(timeout_s, received)
                raise exceeded from None
            body_done = message["type"] != "http.request" or not message.get("more_body", False)
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    exceeded = BodyTooLargeError(limit, received)
                    raise exceeded
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal app_started
            if exceeded is not None and not app_started:
                return  # the app's reply to a cut-off body is replaced by the 413 below
            if message["type"] == "http.response.start":
                app_started = True
                release()
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception:
            if exceeded is None or app_started:
                raise
        if exceeded is None or app_started:
            return
        release()  # the body is cut off: none of it is held
        if isinstance(exceeded, BodyTimeoutError):
            _count(scope, "timeout")
            await _timed_out(scope, exceeded)(scope, receive, send)
            return
        _count(scope, "too-large")
        if not body_done:  # past the end of a body, receive() waits for the client to go away
            await _drain(receive, DRAIN_MAX_BYTES, deadline)
        await _too_large(scope, limit, exceeded.received_bytes, declared=False)(scope, receive, send)
