"""The app's routes as a flat list (route templates for the metrics, the methods of a path for a 405), and
HEAD answered as GET (docs/design/service.md §1.9)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

from fastapi import Request
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["HeadMiddleware", "allowed_methods", "iter_routes", "request_method", "sent_head"]

#: The scope key that keeps a HEAD request's method while the app answers it as a GET.
_SENT_METHOD = "cortexloc.sent_method"


def iter_routes(routes: Iterable[Any]) -> Iterator[Any]:
    """Every route of a router, included routers flattened (FastAPI >= 0.16x keeps an included router as
    one entry whose `effective_candidates()` are its routes with the prefixes applied)."""
    for route in routes:
        candidates = getattr(route, "effective_candidates", None)
        if callable(candidates):
            yield from iter_routes(candidates())
        else:
            yield route


def allowed_methods(request: Request) -> list[str]:
    """Methods of every route whose path matches the request (Starlette's 405 names only the first)."""
    methods: set[str] = set()
    for route in iter_routes(request.app.router.routes):
        route_methods = getattr(route, "methods", None)
        if not route_methods:
            continue
        match, _ = route.matches(request.scope)
        if match in (Match.FULL, Match.PARTIAL):
            methods |= set(route_methods)
    if "GET" in methods:
        methods.add("HEAD")  # HeadMiddleware
    return sorted(methods)


def request_method(request: Request) -> str:
    """The method the client sent (HEAD where `HeadMiddleware` has the app answer it as a GET)."""
    return str(request.scope.get(_SENT_METHOD, request.method))


def sent_head(scope: Scope) -> bool:
    """Whether the client sent HEAD (`HeadMiddleware`): a streamed reply then sends its headers only."""
    return scope.get(_SENT_METHOD) == "HEAD"


class HeadMiddleware:
    """Every GET resource answers HEAD too, as RFC 9110 §9.3.2 asks of a general-purpose server: the same
    status and headers (`Content-Length` included), no body. FastAPI routes a HEAD to nothing (405), and
    probes and caches send one. Innermost of the edge, so the logs and metrics name the method sent.

    The GET runs whole, its body dropped here: a HEAD costs what its GET does, under the same limits,
    but for a streamed reply (`service.limits.ReadStreamingResponse`: a snapshot download, an export),
    which sends its headers and stops, so a HEAD never streams a snapshot's files to be thrown away.
    """

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def send_headers_only(message: Message) -> None:
            if message["type"] != "http.response.body":
                await send(message)
            elif not message.get("more_body", False):
                await send({"type": "http.response.body", "body": b"", "more_body": False})

        await self.app({**scope, "method": "GET", _SENT_METHOD: "HEAD"}, receive, send_headers_only)


