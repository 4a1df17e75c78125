"""The HTTP routes, one router per resource (docs/design/service.md §1), gathered in `api_router`.

`service.app.create_app` includes `api_router`; a new resource is a module here with its own `router`,
added below.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends, Request

from service.deps import ReadKeyDep
from service.errors import Problem, problem_responses
from service.routes import closures, health, maps, metrics, observations, recent, repair, snapshots

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
api_router.include_router(health.router)  # /healthz, /readyz: open to probes, whatever the key rules
# With CORTEXLOC_API_KEY_READS every /v1 route and /metrics need the key: map lists, stream names (robot
# names), sizes, snapshot lists and the metrics' map ids are not for anyone on the network either. A
# route added to these routers is guarded without naming it (writes check the key anyway).
api_router.include_router(metrics.router, dependencies=[ReadKeyDep], responses=problem_responses(401))
v1 = APIRouter(dependencies=[ReadKeyDep], responses=problem_responses(401))
for resource in (maps.router, maps.process_router, observations.router, recent.router, snapshots.router,
                 closures.router, repair.router):
    v1.include_router(resource)
api_router.include_router(v1)
