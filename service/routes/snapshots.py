"""Snapshots: create, list, restore, download (service.md §1.5)."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import APIRouter, Path, Response
from fastapi.responses import StreamingResponse

from service.deps import ApiKeyDep, RegistryDep
from service.errors import problem_responses
from storage import snapshots

router = APIRouter(prefix="/v1/maps/{map_id}/snapshots", tags=["snapshots"])

MapId = Annotated[str, Path(pattern=r"^[a-z0-9][a-z0-9._-]{0,63}$")]
SnapshotId = Annotated[str, Path(pattern=r"^[A-Za-z0-9._-]{1,80}$")]


@router.post("", status_code=201, dependencies=[ApiKeyDep], responses=problem_responses(401, 404, 503))
async def create_snapshot(map_id: MapId, registry: RegistryDep, response: Response) -> dict[str, Any]:
    rt = registry.get(map_id)
    rt.require_ready()
    snap = await rt.run(rt.snapshot, "manual")
    response.headers["Location"] = f"/v1/maps/{map_id}/snapshots/{snap['snapshot_id']}"
    return snap


@router.get("", responses=problem_responses(404))
async def list_snapshots(map_id: MapId, registry: RegistryDep) -> dict[str, Any]:
    rt = registry.get(map_id)
    return {"snapshots": await rt.run(rt.snapshots)}


@router.post("/{snapshot_id}/restore", dependencies=[ApiKeyDep], responses=problem_responses(401, 404, 503))
async def restore_snapshot(map_id: MapId, snapshot_id: SnapshotId, registry: RegistryDep) -> dict[str, Any]:
    rt = registry.get(map_id)
    rt.require_ready()
    return await rt.run(rt.restore, snapshot_id)


@router.get("/{snapshot_id}/download", responses={**problem_responses(404),
                                                    200: {"content": {"application/x-tar": {}}}})
async def download_snapshot(map_id: MapId, snapshot_id: SnapshotId,
                            registry: RegistryDep) -> StreamingResponse:
    rt = registry.get(map_id)
    directory = await rt.run(rt.snapshot_dir, snapshot_id)
    extra = {"projection.npy": rt.projection_path}
    size = snapshots.tar_size(directory, extra)

    def stream() -> Iterator[bytes]:
        # Spooled to a temporary file beside the map, not memory: the projection alone is 266 MB.
        with tempfile.TemporaryFile(dir=directory.parent) as f:
            snapshots.export_tar(directory, f, extra)
            f.seek(0)
            while chunk := f.read(1 << 20):
                yield chunk

    return StreamingResponse(stream(), media_type="application/x-tar", headers={
        "Content-Length": str(size),
        "Content-Disposition": f'attachment; filename="{map_id}-{snapshot_id}.tar"'})
