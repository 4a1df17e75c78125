"""What `cortexloc serve` runs uvicorn with, below the app: the HTTP/1.1 protocol.

uvicorn answers a request it cannot parse (a malformed request line, or a request line plus
headers larger than h11's incomplete-event limit, `service.limits.HEAD_MAX_BYTES`) itself, before the
app sees anything, with a text/plain 400. `ProblemH11Protocol` is uvicorn's h11 protocol with only
that answer replaced by the service's problem+json (docs/design/service.md §2), so every error has one shape.
(uvicorn picks httptools when it is installed; it is not a dependency here, and `serve` names this
protocol explicitly.)
"""

from __future__ import annotations

import json

import h11
from uvicorn.protocols.http.h11_impl import DEFAULT_MAX_INCOMPLETE_EVENT_SIZE, H11Protocol

from service.errors import PROBLEM_MEDIA_TYPE, problem_body
from service.request_ids import REQUEST_ID_HEADER, new_request_id

__all__ = ["ProblemH11Protocol"]


class ProblemH11Protocol(H11Protocol):
    """uvicorn's h11 protocol; unparseable requests get a 400 `invalid-parameter` problem+json."""

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
