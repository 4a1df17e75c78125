"""Maps: create, list, get, delete, memory sizes, stream reset (docs/design/service.md §1.1, §1.3, §1.4)."""

from __future__ import annotations

import uuid
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Path, Response
from pydantic import BaseModel, ConfigDict, Field

from models.evaluation.bench import rss_mb
from service.deps import ApiKeyDep, RegistryDep, SettingsDep
from service.errors import problem_responses

router = APIRouter(prefix="/v1/maps", tags=["maps"])

MapId = Annotated[str, Path(pattern=r"^[a-z0-9][a-z0-9._-]{0,63}$", description="map identifier")]
StreamName = Annotated[str, Path(pattern=r"^[A-Za-z0-9._-]{1,64}$", description="stream name")]


class CreateMap(BaseModel):
    """Every field optional; overrides are merged over the preset and frozen into the map.

    `tm` and `slsbh` are checked parameter by parameter (names, types, ranges: `models.presets.TmParams`
    and `SlsbhParams`, with the rules between them) where the map's parameters are resolved
    (`service.runtime.resolve_params`): a bad value is 422 invalid-configuration naming it.
    """

    model_config = ConfigDict(extra="forbid")
    map_id: str | None = Field(default=None, pattern=r"^[a-z0-9][a-z0-9._-]{0,63}$")
    preset: str | None = None
    seed: int | None = Field(default=None, description="the TM's seed (and the projection's); >= 0")
    tm: dict[str, Any] | None = Field(default=None, description="Temporal Memory overrides, NuPIC names")
    slsbh: dict[str, Any] | None = Field(default=None, description="sLSBH overrides: k, s, seed, adapt_tau")
    exclude_recent: int = Field(default=0, ge=0)


@router.post("", status_code=201, dependencies=[ApiKeyDep],
             responses=problem_responses(400, 401, 409, 422))
async def create_map(body: CreateMap, registry: RegistryDep, settings: SettingsDep,
                     response: Response) -> dict[str, Any]:
    map_id = body.map_id or f"map-{uuid.uuid4().hex[:12]}"
    rt = await anyio.to_thread.run_sync(lambda: registry.create(
        map_id, preset=body.preset or settings.default_preset, seed=body.seed, tm=body.tm,
        slsbh_conf=body.slsbh, exclude_recent=body.exclude_recent))
    response.headers["Location"] = f"/v1/maps/{map_id}"
    return rt.resource()


@router.get("")
async def list_maps(registry: RegistryDep) -> dict[str, Any]:
    return {"maps": [rt.resource() for rt in registry.maps.values()]}


@router.get("/{map_id}", responses=problem_responses(404))
async def get_map(map_id: MapId, registry: RegistryDep) -> dict[str, Any]:
    return registry.get(map_id).resource()


@router.delete("/{map_id}", status_code=204, dependencies=[ApiKeyDep], responses=problem_responses(401, 404))
async def delete_map(map_id: MapId, registry: RegistryDep) -> Response:
    registry.get(map_id)
    await anyio.to_thread.run_sync(registry.delete, map_id)
    return Response(status_code=204)


@router.get("/{map_id}/memory", responses=problem_responses(404))
async def map_memory(map_id: MapId, registry: RegistryDep) -> dict[str, Any]:
    rt = registry.get(map_id)
    out = await rt.run(rt.memory)
    out["process_rss_bytes"] = int(rss_mb() * 2**20)
    return out


@router.post("/{map_id}/streams/{stream}/reset", dependencies=[ApiKeyDep],
             responses=problem_responses(401, 404))
async def reset_stream(map_id: MapId, stream: StreamName, registry: RegistryDep) -> dict[str, Any]:
    rt = registry.get(map_id)
    return await rt.run(rt.reset_stream, stream)
