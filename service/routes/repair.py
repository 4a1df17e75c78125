"""A map's repair of merges made from a stream's own recent trail (docs/design/service.md §1.2,
docs/design/science.md §11.6): the listing, and the repair that undoes them."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter

from service.deps import ApiKeyDep, RegistryDep
from service.errors import problem_responses
from service.routes.params import MapId
from service.schemas import RepairModel

router = APIRouter(prefix="/v1/maps", tags=["maps"])


@router.get("/{map_id}/repair", responses=problem_responses(404, 503))
async def list_own_trail_merges(map_id: MapId, registry: RegistryDep) -> RepairModel:
    """The merges a repair would undo, changing nothing: visits (consolidated frames) and place joins
    into a row of the stream's own recent trail, and the loop closures that named one."""
    rt = registry.get(map_id)
    # shared by the requests that come while it runs: one whose client leaves must not cancel it
    return RepairModel.from_result(await asyncio.shield(asyncio.wrap_future(rt.own_trail_merges())))


@router.post("/{map_id}/repair", dependencies=[ApiKeyDep],
             responses=problem_responses(401, 404, 409, 503, 507))
async def repair_map(map_id: MapId, registry: RegistryDep) -> RepairModel:
    """Undo them, durably and in one transaction: each visit re-made as its own row, each row given back
    its own place, each such loop closure retracted by a new entry of the log (`retracts`). Idempotent:
    a second repair finds nothing. 409 map-full or memory-budget when the re-made rows do not fit
    (nothing changes)."""
    rt = registry.get(map_id)
    return RepairModel.from_result(await rt.run(rt.repair))
