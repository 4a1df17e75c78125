"""`GET /metrics`: the Prometheus text format of the app's own registry (docs/design/service.md §1.6)."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST

from service.metrics import Metrics

__all__ = ["router"]

router = APIRouter(tags=["operations"])


@router.get("/metrics", response_class=Response,
            responses={200: {"description": "Prometheus text format",
                             "content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}}}})
def metrics(request: Request) -> Response:
    """Prometheus text format (`cortexloc_*`)."""
    m: Metrics = request.app.state.metrics
    m.update_maps(getattr(request.app.state, "maps", None) or {})
    registry = getattr(request.app.state, "registry", None)
    if registry is not None:
        m.update_budget(registry.budget.total, registry.budget.used())
    return Response(m.render(), media_type=CONTENT_TYPE_LATEST)
