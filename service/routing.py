"""The app's routes as a flat list (route templates for the metrics, the methods of a path for a 405)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

from fastapi import Request
from starlette.routing import Match

__all__ = ["allowed_methods", "iter_routes"]


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
    return sorted(methods)


