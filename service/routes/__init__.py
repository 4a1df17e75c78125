"""The HTTP routes, one router per resource (docs/design/service.md §1), gathered in `api_router`.

`service.app.create_app` includes `api_router`; a new resource is a module here with its own `router`,
added below.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from service.errors import Problem
from service.routes import closures, health, maps, metrics, observations, recent, snapshots

__all__ = ["api_router", "refuse_repeated_query_parameters"]


def refuse_repeated_query_parameters(request: Request) -> None:
    """A query parameter given twice is ambiguous (FastAPI would silently take the last one).

    Raises:
        Problem: 400 invalid-parameter naming each repeated parameter.
    """
    names = [name for name, _ in request.query_params.multi_items()]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise Problem(400, "invalid-parameter",
                      f"query parameter(s) given more than once: {', '.join(repeated)}; give each once",
                      errors=[{"location": "query", "name": name, "message": "given more than once"}
                              for name in repeated])


# Every route: `?learn=false&learn=true` is a 400, not a guess.
api_router = APIRouter(dependencies=[Depends(refuse_repeated_query_parameters)])
api_router.include_router(health.router)
api_router.include_router(metrics.router)
api_router.include_router(maps.router)
api_router.include_router(observations.router)
api_router.include_router(recent.router)
api_router.include_router(snapshots.router)
api_router.include_router(closures.router)
