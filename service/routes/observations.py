"""Observations: image in, ranked matches out (docs/design/service.md §1.2)."""

from __future__ import annotations

import functools
import hashlib
import time
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Path, Query, Request

from models.frontend import images
from service.deps import ApiKeyDep, EncoderDep, MetricsDep, RegistryDep, SettingsDep
from service.errors import Problem, problem_responses

router = APIRouter(prefix="/v1/maps", tags=["observations"])

MEDIA_TYPES = ("image/jpeg", "image/png", "application/octet-stream")
_DECLARED = {"image/jpeg": "jpeg", "image/png": "png"}

_BINARY_BODY = {"requestBody": {"required": True, "content": {
    t: {"schema": {"type": "string", "format": "binary"}} for t in MEDIA_TYPES}}}


@router.post("/{map_id}/observations", dependencies=[ApiKeyDep], openapi_extra=_BINARY_BODY,
             responses=problem_responses(400, 401, 404, 409, 413, 415, 422, 503))
async def post_observation(
    request: Request,
    map_id: Annotated[str, Path(pattern=r"^[a-z0-9][a-z0-9._-]{0,63}$")],
    registry: RegistryDep,
    encoder: EncoderDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    learn: Annotated[bool, Query(description="true: mapping (stored, learned); false: localisation")] = True,
    top_k: Annotated[int, Query(ge=0, description="matches to return (0 skips ranking)")] = 5,
    stream: Annotated[str, Query(pattern=r"^[A-Za-z0-9._-]{1,64}$")] = "default",
    label: Annotated[str | None, Query(max_length=200)] = None,
) -> dict[str, Any]:
    """Post one camera frame as the raw body (`image/jpeg`, `image/png` or `application/octet-stream`)."""
    t_start = time.perf_counter()
    if top_k > settings.max_top_k:
        raise Problem(400, "invalid-parameter", f"top_k must be at most {settings.max_top_k}",
                      errors=[{"location": "query", "name": "top_k", "message": f"<= {settings.max_top_k}"}])
    rt = registry.get(map_id)
    rt.require_ready()
    media = (request.headers.get("content-type") or "").split(";")[0].strip().lower()
    if media not in MEDIA_TYPES:
        raise Problem(415, "unsupported-media-type", f"Content-Type {media or '(none)'!r} is not accepted",
                      allowed=list(MEDIA_TYPES), detected=media or None)
    body = await request.body()
    # Every input check runs before anything stateful: the header (size, pixels, aspect, decoding cost)
    # here, off the event loop (a chunk walk may take milliseconds), the full decode in the encoder's
    # thread.
    info = await anyio.to_thread.run_sync(functools.partial(
        images.probe, body, max_bytes=settings.max_upload_bytes, max_pixels=settings.max_pixels,
        formats=("jpeg", "png")))
    if media in _DECLARED and _DECLARED[media] != info.format:
        raise Problem(415, "unsupported-media-type", f"declared {media} but the bytes are {info.format}",
                      allowed=list(MEDIA_TYPES), detected=info.format)
    t_checked = time.perf_counter()
    # The ticket: the encoding starts now, concurrently with others, and the writer job is queued now,
    # so the map's memory sees frames in the order their requests passed the checks.
    # The pool projects with the map's own matrix, batched with other requests (service.encoding).
    encoding = request.app.state.encoder_pool.submit(body, hasher=rt.hasher)
    image_sha = hashlib.sha256(body).hexdigest()
    stamps: dict[str, float] = {}

    def step() -> dict[str, Any]:
        embedded = encoding.result()  # an ImageError surfaces here, before anything stateful
        stamps["encoded"] = time.perf_counter()
        stamps["decode"] = embedded.timings_ms["decode"]
        return rt.observe(embedded.features[0], image_sha, learn=learn, stream=stream, top_k=top_k,
                          label=label,
                          projected=None if embedded.projected is None else embedded.projected[0])

    result = await rt.run(step)
    t_done = time.perf_counter()
    t_encoded = stamps["encoded"]
    desc = encoder.describe()
    timings = {"decode": stamps["decode"], "encode": (t_encoded - t_checked) * 1e3,
               **result.pop("timings_ms"), "total": (t_done - t_start) * 1e3}
    map_seq = result.pop("map_seq")
    for stage, ms in timings.items():
        if stage != "total":
            metrics.observe_stage(stage, ms / 1e3)
    metrics.observations.labels(map=map_id, learned=str(learn).lower()).inc()
    return {"request_id": getattr(request.state, "request_id", None), "map_id": map_id, "stream": stream,
            **result, "timings_ms": {k: round(v, 3) for k, v in timings.items()},
            "versions": {"api": "v1", "code": request.app.version, "encoder": desc["encoder"],
                         "weights": desc["weights"], "projection": f"sha256:{rt.params['projection_sha256']}",
                         "map_seq": map_seq}}
