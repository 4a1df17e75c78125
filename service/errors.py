"""One error shape everywhere: RFC 9457 `application/problem+json` (docs/design/service.md §2).

Routes raise `Problem(status, slug, detail, **members)`; the domain (`service.maps`) raises its own
errors, mapped in one table, `DOMAIN_PROBLEMS` (e.g. a damaged snapshot is 409 `snapshot-invalid`).
`install_error_handlers` turns these, FastAPI's validation errors, the router's 404/405, an
`ImageError` and any unexpected exception into the same body:

    {"type": "urn:cortexloc:problem:<slug>", "title": <fixed per slug>, "status": ..., "detail": ...,
     "instance": <request path>, "request_id": ..., <members>}

A client that goes away before its request was read is no server error: logged at info and counted as
499 (nobody receives it). The request id is `service.request_ids`'s; the last-resort 500 for what
escapes everything is `service.request_context.RequestContextMiddleware`'s.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from http import HTTPStatus
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ConfigDict
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from models.frontend.images import ImageError
from service.maps import errors as maps_errors
from service.maps.errors import SnapshotInvalid, StoreClosed
from service.media_types import IMAGE_MEDIA_TYPES, PROBLEM_MEDIA_TYPE
from service.request_ids import REQUEST_ID_HEADER, request_id_of
from service.routing import allowed_methods, request_method

__all__ = ["CLIENT_CLOSED_REQUEST", "DOMAIN_PROBLEMS", "PROBLEM_MEDIA_TYPE", "TITLES", "DomainProblem",
           "Problem", "ProblemDetails", "domain_problem", "image_error_problem", "install_error_handlers",
           "internal_error_response", "problem_body", "problem_response", "problem_responses"]

log = logging.getLogger("cortexloc.errors")

TYPE_PREFIX = "urn:cortexloc:problem:"

#: slug -> (usual status, fixed title): the docs/design/service.md §2 table plus `unauthorized`.
PROBLEMS: dict[str, tuple[int, str]] = {
    "invalid-parameter": (400, "Invalid parameter"),
    "unauthorized": (401, "Unauthorized"),
    "map-not-found": (404, "Map not found"), "observation-not-found": (404, "Observation not found"),
    "recent-answer-not-found": (404, "Recent answer not found"),
    "snapshot-not-found": (404, "Snapshot not found"),
    "snapshot-invalid": (409, "Snapshot invalid"),
    "snapshot-in-use": (409, "Snapshot in use"),
    "map-restored": (409, "Map restored"),
    "not-found": (404, "Not found"),
    "method-not-allowed": (405, "Method not allowed"),
    "method-not-implemented": (501, "Method not implemented"),
    "transfer-coding-not-implemented": (501, "Transfer coding not implemented"),
    "map-exists": (409, "Map already exists"),
    "map-limit": (409, "Too many maps"),
    "map-full": (409, "Map is full"),
    "request-timeout": (408, "Request timeout"),
    "memory-budget": (409, "Memory budget exceeded"),
    "payload-too-large": (413, "Payload too large"),
    "stream-limit": (429, "Too many streams"),
    "image-too-large": (413, "Image too large"),
    "unsupported-media-type": (415, "Unsupported media type"),
    "undecodable-image": (422, "Undecodable image"),
    "degenerate-image": (422, "Degenerate image"),
    "decompression-bomb": (422, "Decompression bomb"),
    "raw-frame-size-mismatch": (422, "Raw frame size mismatch"),
    "invalid-metadata": (422, "Invalid metadata"), "idempotency-key-reused": (422, "Idempotency key reused"),
    "map-too-large": (422, "Map too large"),
    "invalid-configuration": (422, "Invalid configuration"),
    "not-ready": (503, "Not ready"),
    "map-unavailable": (503, "Map unavailable"),
    "map-read-only": (503, "Map read-only"),
    "overloaded": (503, "Overloaded"),
    "insufficient-storage": (507, "Insufficient storage"),
    "internal-error": (500, "Internal error"),
}
TITLES: dict[str, str] = {slug: title for slug, (_, title) in PROBLEMS.items()}

#: Members every problem has; a route's extra members may not reuse these names.
RESERVED_MEMBERS = frozenset({"type", "title", "status", "detail", "instance", "request_id"})

#: Slug for an HTTPException raised by the framework (or a library) with this status.
_STATUS_SLUGS = {400: "invalid-parameter", 401: "unauthorized", 404: "not-found", 405: "method-not-allowed",
                 413: "payload-too-large", 415: "unsupported-media-type", 503: "not-ready"}



class Problem(Exception):  # noqa: N818 - the RFC 9457 name
    """An error that becomes a problem+json response.

    Args:
        status: HTTP status.
        slug: one of `TITLES` (the type is `urn:cortexloc:problem:<slug>`).
        detail: a specific, human-readable sentence.
        headers: extra response headers (e.g. `Retry-After`).
        **members: the slug's extra members (docs/design/service.md §2 table), JSON-serialisable.
    """

    def __init__(self, status: int, slug: str, detail: str, *, headers: Mapping[str, str] | None = None,
                 **members: Any) -> None:
        if slug not in TITLES:
            raise ValueError(f"unknown problem slug {slug!r}; register it in service.errors.PROBLEMS")
        clash = RESERVED_MEMBERS & set(members)
        if clash:
            raise ValueError(f"problem members may not be named {sorted(clash)}")
        super().__init__(detail)
        self.status = int(status)
        self.slug = slug
        self.detail = detail
        self.headers = dict(headers or {})
        self.members = members

    @property
    def title(self) -> str:
        return TITLES[self.slug]

    def __repr__(self) -> str:
        return f"Problem({self.status}, {self.slug!r}, {self.detail!r})"


class ProblemDetails(BaseModel):
    """The problem+json body, for OpenAPI (`problem_responses`); slug-specific members are extra."""

    model_config = ConfigDict(extra="allow")

    type: str
    title: str
    status: int
    detail: str
    instance: str
    request_id: str


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI `responses=` entries documenting problem+json bodies for these statuses."""
    schema = ProblemDetails.model_json_schema()
    return {s: {"description": HTTPStatus(s).phrase, "content": {PROBLEM_MEDIA_TYPE: {"schema": schema}}}
            for s in statuses}


# ------------------------------------------------------------------------------------ problem bodies


def problem_body(status: int, slug: str, detail: str, *, instance: str, request_id: str,
                 **members: Any) -> dict[str, Any]:
    """The problem+json object (also for answers written below the app, e.g. by the HTTP protocol)."""
    if slug not in TITLES:
        raise ValueError(f"unknown problem slug {slug!r}")
    body = {"type": TYPE_PREFIX + slug, "title": TITLES[slug], "status": int(status), "detail": detail,
            "instance": instance, "request_id": request_id}
    body.update({k: v for k, v in members.items() if k not in RESERVED_MEMBERS})
    return body


def problem_response(request: Request, status: int, slug: str, detail: str, *,
                     headers: Mapping[str, str] | None = None, **members: Any) -> JSONResponse:
    """The problem+json response for this request.

    Args:
        request: the request (gives `instance` and `request_id`).
        status, slug, detail, members: see `Problem`.
        headers: extra headers; `X-Request-ID` is always set.
    """
    rid = request_id_of(request)
    body = problem_body(status, slug, detail, instance=request.url.path, request_id=rid, **members)
    out_headers = {**(headers or {}), REQUEST_ID_HEADER: rid}
    return JSONResponse(body, status_code=int(status), headers=out_headers, media_type=PROBLEM_MEDIA_TYPE)


def problem_to_response(request: Request, problem: Problem) -> JSONResponse:
    return problem_response(request, problem.status, problem.slug, problem.detail, headers=problem.headers,
                            **problem.members)


# --------------------------------------------------------------------------------- image errors

_IMAGE_SLUGS: dict[str, tuple[int, str]] = {
    "too-large": (413, "payload-too-large"),
    "too-many-pixels": (413, "image-too-large"),
    "unsupported-format": (415, "unsupported-media-type"),
    "empty": (422, "undecodable-image"),
    "not-an-image": (422, "undecodable-image"),
    "truncated": (422, "undecodable-image"),
    "degenerate": (422, "degenerate-image"),
    "bomb": (422, "decompression-bomb"), "size-mismatch": (422, "raw-frame-size-mismatch"),
    "unsupported-encoding": (415, "unsupported-media-type"),
}


def image_error_problem(e: ImageError, *, max_pixels: int | None = None,
                        allowed: tuple[str, ...] = IMAGE_MEDIA_TYPES) -> Problem:
    """The docs/design/service.md §2 problem for an `ImageError`, with `e.details` as members.

    Args:
        e: the error from `models.frontend.images`.
        max_pixels: filled in as `max_pixels` for `image-too-large` when the error lacks it (OpenCV's
            own guard does not know the configured cap).
        allowed: the `allowed` member of `unsupported-media-type`.
    """
    status, slug = _IMAGE_SLUGS[e.code]
    members = {k: v for k, v in e.details.items() if k not in RESERVED_MEMBERS}
    if slug == "image-too-large" and max_pixels is not None:
        members.setdefault("max_pixels", max_pixels)
    if slug == "unsupported-media-type":
        members.setdefault("allowed", list(allowed))
        members.setdefault("detected", None)
    return Problem(status, slug, e.message, **members)


# ------------------------------------------------------------------------------------- handlers


async def _problem_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, Problem)
    return problem_to_response(request, exc)


async def _image_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, ImageError)
    settings = getattr(request.app.state, "settings", None)
    problem = image_error_problem(exc, max_pixels=getattr(settings, "max_pixels", None))
    return problem_to_response(request, problem)


def _validation_errors(exc: RequestValidationError) -> list[dict[str, str]]:
    out = []
    for err in exc.errors():
        loc = [str(p) for p in err.get("loc", ())]
        location = loc[0] if loc else "request"
        if err.get("type") == "json_invalid":  # loc is ("body", <character offset>)
            name, message = "", f"invalid JSON: {err.get('ctx', {}).get('error', err.get('msg', ''))}"
        elif err.get("type") == "value_error" and "error" in err.get("ctx", {}):  # one of our validators:
            name, message = ".".join(loc[1:]), str(err["ctx"]["error"])  # its words, not "Value error, ..."
        else:
            name, message = ".".join(loc[1:]), str(err.get("msg", "invalid value"))
        out.append({"location": location, "name": name, "message": message})
    return out


class DomainProblem(NamedTuple):
    """How a domain error is answered: status, slug, the error's attributes shown as members, headers;
    `detail` replaces the error's message where that message is for the log only (it names a file)."""
    status: int
    slug: str
    members: tuple[str, ...] = ()
    headers: Mapping[str, str] = MappingProxyType({})
    detail: str | None = None


#: Domain errors -> their problem, the one table (docs/design/service.md §2). The detail is the error's
#: message, with the data directory's path cut off (it names the file, not where the server keeps it).
DOMAIN_PROBLEMS: dict[type[Exception], DomainProblem] = {
    maps_errors.InvalidMapId: DomainProblem(400, "invalid-parameter", ("errors",)),
    maps_errors.MapNotFound: DomainProblem(404, "map-not-found", ("map_id",)),
    maps_errors.SnapshotNotFound: DomainProblem(404, "snapshot-not-found", ("map_id",)),
    maps_errors.ObservationNotFound: DomainProblem(404, "observation-not-found", ("map_id", "seq")),
    maps_errors.RecentAnswerNotFound: DomainProblem(404, "recent-answer-not-found", ("map_id", "answer_id")),
    maps_errors.IdempotencyKeyReused: DomainProblem(422, "idempotency-key-reused", ("key",)),
    SnapshotInvalid: DomainProblem(409, "snapshot-invalid"),
    maps_errors.SnapshotInUse: DomainProblem(409, "snapshot-in-use", ("map_id", "snapshot_id")),
    maps_errors.MapRestored: DomainProblem(409, "map-restored", ("map_id",)),
    maps_errors.MapAlreadyExists: DomainProblem(409, "map-exists", ("map_id",)),
    maps_errors.UnlistedMaps: DomainProblem(409, "map-exists", ("map_id",)),  # on disk, not in the catalog
    maps_errors.MapLimit: DomainProblem(409, "map-limit", ("max_maps",)),
    maps_errors.MapFull: DomainProblem(409, "map-full", ("max_observations",)),
    maps_errors.RowsOverCap: DomainProblem(409, "map-full", ("max_observations", "rows_held")),
    maps_errors.MemoryBudgetExceeded: DomainProblem(409, "memory-budget", (
        "map_id", "used_bytes", "asked_bytes", "total_bytes", "free_bytes")),
    maps_errors.MapTooLarge: DomainProblem(422, "map-too-large", ("required_bytes", "max_bytes")),
    maps_errors.InvalidConfiguration: DomainProblem(422, "invalid-configuration", ("errors",)),
    maps_errors.InvalidCamera: DomainProblem(422, "invalid-metadata", ("errors",)),
    maps_errors.MapUnavailable: DomainProblem(503, "map-unavailable", ("state", "state_reason")),
    maps_errors.MapReadOnly: DomainProblem(503, "map-read-only", ("map_id", "state", "state_reason")),
    maps_errors.MapReplaying: DomainProblem(503, "map-unavailable", (
        "state", "state_reason", "steps", "replayed", "retry_after")),
    maps_errors.ShardUnavailable: DomainProblem(503, "map-unavailable", (
        "map_id", "shard", "retry_after", "outcome_unknown")),
    maps_errors.Overloaded: DomainProblem(503, "overloaded", ("retry_after",), {"Retry-After": "1"}),
    maps_errors.EncoderUnavailable: DomainProblem(503, "not-ready", ("retry_after",)),
    # (raised at start only, where it keeps the service not ready: /readyz and every map route say why)
    maps_errors.DataDirectoryInUse: DomainProblem(503, "not-ready"),
    maps_errors.StreamLimit: DomainProblem(429, "stream-limit",
                                           ("max_streams", "keep_seconds", "retry_after")),
    # mid-restore or delete; the storage's message names the file (maps/<id>/map.sqlite)
    StoreClosed: DomainProblem(503, "map-unavailable", (), {"Retry-After": "1"},
                               "the map's store was closed under this request (a restore or a deletion "
                               "replaced it); retry"),
    maps_errors.InsufficientStorage: DomainProblem(507, "insufficient-storage"),
}


def domain_problem(exc: Exception, data_dir: Path | None = None) -> Problem:
    """The `Problem` for a domain error of `DOMAIN_PROBLEMS` (its nearest listed class); an error with a
    `retry_after` (seconds) says it in the `Retry-After` header too."""
    entry = next(DOMAIN_PROBLEMS[cls] for cls in type(exc).__mro__ if cls in DOMAIN_PROBLEMS)
    detail = entry.detail or str(exc)
    for root in {str(data_dir.resolve()), str(data_dir)} if data_dir is not None else ():
        detail = detail.replace(root.rstrip("/") + "/", "")
    retry = getattr(exc, "retry_after", None)
    headers = {**entry.headers, **({"Retry-After": str(retry)} if retry is not None else {})}
    return Problem(entry.status, entry.slug, detail, headers=headers,
                   **{name: getattr(exc, name) for name in entry.members})


async def _domain_error_handler(request: Request, exc: Exception) -> JSONResponse:
    settings = getattr(request.app.state, "settings", None)
    return problem_to_response(request, domain_problem(exc, getattr(settings, "data_dir", None)))


async def _validation_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, RequestValidationError)
    errors = _validation_errors(exc)
    first = errors[0] if errors else {"location": "request", "name": "", "message": "invalid request"}
    where = f"{first['location']} parameter {first['name']!r}" if first["name"] else first["location"]
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return problem_response(request, 400, "invalid-parameter", f"{where}: {first['message']}{more}",
                            errors=errors)


#: Status recorded for a request whose client went away before it was read (nginx's "client closed
#: request"): nobody receives it, the metrics count it apart from the server's errors.
CLIENT_CLOSED_REQUEST = 499


async def _client_disconnect_handler(request: Request, exc: Exception) -> Response:
    """The client closed the connection mid-request (e.g. during an upload, or before its post reached
    the map's writer: `ClientGone`): not a server error."""
    log.info("client went away before %s %s was answered", request.method, request.url.path)
    return Response(status_code=CLIENT_CLOSED_REQUEST)


async def _http_exception_handler(request: Request, exc: Exception) -> Response:
    assert isinstance(exc, StarletteHTTPException)
    if isinstance(exc.__cause__, ClientDisconnect):  # FastAPI's 400 "error parsing the body"
        return await _client_disconnect_handler(request, exc.__cause__)
    status = exc.status_code
    phrase = HTTPStatus(status).phrase if status in HTTPStatus._value2member_map_ else ""
    custom = isinstance(exc.detail, str) and exc.detail and exc.detail != phrase
    headers = dict(exc.headers or {})
    if status == 404:
        detail = exc.detail if custom else f"no resource at {request.url.path}"
        return problem_response(request, 404, "not-found", detail, headers=headers)
    if status == 405:
        allowed = allowed_methods(request)
        if not allowed and "Allow" in headers:
            allowed = sorted(m.strip() for m in headers["Allow"].split(",") if m.strip())
        headers["Allow"] = ", ".join(allowed)
        detail = (f"{request_method(request)} is not allowed on {request.url.path}; "
                  f"allowed: {', '.join(allowed)}")
        return problem_response(request, 405, "method-not-allowed", detail, headers=headers, allowed=allowed)
    slug = _STATUS_SLUGS.get(status, "internal-error" if status >= 500 else "invalid-parameter")
    detail = exc.detail if custom else (phrase or f"HTTP {status}")
    members: dict[str, Any] = {"errors": []} if slug == "invalid-parameter" else {}
    return problem_response(request, status, slug, str(detail), headers=headers, **members)


def internal_error_response(request: Request) -> JSONResponse:
    return problem_response(request, 500, "internal-error",
                            f"an internal error occurred; quote request id {request_id_of(request)} when "
                            "reporting it")


async def _internal_error_handler(request: Request, exc: Exception) -> JSONResponse:
    log.error("unhandled exception in %s %s", request.method, request.url.path, exc_info=exc)
    return internal_error_response(request)


def install_error_handlers(app: FastAPI) -> None:
    """Replace FastAPI's validation, 404/405 and 500 handlers with problem+json ones."""
    app.add_exception_handler(Problem, _problem_handler)
    app.add_exception_handler(ImageError, _image_error_handler)
    for domain_error in DOMAIN_PROBLEMS:
        app.add_exception_handler(domain_error, _domain_error_handler)
    app.add_exception_handler(RequestValidationError, _validation_handler)
    app.add_exception_handler(ClientDisconnect, _client_disconnect_handler)
    app.add_exception_handler(maps_errors.ClientGone, _client_disconnect_handler)
    app.add_exception_handler(StarletteHTTPException, _http_exception_handler)
    app.add_exception_handler(Exception, _internal_error_handler)
