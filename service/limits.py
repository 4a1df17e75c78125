"""Request body limits, before routing and parsing (docs/design/service.md §3).

`UploadLimitMiddleware` is a pure ASGI middleware (no `BaseHTTPMiddleware`, which would buffer and run
the app in another task):

- a `Content-Length` above the limit is answered 413 `payload-too-large` at once, without reading a
  byte of the body;
- otherwise the body is counted as it arrives (chunked uploads too): the chunk that crosses the limit is
  not handed to the app, which sees `BodyTooLargeError` from `receive()`; whatever the app then does, its
  response is replaced by the 413 (a route that already started streaming its reply is only cut off).

The limit is `CORTEXLOC_MAX_UPLOAD_BYTES`, read per request from `app.state.settings`, and 64 KiB for
JSON bodies (`application/json` or `application/*+json`). 413 responses carry `Connection: close`
because the rest of the body is left unread.

The request line and headers are limited to `HEAD_MAX_BYTES` (16 KiB, h11's own limit, which
`cortexloc serve` passes to uvicorn): h11 enforces it only while a head is incomplete, so a larger head
that arrives in one read would get through; here it is refused whatever the segmentation, with the
same 400 `invalid-parameter` that `service.server.ProblemH11Protocol` writes in the other case.
"""

from __future__ import annotations

from starlette.datastructures import Headers
from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import problem_response
from service.settings import Settings

__all__ = [
    "HEAD_MAX_BYTES", "JSON_MAX_BYTES", "BodyTooLargeError", "UploadLimitMiddleware", "body_limit",
    "head_bytes",
]

JSON_MAX_BYTES = 64 * 1024
HEAD_MAX_BYTES = 16 * 1024


class BodyTooLargeError(Exception):
    """Raised from `receive()` once the body passed its limit."""

    def __init__(self, max_bytes: int, received_bytes: int) -> None:
        super().__init__(f"request body exceeds {max_bytes} bytes")
        self.max_bytes = max_bytes
        self.received_bytes = received_bytes


def _is_json(content_type: str | None) -> bool:
    if not content_type:
        return False
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


def body_limit(scope: Scope, headers: Headers) -> int:
    """The byte limit of this request's body."""
    settings = getattr(getattr(scope.get("app"), "state", None), "settings", None)
    limit = int(getattr(settings, "max_upload_bytes", Settings.model_fields["max_upload_bytes"].default))
    if _is_json(headers.get("content-type")):
        limit = min(limit, JSON_MAX_BYTES)
    return limit


def head_bytes(scope: Scope) -> int:
    """Bytes of the request line and headers as sent (`METHOD target HTTP/x.y`, `name: value`, CRLFs)."""
    target = len(scope.get("raw_path") or scope["path"].encode()) + len(scope.get("query_string") or b"")
    line = len(scope.get("method", "")) + target + 1 + 12
    return line + sum(len(k) + len(v) + 4 for k, v in scope.get("headers", ())) + 2


def _too_large(scope: Scope, max_bytes: int, received: int, *, declared: bool) -> JSONResponse:
    what = f"Content-Length: {received}" if declared else f"cut off after {received} bytes"
    detail = f"request body is larger than the limit of {max_bytes} bytes ({what})"
    return problem_response(Request(scope), 413, "payload-too-large", detail, headers={"Connection": "close"},
                            max_bytes=max_bytes, received_bytes=received)


class UploadLimitMiddleware:
    """Pure ASGI body limit; see the module docstring."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

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
        limit = body_limit(scope, headers)
        declared = headers.get("content-length")
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
                await _too_large(scope, limit, length, declared=True)(scope, receive, send)
                return

        received = 0
        exceeded: BodyTooLargeError | None = None
        app_started = False

        async def limited_receive() -> Message:
            nonlocal received, exceeded
            if exceeded is not None:
                raise exceeded
            message = await receive()
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
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception:
            if exceeded is None or app_started:
                raise
        if exceeded is not None and not app_started:
            await _too_large(scope, limit, exceeded.received_bytes, declared=False)(scope, receive, send)
