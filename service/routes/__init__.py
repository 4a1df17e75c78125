"""The HTTP routes, one router per resource (service.md §1), gathered in `api_router`.

`service.app.create_app` includes `api_router`; a new resource is a module here with its own `router`,
added below.
"""

from __future__ import annotations

from fastapi import APIRouter

from service.routes import health, maps, metrics, observations, snapshots

__all__ = ["api_router"]

api_router = APIRouter()
api_router.include_router(health.router)
api_router.include_router(metrics.router)
api_router.include_router(maps.router)
api_router.include_router(observations.router)
api_router.include_router(snapshots.router)
