"""What `cortexloc serve` runs uvicorn with, below the app: the HTTP/1.1 protocol.

uvicorn's httptools protocol (the C parser llhttp: issue 40 measured h11's pure-Python parsing as a
large part of the event loop's ~3.5 ms of CPU per image, docs/benchmarks.md §10.1), with what the
service needs below the app:

- uvicorn answers a request it cannot parse (a malformed request line or header) itself, before the
  app sees anything, with a text/plain 400. `ProblemHttpToolsProtocol` replaces only that answer by the
  service's problem+json (docs/design/service.md §2), so every error has one shape; a request whose
  method llhttp does not know (`FOO`, `get`) is 501 `method-not-implemented` (RFC 9110 §9.1).
- A request head still incomplete past `service.limits.HEAD_MAX_BYTES` (16 KiB) is refused with the
  same 400 problem+json: llhttp has no limit of its own, nor uvicorn's httptools protocol, so a client
  could otherwise make the server buffer megabytes of header. A longer head that completes within one
  read reaches the app, whose upload-limit middleware refuses it the same way (`service.limits`).
- It bounds the connections open at once (`connection_cap`: `CORTEXLOC_MAX_CONNECTIONS`, lowered to what
  the process's descriptor limit leaves after `FD_RESERVE` for the service's own files): a further one
  is answered 503 `overloaded` (Retry-After) and closed as it opens. An outside probe opened more idle
  connections than the descriptor limit: accepts failed (asyncio logged a traceback for each, a flood),
  and so did the maps' own file operations, the group commit's fsync among them, so posts already
  committed were answered 500.
- It bounds how long a request's head may take: a connection that has not completed a request head
  within `CORTEXLOC_BODY_TIMEOUT_S` of opening (or of its previous reply) is answered 408
  `request-timeout` and closed. uvicorn bounds only an idle keep-alive connection (5 s, reset by any
  byte), so a client sending its headers a byte at a time would otherwise hold the connection for ever
  (the body is bounded by `service.limits`, docs/design/service.md §3).
- It bounds how long a reply may wait for its client to read it: a connection whose writes stay paused
  (more than the transport's high-water mark unsent, the kernel's buffers full) while its client takes
  less than a piece (`REPLY_CHUNK_BYTES`, 64 KiB) in `CORTEXLOC_BODY_TIMEOUT_S` is aborted. A stall
  deadline, not a total one: a client that reads a piece a timeout, however large the reply, is served.
  An outside probe: clients that never read a large reply held their connections (and, pipelined
  behind it, an upload's budget) for as long as they kept them open; only streamed replies had a
  deadline (`service.limits.ReadStreamingResponse`, which keeps it for any server), and a graceful
  close never ends while unsent bytes wait, so the connection is aborted.
"""

from __future__ import annotations

import asyncio
import functools
import json
import logging
import re
import resource

import httptools
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.errors import PROBLEM_MEDIA_TYPE, problem_body
from service.limits import HEAD_MAX_BYTES, REPLY_CHUNK_BYTES
from service.request_ids import REQUEST_ID_HEADER, new_request_id
from service.settings import Settings

__all__ = ["BACKLOG", "FD_RESERVE", "ProblemHttpToolsProtocol", "connection_cap"]

log = logging.getLogger("cortexloc.service")

#: Connections the kernel may queue for accepting (`uvicorn.run(backlog=...)`): asyncio accepts up to that
#: many in one turn of the loop, each holding a descriptor before the cap sees it (uvicorn's default, 2,048,
#: would outrun the reserve below; a review).
BACKLOG = 256
#: File descriptors kept beside the connections: a burst of `BACKLOG` accepts, and the service's own files,
#: each open map's SQLite database, journal and shared memory (64 maps by default), snapshots being
#: written or read, the logs.
FD_RESERVE = 1024


@functools.lru_cache(maxsize=8)
def connection_cap(max_connections: int) -> int:
    """Client connections open at once: `max_connections`, or what the soft descriptor limit leaves
    after `FD_RESERVE` where that is fewer (at least 1). Read once per value: `cortexloc serve` sets the
    limit before it serves."""
    soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return max_connections
    return max(1, min(max_connections, soft - FD_RESERVE))


#: Bytes of a request head kept to name its method when llhttp refuses it (the longest method token
#: a 501 names; a longer one is a malformed request line, 400).
_METHOD_PEEK = 33
_METHOD_TOKEN = re.compile(rb"([!#$%&'*+.^_`|~0-9A-Za-z-]{1,32}) ")


def _unknown_method(head_start: bytes | None) -> str | None:
    """The method of a request line whose method token is well formed but one llhttp does not know
    (`FOO`, or `get`: methods are case-sensitive), else None."""
    m = None if head_start is None else _METHOD_TOKEN.match(head_start)
    if m is None:
        return None
    try:
        httptools.HttpRequestParser(object()).feed_data(m.group(0) + b"/ HTTP/1.1\r\n\r\n")
    except httptools.HttpParserInvalidMethodError:
        return m.group(1).decode("ascii")
    except Exception:  # any other answer (CONNECT's HttpParserUpgrade among them): a known method
        return None
    return None


class ProblemHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol; unparseable requests and heads over `HEAD_MAX_BYTES` get a 400
    `invalid-parameter` problem+json, and a head that does not arrive in time a 408 (module docstring)."""

    _head_timer: asyncio.TimerHandle | None = None
    _stall_timer: asyncio.TimerHandle | None = None  # set while the transport's writes are paused
    _unsent = 0  # the transport's unsent bytes when the stall clock last started
    _in_head, _head_bytes = True, 0  # the current message's head is unfinished; bytes read since it began
    # The current message's first bytes (`_METHOD_PEEK`), or None where it began inside a read that ended
    # another (pipelined): only a read that starts with a message gives its method.
    _head_start: bytes | None = b""
    _message_open = False  # llhttp began a message that has not completed
    _read_starts_message = True  # this read's first byte is a message's first byte

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        settings = self._settings()
        cap = connection_cap(int(getattr(settings, "max_connections",
                                         Settings.model_fields["max_connections"].default)))
        if len(self.connections) > cap:
            self._answer(503, "Service Unavailable", "overloaded", f"more than {cap} connections are open; "
                         "retry later", headers={"retry-after": "1"}, max_connections=cap)
            return
        self._await_head()

    def _settings(self) -> Settings | None:
        return getattr(getattr(self.config.app, "state", None), "settings", None)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        self._await_head()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self._head_timer, self._stall_timer):
            if timer is not None:
                timer.cancel()
        super().connection_lost(exc)

    # ---------------------------------------------------------------- the reply's reader

    def pause_writing(self) -> None:
        super().pause_writing()
        if self._stall_timer is None:
            self._await_reader()

    def _await_reader(self) -> None:
        self._unsent = self.transport.get_write_buffer_size()
        self._stall_timer = self.loop.call_later(self._timeout_s(), self._stalled)

    def resume_writing(self) -> None:
        super().resume_writing()
        if self._stall_timer is not None:
            self._stall_timer.cancel()
            self._stall_timer = None

    def _stalled(self) -> None:
        """The writes stayed paused `body_timeout_s`: the client takes none of its reply (module
        docstring). Aborted, not closed: a close would wait for the unsent bytes for ever."""
        self._stall_timer = None
        unsent = self.transport.get_write_buffer_size()
        if self.transport.is_closing() and unsent == 0:
            return
        # Writes resume only near the low-water mark, so a reply written at once stays paused while a slow
        # client reads it (a review: a steady slow reader of a large reply was cut): a piece
        # (`REPLY_CHUNK_BYTES`, or what was left) taken since is reading, and the clock starts again.
        if self._unsent - unsent >= min(REPLY_CHUNK_BYTES, self._unsent):
            self._await_reader()
            return
        log.warning("%s: the client read none of its reply for %g s; the connection is aborted",
                    self.client or "a client", self._timeout_s())
        self.transport.abort()

    # ---------------------------------------------------------------- the head's size

    def data_received(self, data: bytes) -> None:
        # Bytes since the message began while its head is unfinished: a head still incomplete past the
        # limit is refused. One that completes within a read reaches the app, which checks its size.
        self._read_starts_message = not self._message_open
        if self._read_starts_message:
            self._head_start = b""
        if self._in_head:
            if self._head_start is not None and len(self._head_start) < _METHOD_PEEK:
                self._head_start += data[:_METHOD_PEEK - len(self._head_start)]  # for a refused method
            self._head_bytes += len(data)
        super().data_received(data)
        if self._in_head and self._head_bytes > HEAD_MAX_BYTES and not self.transport.is_closing():
            self.send_400_response(f"the request head is over {HEAD_MAX_BYTES} bytes")

    def on_headers_complete(self) -> None:
        self._in_head = False
        super().on_headers_complete()

    def on_message_begin(self) -> None:
        if not self._read_starts_message:  # a pipelined message, begun part way through a read
            self._head_start = None
        self._read_starts_message, self._message_open = False, True
        super().on_message_begin()

    def on_message_complete(self) -> None:
        self._in_head, self._head_bytes, self._message_open = True, 0, False
        super().on_message_complete()

    # ---------------------------------------------------------------- the head's time

    def _timeout_s(self) -> float:
        """`CORTEXLOC_BODY_TIMEOUT_S`: the head's, the body's (`service.limits`) and the reply's."""
        return float(getattr(self._settings(), "body_timeout_s",
                             Settings.model_fields["body_timeout_s"].default))

    def _await_head(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
        timeout = self._timeout_s()
        self._head_timer = self.loop.call_later(timeout, self._head_timed_out, self.cycle, timeout)

    def _head_timed_out(self, cycle: object, timeout: float) -> None:
        """No request head since the timer was set (`cycle` is still the latest, and answered)."""
        if self.transport.is_closing() or self.cycle is not cycle:
            return
        if cycle is not None and not getattr(cycle, "response_complete", True):
            return  # a request is being served
        detail = f"no complete request head within {timeout:g} s"
        self._answer(408, "Request Timeout", "request-timeout", detail, timeout_s=timeout, received_bytes=0)

    def send_400_response(self, msg: str) -> None:
        method = _unknown_method(self._head_start)
        if method is not None:  # RFC 9110 §9.1: a method the server does not know is 501, not a bad request
            self._answer(501, "Not Implemented", "method-not-implemented",
                         f"{method!r} is no HTTP method this service knows (methods are case-sensitive)",
                         method=method)
            return
        detail = (f"the request could not be parsed as HTTP/1.1: a malformed request line or header, or a "
                  f"request line and headers larger than {HEAD_MAX_BYTES} bytes")
        self._answer(400, "Bad Request", "invalid-parameter", detail,
                     errors=[{"location": "header", "name": "", "message": msg}])

    def _answer(self, status: int, reason: str, slug: str, detail: str, *,
                headers: dict[str, str] | None = None, **members: object) -> None:
        """Write a problem+json answer as bytes and close: no request was parsed to answer. The path is
        unknown (the request line may be what failed), so the instance names the occurrence."""
        rid = new_request_id()
        body = json.dumps(problem_body(status, slug, detail, instance=f"urn:uuid:{rid}", request_id=rid,
                                       **members)).encode()
        extra = b"".join(b"%s: %s\r\n" % (k.encode(), v.encode()) for k, v in (headers or {}).items())
        self.transport.write(b"HTTP/1.1 %d %s\r\ncontent-type: " % (status, reason.encode())
                             + PROBLEM_MEDIA_TYPE.encode()
                             + b"\r\ncontent-length: %d\r\nconnection: close\r\n" % len(body) + extra
                             + REQUEST_ID_HEADER.lower().encode() + b": " + rid.encode() + b"\r\n\r\n" + body)
        self.transport.close()
