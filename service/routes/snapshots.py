"""Snapshots: create, list, delete, restore, download (docs/design/service.md §1.5)."""

from __future__ import annotations

import anyio
from fastapi import APIRouter, Response

from service.deps import ApiKeyDep, RegistryDep
from service.errors import problem_responses
from service.limits import REPLY_CHUNK_BYTES, ReadStreamingResponse
from service.maps.recovery import snapshots
from service.media_types import TAR_MEDIA_TYPE
from service.routes.params import MapId, SnapshotId
from service.schemas import RestoreModel, SnapshotList, SnapshotModel

router = APIRouter(prefix="/v1/maps/{map_id}/snapshots", tags=["snapshots"])



@router.post("", status_code=201, dependencies=[ApiKeyDep], responses=problem_responses(401, 404, 503, 507))
async def create_snapshot(map_id: MapId, registry: RegistryDep, response: Response) -> SnapshotModel:
    rt = registry.get(map_id)
    rt.require_ready()
    snap = await rt.run(rt.snapshot, "manual")
    response.headers["Location"] = f"/v1/maps/{map_id}/snapshots/{snap.snapshot_id}"
    return SnapshotModel.from_result(snap)


@router.get("", responses=problem_responses(404))
async def list_snapshots(map_id: MapId, registry: RegistryDep) -> SnapshotList:
    rt = registry.get(map_id)
    return SnapshotList(snapshots=[SnapshotModel.from_result(s) for s in await rt.run(rt.snapshots)])


@router.delete("/{snapshot_id}", status_code=204, dependencies=[ApiKeyDep],
               responses=problem_responses(401, 404, 409, 503))
async def delete_snapshot(map_id: MapId, snapshot_id: SnapshotId, registry: RegistryDep) -> Response:
    """Delete one snapshot (any kind); 409 snapshot-in-use for the one the map recovers from."""
    rt = registry.get(map_id)
    await rt.run(rt.delete_snapshot, snapshot_id)
    return Response(status_code=204)


@router.post("/{snapshot_id}/restore", dependencies=[ApiKeyDep],
             responses=problem_responses(401, 404, 409, 503, 507))
async def restore_snapshot(map_id: MapId, snapshot_id: SnapshotId, registry: RegistryDep) -> RestoreModel:
    rt = registry.get(map_id)
    rt.require_ready()
    return RestoreModel.from_result(await rt.run(rt.restore, snapshot_id))


class TarExportResponse(ReadStreamingResponse):
    """Streams a `TarExport` chunk by chunk (file reads in worker threads) and releases its file
    descriptors however the response ends: sent, client gone (Starlette cancels the stream), stalled
    (`ReadStreamingResponse`), or error."""

    media_type = TAR_MEDIA_TYPE  # what the OpenAPI declares for the route (`response_class`)

    def __init__(self, export: snapshots.TarExport, filename: str) -> None:
        super().__init__(export.chunks(REPLY_CHUNK_BYTES), media_type=TAR_MEDIA_TYPE, headers={
            "Content-Length": str(export.size), "Content-Disposition": f'attachment; filename="{filename}"'})
        self.export = export

    def on_close(self) -> None:
        self.export.close()


@router.get("/{snapshot_id}/download", response_class=TarExportResponse, status_code=200,
            responses={**problem_responses(401, 404, 409, 503), 200: {
                "description": "the snapshot as a tar", "content": {TAR_MEDIA_TYPE: {
                    "schema": {"type": "string", "format": "binary"}}}}})
async def download_snapshot(map_id: MapId, snapshot_id: SnapshotId,
                            registry: RegistryDep) -> TarExportResponse:
    """The snapshot as a tar (manifest.json, map.sqlite, memory.npz, projection.npy), streamed from its
    files with no copy; every checksum is verified before the first byte (409 snapshot-invalid if not)."""
    rt = registry.get(map_id)
    directory = await rt.run(rt.snapshot_dir, snapshot_id)
    export = await anyio.to_thread.run_sync(snapshots.export, directory, rt.projection_path)
    return TarExportResponse(export, f"{map_id}-{snapshot_id}.tar")
