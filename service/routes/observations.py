"""Observations: image in, ranked matches out (docs/design/service.md §1.2).

The route checks the request and the image's header, hands the bytes to the map
(`MapRuntime.observe`: encoder pool, then the map's writer) and turns its `ObservationResult` into the
reply, adding what only the HTTP layer knows: the request id, the code's and encoder's versions, the
total time.
"""

from __future__ import annotations

import functools
import time
from typing import Annotated

import anyio
from fastapi import APIRouter, Path, Query, Request

from models.frontend import images
from service.deps import ApiKeyDep, EncoderDep, MetricsDep, RegistryDep, SettingsDep
from service.errors import IMAGE_MEDIA_TYPES, Problem, problem_responses
from service.schemas import MAP_ID_PATTERN, MatchModel, ObservationModel, SequenceModel, Versions

router = APIRouter(prefix="/v1/maps", tags=["observations"])

_DECLARED = {"image/jpeg": "jpeg", "image/png": "png"}

_BINARY_BODY = {"requestBody": {"required": True, "content": {
    t: {"schema": {"type": "string", "format": "binary"}} for t in IMAGE_MEDIA_TYPES}}}


@router.post("/{map_id}/observations", dependencies=[ApiKeyDep], openapi_extra=_BINARY_BODY,
             responses=problem_responses(400, 401, 404, 409, 413, 415, 422, 503, 507))
async def post_observation(
    request: Request,
    map_id: Annotated[str, Path(pattern=MAP_ID_PATTERN)],
    registry: RegistryDep,
    encoder: EncoderDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    learn: Annotated[bool, Query(description="true: mapping (stored, learned); false: localisation")] = True,
    top_k: Annotated[int, Query(ge=0, description="matches to return (0: none; `place` is still answered)")]
    = 5,
    stream: Annotated[str, Query(pattern=r"^[A-Za-z0-9._-]{1,64}$")] = "default",
    label: Annotated[str | None, Query(max_length=200)] = None,
) -> ObservationModel:
    """Post one camera frame as the raw body (`image/jpeg`, `image/png` or `application/octet-stream`)."""
    t_start = time.perf_counter()
    if top_k > settings.max_top_k:
        raise Problem(400, "invalid-parameter", f"top_k must be at most {settings.max_top_k}",
                      errors=[{"location": "query", "name": "top_k", "message": f"<= {settings.max_top_k}"}])
    rt = registry.get(map_id)
    rt.require_ready()
    media = (request.headers.get("content-type") or "").split(";")[0].strip().lower()
    if media not in IMAGE_MEDIA_TYPES:
        raise Problem(415, "unsupported-media-type", f"Content-Type {media or '(none)'!r} is not accepted",
                      allowed=list(IMAGE_MEDIA_TYPES), detected=media or None)
    body = await request.body()
    # Every input check runs before anything stateful: the header (size, pixels, aspect, decoding cost)
    # here, off the event loop (a chunk walk may take milliseconds), the full decode in the encoder pool.
    info = await anyio.to_thread.run_sync(functools.partial(
        images.probe, body, max_bytes=settings.max_upload_bytes, max_pixels=settings.max_pixels,
        formats=("jpeg", "png")))
    if media in _DECLARED and _DECLARED[media] != info.format:
        raise Problem(415, "unsupported-media-type", f"declared {media} but the bytes are {info.format}",
                      allowed=list(IMAGE_MEDIA_TYPES), detected=info.format)
    result = await rt.observe(request.app.state.encoder_pool, body, learn=learn, stream=stream,
                              top_k=top_k, label=label)
    timings = {**result.timings_ms, "total": (time.perf_counter() - t_start) * 1e3}
    for stage, ms in timings.items():
        if stage != "total":
            metrics.observe_stage(stage, ms / 1e3)
    metrics.observations.labels(map=map_id, learned=str(learn).lower()).inc()
    desc = registry.encoders.get(result.backbone).describe()  # the map's own backbone's encoder
    reply = ObservationModel(
        request_id=getattr(request.state, "request_id", None), map_id=result.map_id, stream=result.stream,
        learned=result.learned, observation_id=result.observation_id, seq=result.seq,
        sequence=SequenceModel.from_result(result.sequence),
        matches=[MatchModel.from_result(m) for m in result.matches],
        place=result.place,
        timings_ms={k: round(v, 3) for k, v in timings.items()},
        versions=Versions(api="v1", code=request.app.version, backbone=result.backbone,
                          encoder=desc["encoder"], weights=desc["weights"],
                          projection=f"sha256:{result.projection_sha256}", map_seq=result.map_seq))
    rt.recent.add(result.stream, reply)  # the viewer's window (GET .../recent): the reply as sent
    return reply
