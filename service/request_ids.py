"""Request ids (docs/design/service.md §2): every request has one, echoed in `X-Request-ID`, quoted in
problems and logs. `service.request_context.RequestContextMiddleware` sets it; this module only names it."""

from __future__ import annotations

import contextvars
import re
import uuid

from fastapi import Request
from starlette.types import Scope

__all__ = ["REQUEST_ID_HEADER", "new_request_id", "request_id_of", "request_id_var", "valid_request_id"]

REQUEST_ID_HEADER = "X-Request-ID"

#: The current request's id, for logging (`service.app`'s log records).
request_id_var: contextvars.ContextVar[str | None] = contextvars.ContextVar("cortexloc_request_id",
                                                                            default=None)
_REQUEST_ID_RE = re.compile(r"[A-Za-z0-9._:-]{1,128}")


def valid_request_id(value: str) -> bool:
    """An incoming `X-Request-ID` worth keeping: 1-128 of `A-Za-z0-9._:-`."""
    return _REQUEST_ID_RE.fullmatch(value) is not None


def request_id_of(scope_or_request: Scope | Request) -> str:
    """The request's id (set by `RequestContextMiddleware`); a fresh one if the middleware did not run."""
    scope = scope_or_request.scope if isinstance(scope_or_request, Request) else scope_or_request
    state = scope.setdefault("state", {})
    rid = state.get("request_id")
    if rid is None:
        rid = state["request_id"] = new_request_id()
    return rid


def new_request_id() -> str:
    return str(uuid.uuid4())
