"""`RequestContextMiddleware` (pure ASGI, outermost): every request gets an id (a valid incoming
`X-Request-ID`, else a UUID4), echoed in the `X-Request-ID` response header and exposed to logging
(`service.request_ids.request_id_var`); an exception that escaped everything else becomes a 500
`internal-error` problem that leaks nothing (the traceback goes to the log with the request id)
(docs/design/service.md §2)."""

from __future__ import annotations

import logging

from fastapi import Request
from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import internal_error_response
from service.request_ids import REQUEST_ID_HEADER, new_request_id, request_id_var, valid_request_id

__all__ = ["RequestContextMiddleware"]

log = logging.getLogger("cortexloc.errors")


class RequestContextMiddleware:
    """Pure ASGI, outermost: request id in, `X-Request-ID` out, and the last-resort 500.

    The id is a valid incoming `X-Request-ID` (1-128 of `A-Za-z0-9._:-`), else a new UUID4; it is stored
    in `scope["state"]["request_id"]` (so `request.state.request_id`) and in `request_id_var` for logs.
    An exception that reaches this middleware before the response started is logged with its traceback
    and answered with a 500 `internal-error` carrying no internals; it is not re-raised (the server
    would log it a second time, without the request id).
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        incoming = None
        for key, value in scope.get("headers", ()):
            if key == b"x-request-id":
                incoming = value.decode("latin-1").strip()
                break
        rid = incoming if incoming and valid_request_id(incoming) else new_request_id()
        scope.setdefault("state", {})["request_id"] = rid
        token = request_id_var.set(rid)
        started = False

        async def send_with_id(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                headers = MutableHeaders(scope=message)
                if REQUEST_ID_HEADER not in headers:
                    headers[REQUEST_ID_HEADER] = rid
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        except Exception as exc:
            request = Request(scope)
            log.error("unhandled exception in %s %s", scope.get("method"), scope.get("path"), exc_info=exc)
            if started:
                raise
            await internal_error_response(request)(scope, receive, send)
        finally:
            request_id_var.reset(token)
