"""Maps: create, list, get, delete, memory sizes, stream reset (docs/design/service.md §1.1, §1.3, §1.4)."""

from __future__ import annotations

import functools

import anyio
from fastapi import APIRouter, Response

from service.deps import ApiKeyDep, RegistryDep
from service.errors import problem_responses
from service.maps.config import MapOptions
from service.maps.ids import new_map_id
from service.routes.params import REPLAY_HEADER, IdempotencyKey, MapId, StreamName
from service.schemas import (
    BudgetModel,
    CreateMap,
    MapList,
    MapModel,
    MemoryModel,
    PatchMap,
    StreamResetModel,
)

router = APIRouter(prefix="/v1/maps", tags=["maps"])
#: Resources of the whole process beside the maps (`GET /v1/memory`).
process_router = APIRouter(prefix="/v1", tags=["maps"])


@process_router.get("/memory")
async def process_memory(registry: RegistryDep) -> BudgetModel:
    """The memory budget: total, used, free, the encoders and each map's share (§1.8)."""
    return BudgetModel.from_result(await anyio.to_thread.run_sync(registry.memory_budget))

@router.post("", status_code=201, dependencies=[ApiKeyDep],
             responses=problem_responses(400, 401, 409, 415, 422, 507))
async def create_map(
    body: CreateMap, registry: RegistryDep, response: Response,
    idempotency_key: IdempotencyKey = None,
) -> MapModel:
    """A new map (201). With an `Idempotency-Key`, a retry answers the map its first try made (§1.1)."""
    map_id = body.map_id or new_map_id(idempotency_key)
    # the members as sent: a keyed creation is told from another by them (MapOptions.digest)
    options = MapOptions.model_validate(body.model_dump(exclude={"map_id"}, exclude_unset=True))
    if idempotency_key is None:
        rt = await anyio.to_thread.run_sync(registry.create, map_id, options)
    else:
        rt, created = await anyio.to_thread.run_sync(registry.create_or_replay, map_id, options,
                                                     idempotency_key)
        if not created:
            response.status_code = 200
            response.headers[REPLAY_HEADER] = "true"
    response.headers["Location"] = f"/v1/maps/{map_id}"
    return MapModel.from_result(await rt.run(rt.info))


@router.get("")
async def list_maps(registry: RegistryDep) -> MapList:
    return MapList(maps=[MapModel.from_result(await rt.run(rt.info)) for rt in list(registry.maps.values())])


@router.get("/{map_id}", responses=problem_responses(404))
async def get_map(map_id: MapId, registry: RegistryDep) -> MapModel:
    rt = registry.get(map_id)
    return MapModel.from_result(await rt.run(rt.info))


@router.patch("/{map_id}", dependencies=[ApiKeyDep],
              responses=problem_responses(400, 401, 404, 415, 422, 503, 507))
async def patch_map(map_id: MapId, body: PatchMap, registry: RegistryDep) -> MapModel:
    """Change the map's settings that may change after creation (durable): `revisit_threshold`,
    `verify_revisit` (a revisit needs a verified keyframe; maps with keyframes only)."""
    rt = registry.get(map_id)
    return MapModel.from_result(await rt.run(functools.partial(
        rt.patch, revisit_threshold=body.revisit_threshold, verify_revisit=body.verify_revisit)))


@router.delete("/{map_id}", status_code=204, dependencies=[ApiKeyDep], responses=problem_responses(401, 404))
async def delete_map(map_id: MapId, registry: RegistryDep) -> Response:
    registry.get(map_id)
    await anyio.to_thread.run_sync(registry.delete, map_id)
    return Response(status_code=204)


@router.get("/{map_id}/memory", responses=problem_responses(404, 503))
async def map_memory(map_id: MapId, registry: RegistryDep) -> MemoryModel:
    rt = registry.get(map_id)
    return MemoryModel.from_result(await rt.run(rt.memory))


# `{stream:path}`: a ROS-style name holds '/', which arrives percent-decoded in the path.
@router.post("/{map_id}/streams/{stream:path}/reset", dependencies=[ApiKeyDep],
             responses=problem_responses(401, 404, 503, 507))
async def reset_stream(map_id: MapId, stream: StreamName, registry: RegistryDep) -> StreamResetModel:
    rt = registry.get(map_id)
    return StreamResetModel.from_result(await rt.run(rt.reset_stream, stream))
