"""A map's loop-closure log (docs/design/service.md §1.2, docs/design/science.md §11.6): a typed page, and
the export of candidate pairs (CSV or JSON lines) for pose-graph back ends that verify pairs themselves."""

from __future__ import annotations

from typing import Annotated, Literal

import anyio
from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse

from service.deps import RegistryDep
from service.errors import problem_responses
from service.limits import REPLY_CHUNK_BYTES, ReadStreamingResponse
from service.maps import closures
from service.routes.params import DECIMAL, MapId
from service.schemas import LoopClosureList, LoopClosureModel

router = APIRouter(prefix="/v1/maps", tags=["loop closures"])

#: Loop closures per page of `GET /v1/maps/{id}/loop-closures`.
MAX_PAGE = 500
#: The most log ids a cursor can name (SQLite's INTEGER).
MAX_ID = 2**63 - 1


@router.get("/{map_id}/loop-closures", responses=problem_responses(404, 503))
async def list_loop_closures(
    map_id: MapId, registry: RegistryDep,
    after: Annotated[int, Query(ge=0, le=MAX_ID, description="the page starts after this log id"),
                     DECIMAL] = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE), DECIMAL] = 100,
) -> LoopClosureList:
    """The revisits streams were told of, oldest first: learning streams' with the row that saw them."""
    rt = registry.get(map_id)
    rt.require_ready(learns=False)
    assert rt.store is not None
    page = await anyio.to_thread.run_sync(closures.page, rt.store, after, limit)
    found = page.entries
    return LoopClosureList(loop_closures=[LoopClosureModel.from_result(c) for c in found],
                           next_after=found[-1].id if len(found) == limit else None, oldest=page.oldest,
                           newest=page.newest, epoch=rt.epoch)


@router.get("/{map_id}/loop-closures/export",
            response_class=StreamingResponse, responses={**problem_responses(404, 503), 200: {
                "content": {t.split(";")[0]: {"schema": {"type": "string"}}
                            for t in closures.EXPORT_FORMATS.values()}}})
async def export_loop_closures(
    map_id: MapId, registry: RegistryDep,
    format: Annotated[Literal["csv", "jsonl", "g2o"], Query(
        description="csv | jsonl | g2o (the verified closures as EDGE_SE3:QUAT lines, in the "
                    "body axes of the VERTEX_SE3:QUAT lines declared for every id they name)")] = "csv",
) -> StreamingResponse:
    """Every logged loop closure as a candidate pair: both stamps in seconds, both ids, the confidence,
    both poses where given, the geometric verification and relative pose where the map keeps keyframes
    (`closures.EXPORT_COLUMNS`); or, as g2o, the verified ones with a pose (`closures.g2o_lines`)."""
    rt = registry.get(map_id)
    rt.require_ready(learns=False)
    assert rt.store is not None
    # Rendered whole first: a failure is an error answer, never a 200 with a short body.
    spool = await anyio.to_thread.run_sync(closures.render, rt.store, format)
    # (a client that stops reading is cut, `ReadStreamingResponse`; the spool closes with its generator)
    return ReadStreamingResponse(closures.chunks(spool, REPLY_CHUNK_BYTES),
                                 media_type=closures.EXPORT_FORMATS[format],
                                 headers={"Content-Disposition": f'attachment; filename="{map_id}-loop-'
                                                                 f'closures.{format}"'})
