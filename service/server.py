"""What `cortexloc serve` runs uvicorn with, below the app: the HTTP/1.1 protocol.

uvicorn answers a request it cannot parse (a malformed request line, or a request line plus
headers larger than h11's incomplete-event limit, `service.limits.HEAD_MAX_BYTES`) itself, before the
app sees anything, with a text/plain 400. `ProblemH11Protocol` is uvicorn's h11 protocol with only
that answer replaced by the service's problem+json (docs/design/service.md §2), so every error has one shape.
(uvicorn picks httptools when it is installed; it is not a dependency here, and `serve` names this
protocol explicitly.)

It also bounds how long a request's head may take: a connection that has not completed a request head
within `CORTEXLOC_BODY_TIMEOUT_S` of opening (or of its previous reply) is answered 408
`request-timeout` and closed. uvicorn bounds only an idle keep-alive connection (5 s, reset by any byte),
so a client sending its headers a byte at a time would otherwise hold the connection for ever (the body
is bounded by `service.limits`, docs/design/service.md §3).
"""

from __future__ import annotations

import asyncio
import json

import h11
from uvicorn.protocols.http.h11_impl import DEFAULT_MAX_INCOMPLETE_EVENT_SIZE, H11Protocol

from service.errors import PROBLEM_MEDIA_TYPE, problem_body
from service.request_ids import REQUEST_ID_HEADER, new_request_id
from service.settings import Settings

__all__ = ["ProblemH11Protocol"]


class ProblemH11Protocol(H11Protocol):
    """uvicorn's h11 protocol; unparseable requests get a 400 `invalid-parameter` problem+json, and a head
    that does not arrive in time a 408 (see the module docstring)."""

    _head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._await_head()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._await_head()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        super().connection_lost(exc)

    def _await_head(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        settings = getattr(getattr(self.config.app, "state", None), "settings", None)
        timeout = float(getattr(settings, "body_timeout_s", Settings.model_fields["body_timeout_s"].default))
        self._head_timer = self.loop.call_later(timeout, self._head_timed_out, self.cycle, timeout)

    def _head_timed_out(self, cycle: object, timeout: float) -> None:
        """No request head since the timer was set (`cycle` is still the latest, and answered)."""
        if self.transport.is_closing() or self.cycle is not cycle:
            return
        if cycle is not None and not getattr(cycle, "response_complete", True):
            return  # a request is being served
        rid = new_request_id()
        detail = f"no complete request head within {timeout:g} s"
        body = json.dumps(problem_body(408, "request-timeout", detail, instance=f"urn:uuid:{rid}",
                                       request_id=rid, timeout_s=timeout, received_bytes=0)).encode()
        # Written as bytes: h11 sends no response to a request it has not seen.
        self.transport.write(b"HTTP/1.1 408 Request Timeout\r\ncontent-type: " + PROBLEM_MEDIA_TYPE.encode()
                             + b"\r\ncontent-length: %d\r\nconnection: close\r\n" % len(body)
                             + REQUEST_ID_HEADER.lower().encode() + b": " + rid.encode() + b"\r\n\r\n" + body)
        self.transport.close()

    def send_400_response(self, msg: str) -> None:
        limit = self.config.h11_max_incomplete_event_size or DEFAULT_MAX_INCOMPLETE_EVENT_SIZE
        rid = new_request_id()
        detail = (f"the request could not be parsed as HTTP/1.1: a malformed request line or header, or a "
                  f"request line and headers larger than {limit} bytes")
        # The path is unknown (the request line may be what failed), so the instance names the occurrence.
        body = json.dumps(problem_body(400, "invalid-parameter", detail, instance=f"urn:uuid:{rid}",
                                       request_id=rid, errors=[{"location": "header", "name": "",
                                                                "message": msg}])).encode()
        headers = [(b"content-type", PROBLEM_MEDIA_TYPE.encode()),
                   (b"content-length", str(len(body)).encode()), (b"connection", b"close"),
                   (REQUEST_ID_HEADER.lower().encode(), rid.encode())]
        for event in (h11.Response(status_code=400, headers=headers, reason=b"Bad Request"),
                      h11.Data(data=body), h11.EndOfMessage()):
            self.transport.write(self.conn.send(event))
        self.transport.close()
