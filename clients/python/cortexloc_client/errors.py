"""Refusals of the service as exceptions: an `application/problem+json` reply (the service's
docs/design/service.md §2) becomes a `CortexlocError`, or the subclass of its status; a success reply
whose body is not the route's answer (a proxy's page sent with 200) an `InvalidResponseError`.

Example:
    >>> try:
    ...     client.get_map("nowhere")
    ... except NotFoundError as e:
    ...     print(e.status, e.slug, e.detail, e.extra.get("map_id"))
    404 map-not-found no map 'nowhere' nowhere
"""

from __future__ import annotations

import math
from datetime import datetime, timezone
from email.utils import parsedate_to_datetime
from typing import Any

import httpx
from pydantic import ValidationError

from cortexloc_client.models import Problem

__all__ = [
    "BadRequestError",
    "ConflictError",
    "CortexlocError",
    "InsufficientStorageError",
    "InvalidResponseError",
    "NotFoundError",
    "PayloadTooLargeError",
    "ServerError",
    "ServiceUnavailableError",
    "TooManyRequestsError",
    "UnauthorizedError",
    "UnprocessableError",
    "UnsupportedMediaTypeError",
    "error_from_response",
    "is_problem",
]

TYPE_PREFIX = "urn:cortexloc:problem:"


class CortexlocError(Exception):
    """A refusal by the service (or, as `InvalidResponseError`, a reply the client cannot read).

    Attributes:
        status: the HTTP status.
        problem: the problem+json body, or None for a reply that was not one (e.g. a proxy's HTML page).
        type: the problem type (`urn:cortexloc:problem:<slug>`), or None.
        slug: the last part of `type` (`map-not-found`, `overloaded`, ...), or None.
        title: fixed per slug, or None.
        detail: the specific, human-readable sentence (the body's text when not problem+json).
        instance: the request path, or None.
        request_id: the service's id of the request (quote it when reporting a 500).
        extra: the slug's members (`errors`, `map_id`, `max_bytes`, `retry_after`, ...).
        retry_after: seconds from the `Retry-After` header (`retry_after_seconds`), or None.
    """

    def __init__(self, status: int, problem: Problem | None = None, *, detail: str = "",
                 request_id: str | None = None, retry_after: float | None = None) -> None:
        self.status = status
        self.problem = problem
        self.type = problem.type if problem else None
        self.slug = self.type[len(TYPE_PREFIX):] if self.type and self.type.startswith(TYPE_PREFIX) else None
        self.title = problem.title if problem else None
        self.detail = problem.detail if problem else detail
        self.instance = problem.instance if problem else None
        self.request_id = (problem.request_id if problem else None) or request_id
        self.extra: dict[str, Any] = dict(problem.model_extra or {}) if problem else {}
        self.retry_after = retry_after
        super().__init__(f"{status} {self.slug or self.title or 'error'}: {self.detail}")


class InvalidResponseError(CortexlocError):
    """A reply with a success status (2xx, or a 3xx: the client follows no redirect) whose body is not
    the route's answer: a proxy's or captive portal's HTML page sent with 200, JSON cut short, JSON
    without the members the route answers (a server of another version). `problem` and `slug` are None.

    What was asked may have been done (the service may have answered and the body been spoilt on the
    way), so the client treats it as a connection lost after the request left (`RetryPolicy`): sent again
    for idempotent requests only, an observation post with the same `Idempotency-Key` (answered from the
    service's store if it was learned: exactly once); raised once the retries are spent, or at once for
    a request that is not idempotent (`create_map`, `create_snapshot`, `restore_snapshot`, a post without
    a key).

    Attributes (besides `CortexlocError`'s: `status`, `detail`, `request_id`):
        content_type: the reply's `Content-Type` ("" without one).
        excerpt: the start of the body (at most `EXCERPT_CHARS` characters, undecodable bytes replaced).
        reason: what is wrong with it (the first JSON or validation error).
    """

    EXCERPT_CHARS = 200

    def __init__(self, status: int, *, content_type: str, excerpt: str, reason: str,
                 request_id: str | None = None) -> None:
        self.content_type, self.excerpt, self.reason = content_type, excerpt, reason
        detail = (f"a reply the client cannot read ({reason}); Content-Type {content_type or 'none'!r}, "
                  f"body {excerpt!r}")
        super().__init__(status, detail=detail, request_id=request_id)
        self.args = (f"{status} invalid response: {detail}",)

    @classmethod
    def because(cls, response: httpx.Response, reason: str) -> InvalidResponseError:
        """The error for `response`, not the route's answer for `reason`. The excerpt only from a body
        already read: a streamed one (a download) is not read for it."""
        try:
            excerpt = response.content[:cls.EXCERPT_CHARS].decode("utf-8", "replace")
        except httpx.ResponseNotRead:
            excerpt = ""
        return cls(response.status_code, content_type=response.headers.get("Content-Type", ""),
                   excerpt=excerpt, reason=reason, request_id=response.headers.get("X-Request-ID"))

    @classmethod
    def of(cls, response: httpx.Response, error: ValidationError) -> InvalidResponseError:
        """The error for `response`, whose body (read) failed the route's model with `error`."""
        errors = error.errors(include_url=False)
        first = errors[0] if errors else {"loc": (), "msg": str(error)}
        where = ".".join(map(str, first.get("loc", ())))
        reason = f"{where}: {first['msg']}" if where else str(first["msg"])
        if len(errors) > 1:
            reason += f" (and {len(errors) - 1} more)"
        return cls.because(response, reason)


class BadRequestError(CortexlocError):
    """400 `invalid-parameter`: `extra["errors"]` lists `{location, name, message}`."""


class UnauthorizedError(CortexlocError):
    """401 `unauthorized`: a write (or a download) without the server's API key."""


class NotFoundError(CortexlocError):
    """404 `map-not-found`, `snapshot-not-found`, `observation-not-found`, `recent-answer-not-found`,
    `not-found`."""


class ConflictError(CortexlocError):
    """409 `map-exists`, `map-limit`, `map-full`, `map-restored` (retried before it is raised: a restore
    rolled the post back), `snapshot-invalid`, `snapshot-in-use`, `memory-budget` (`extra` holds
    `used_bytes`, `asked_bytes`, `total_bytes`, `free_bytes`)."""


class PayloadTooLargeError(CortexlocError):
    """413 `payload-too-large`, `image-too-large`."""


class UnsupportedMediaTypeError(CortexlocError):
    """415 `unsupported-media-type`: `extra["allowed"]`, `extra["detected"]`."""


class TooManyRequestsError(CortexlocError):
    """429 `stream-limit`: every stream slot of the map posted recently; a new stream may come in after
    `retry_after` seconds (not retried by the client: the wait may be minutes)."""


class UnprocessableError(CortexlocError):
    """422: an undecodable or degenerate image, a decompression bomb, an invalid map configuration."""


class ServerError(CortexlocError):
    """5xx not covered below (500 `internal-error`: quote `request_id`)."""


class ServiceUnavailableError(ServerError):
    """503 `not-ready`, `map-unavailable`, `overloaded`, still refused after the client's retries."""


class InsufficientStorageError(ServerError):
    """507 `insufficient-storage`: the server's disk is full; nothing was stored."""


#: status -> exception class; anything else >= 500 is a `ServerError`, < 500 a `CortexlocError`.
STATUS_ERRORS: dict[int, type[CortexlocError]] = {
    400: BadRequestError,
    401: UnauthorizedError,
    404: NotFoundError,
    409: ConflictError,
    413: PayloadTooLargeError,
    415: UnsupportedMediaTypeError,
    422: UnprocessableError,
    429: TooManyRequestsError,
    503: ServiceUnavailableError,
    507: InsufficientStorageError,
}


def retry_after_seconds(value: str | None, now: datetime | None = None) -> float | None:
    """The `Retry-After` header as seconds to wait (RFC 9110 §10.2.3): a number of seconds (what the
    service sends), or an HTTP date (a proxy's; one past, or `now`, is 0). None, so that the caller backs
    off as for a reply without one, when it is absent or is neither: unreadable, negative, or not finite
    (`nan`, `inf`: `time.sleep` refuses NaN, and `Event.wait` returns at once, a tight retry loop). The
    caller caps it (`RetryPolicy.max_wait_s`), whichever form it came in.

    Args:
        now: the time to count a date from (default the present, UTC).
    """
    if value is None:
        return None
    try:
        seconds = float(value)
    except ValueError:
        try:
            when = parsedate_to_datetime(value)
        except (TypeError, ValueError, IndexError, OverflowError):
            return None
        if when.tzinfo is None:  # "-0000": UTC, as HTTP dates are
            when = when.replace(tzinfo=timezone.utc)
        return max((when - (now or datetime.now(timezone.utc))).total_seconds(), 0.0)
    return seconds if math.isfinite(seconds) and seconds >= 0 else None


PROBLEM_MEDIA_TYPE = "application/problem+json"


def is_problem(response: httpx.Response) -> bool:
    """The reply is the service's problem+json (not a proxy's page)."""
    return response.headers.get("Content-Type", "").split(";")[0].strip().lower() == PROBLEM_MEDIA_TYPE


def error_from_response(response: httpx.Response) -> CortexlocError:
    """The exception for a reply with status >= 400 (its body must have been read)."""
    status = response.status_code
    cls = STATUS_ERRORS.get(status, ServerError if status >= 500 else CortexlocError)
    try:
        problem: Problem | None = Problem.model_validate_json(response.content)
    except ValidationError:
        problem = None
    return cls(status, problem, detail=response.text[:500] or response.reason_phrase,
               request_id=response.headers.get("X-Request-ID"),
               retry_after=retry_after_seconds(response.headers.get("Retry-After")))
