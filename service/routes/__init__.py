"""The HTTP routes, one router per resource (docs/design/service.md §1), gathered in `api_router`.

`service.app.create_app` includes `api_router`; a new resource is a module here with its own `router`,
added below.
"""

from __future__ import annotations

from collections import Counter
from urllib.parse import unquote_to_bytes

from fastapi import APIRouter, Depends, Request
from fastapi.dependencies.models import Dependant

from service.deps import ReadKeyDep
from service.errors import Problem, problem_responses
from service.limits import is_json
from service.routes import closures, health, maps, metrics, observations, recent, repair, snapshots
from service.routes.params import duplicate_keys

__all__ = ["MAX_QUERY_PARAMETERS", "QueryRulesDep", "api_router", "check_request_parameters",
           "declared_parameters"]

#: Query parameters one request may carry: a route declares 8 at most, and the rules below run before the
#: write key is checked, so a query of thousands of names must cost nothing and echo nothing.
MAX_QUERY_PARAMETERS = 32
#: Offending names a refusal lists (the count is always given).
_NAMES_LISTED = 10


def declared_parameters(dependant: Dependant) -> tuple[frozenset[str], frozenset[str]]:
    """The query parameter names and the header names (lower case) `dependant` (a route's, with every
    dependency it pulls in) declares: what the route reads, so a rule over them needs no list kept by hand.
    Walked per request: a few dozen fields, and no cache to keep a dropped app's routes alive."""
    queries = {field.alias for field in dependant.query_params}
    headers = {field.alias.lower() for field in dependant.header_params}
    for sub in dependant.dependencies:
        sub_queries, sub_headers = declared_parameters(sub)
        queries |= sub_queries
        headers |= sub_headers
    return frozenset(queries), frozenset(headers)


def _invalid(what: str, names: list[str], message: str, location: str = "query", advice: str = "",
             **members: object) -> Problem:
    """400 invalid-parameter naming at most `_NAMES_LISTED` of `names` (a reply never echoes a request)."""
    shown = names[:_NAMES_LISTED]
    more = f" and {len(names) - len(shown)} more" if len(names) > len(shown) else ""
    return Problem(400, "invalid-parameter", f"{what}: {', '.join(map(repr, shown))}{more}{advice}",
                   **members,
                   errors=[{"location": location, "name": name, "message": message} for name in shown])


def _not_utf8(query_string: bytes) -> list[str]:
    """The parameters of a raw query string whose percent-decoded name or value is not UTF-8 (Starlette
    would read each bad byte as U+FFFD and the service would store that, not what was sent)."""
    bad = []
    for field in query_string.decode("latin-1").split("&"):
        name, _, value = field.partition("=")
        raw_name = unquote_to_bytes(name.replace("+", " "))
        try:
            raw_name.decode()
            unquote_to_bytes(value.replace("+", " ")).decode()
        except UnicodeDecodeError:
            bad.append(raw_name.decode(errors="backslashreplace"))
    return bad


#: The most of a body a route that takes none reads to see whether it is empty (`{}`, whitespace).
_EMPTY_BODY_READ = 64


async def _no_body(request: Request) -> None:
    """A route that declares no body (no body parameter, no OpenAPI `requestBody`: its options are query
    parameters) gets none: a body such as
    `{"dry_run": true}` to `POST .../repair` would otherwise be ignored and the repair run. An empty JSON
    object, or whitespace, says nothing and passes; anything else is refused unread past
    `_EMPTY_BODY_READ` bytes.

    Raises:
        Problem: 400 invalid-parameter (location `body`)."""
    body = b""
    async for chunk in request.stream():  # the route reads nothing: at most a few bytes are read here
        body += chunk
        if len(body) > _EMPTY_BODY_READ:
            break
    if body.strip() not in (b"", b"{}"):
        raise Problem(400, "invalid-parameter", "this route takes no request body: its options are query "
                      "parameters (nothing was done)",
                      errors=[{"location": "body", "name": "", "message": "no body is accepted"}])


async def check_request_parameters(request: Request) -> None:
    """The rules every route's query (and declared headers) follow (docs/design/service.md §2), read from
    the route's own declarations: each query name and value is UTF-8, each parameter is one the route
    declares and is given once (FastAPI would silently ignore an unknown one, so a misspelt `learn=false`
    would learn, and take the last of a repeated one), and so is each header the route declares
    (`Idempotency-Key`: two keys in one request bind neither safely). A route that reads a JSON body
    gets one sent as JSON; a route that reads none gets none (`_no_body`).

    Raises:
        Problem: 415 unsupported-media-type for a body of another type on a JSON route; 400
            invalid-parameter naming each offending parameter (and listing the accepted ones
            for an unknown one), or a body sent to a route that takes none.
    """
    query = request.scope.get("query_string") or b""
    if query.count(b"&") >= MAX_QUERY_PARAMETERS:
        raise Problem(400, "invalid-parameter", f"more than {MAX_QUERY_PARAMETERS} query parameters",
                      errors=[{"location": "query", "name": "", "message": "too many parameters"}])
    not_utf8 = _not_utf8(query)
    if not_utf8:
        raise _invalid("query parameter(s) not UTF-8 once percent-decoded", not_utf8, "not UTF-8")
    names = [name for name, _ in request.query_params.multi_items()]
    repeated = sorted(name for name, n in Counter(names).items() if n > 1)
    if repeated:
        raise _invalid("query parameter(s) given more than once", repeated, "given more than once",
                       advice="; give each once")
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if not isinstance(dependant, Dependant):
        return
    accepted, headers = declared_parameters(dependant)
    unknown = sorted(set(names) - accepted)
    if unknown:
        listed = ", ".join(sorted(accepted)) or "none"
        raise _invalid("unknown query parameter(s)", unknown, "unknown parameter",
                       advice=f"; this route accepts: {listed}", accepted=sorted(accepted))
    sent = (request.headers.get("content-length", "0") not in ("", "0")
            or "transfer-encoding" in request.headers)
    declared = (getattr(route, "openapi_extra", None) or {}).get("requestBody")  # a body it reads itself
    if sent and not (dependant.body_params or declared is not None):
        await _no_body(request)
    if dependant.body_params and sent and not is_json(request.headers.get("content-type")):
        # FastAPI would read any other type as bytes and say the body is no object: the wrong reason
        media = request.headers.get("content-type")
        raise Problem(415, "unsupported-media-type",
                      f"Content-Type {media or '(none)'!r} is not accepted: this route reads "
                      f"application/json",
                      allowed=["application/json"])
    reads_json = dependant.body_params or "application/json" in (declared or {}).get("content", {})
    if (reads_json and sent and is_json(request.headers.get("content-type"))
            and (twice := duplicate_keys(await request.body()))):
        # (FastAPI reads a declared body before the dependencies run, and keeps it; one a route reads
        # itself, the ingress's, is kept for it too: a JSON body is at most 64 KiB, service/limits.py)
        raise _invalid("JSON member(s) given more than once in one object", twice, "given more than once",
                       location="body", advice="; give each once")
    doubled = sorted(name for name in headers if len(request.headers.getlist(name)) > 1)
    if doubled:
        raise _invalid("header(s) given more than once", doubled, "given more than once", location="header",
                       advice="; give each once")


#: The rules above, on every route but the probes' (`api_router`; the scale-out ingress's own routes).
QueryRulesDep = Depends(check_request_parameters)

api_router = APIRouter()
# /healthz, /readyz: open to probes, whatever the key rules, and whatever their query: they read none, and
# a liveness check that adds a cache-busting parameter must not restart a healthy service.
api_router.include_router(health.router)
# Every other route: `?learn=false&learn=true`, `?Learn=false` and `?label=caf%E9` are each a 400, not a
# guess. With CORTEXLOC_API_KEY_READS every /v1 route and /metrics need the key: map lists, stream names
# (robot names), sizes, snapshot lists and the metrics' map ids are not for anyone on the network either.
# A route added to these routers is guarded without naming it (writes check the key anyway).
api_router.include_router(metrics.router, dependencies=[ReadKeyDep, QueryRulesDep],
                          responses=problem_responses(401))
v1 = APIRouter(dependencies=[ReadKeyDep, QueryRulesDep], responses=problem_responses(401))
for resource in (maps.router, maps.process_router, observations.router, recent.router, snapshots.router,
                 closures.router, repair.router):
    v1.include_router(resource)
api_router.include_router(v1)
