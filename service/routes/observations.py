"""Observations: image in, ranked matches out; stored observations and their thumbnails read back
(docs/design/service.md §1.2).

The route checks the request and the image's header, hands the frame to the map
(`MapRuntime.observe`: encoder pool, then the map's writer) and turns its `ObservationResult` into the
reply, adding what only the HTTP layer knows: the request id, the code's and encoder's versions, the
total time. A post with an `Idempotency-Key` is answered with its sealed reply, the first one's for a
repeat (`service.maps.runtime.idempotency`).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import hashlib
import json
import math
import re
import time
from collections.abc import AsyncIterator
from datetime import datetime
from typing import Annotated, Any

import anyio
from fastapi import APIRouter, Query, Request, Response
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from models.frontend import images
from models.localisation.motion import stamp_seconds
from service.deps import ApiKeyDep, MetricsDep, RegistryDep, SettingsDep
from service.errors import Problem, problem_responses
from service.maps.departure import Departure
from service.maps.results import ObservationResult
from service.maps.runtime import idempotency, stored
from service.media_types import IMAGE_MEDIA_TYPES
from service.routes.params import (
    DECIMAL,
    MAX_SEQ,
    REPLAY_HEADER,
    IdempotencyKey,
    MapId,
    Seq,
    StreamQuery,
    duplicate_keys,
)
from service.schemas import (
    STREAM_PATTERN,
    MatchModel,
    ObservationModel,
    SequenceModel,
    StoredObservationList,
    StoredObservationModel,
    Versions,
)

router = APIRouter(prefix="/v1/maps", tags=["observations"])


_DECLARED = {"image/jpeg": "jpeg", "image/png": "png", "image/webp": "webp", "image/bmp": "bmp"}
#: Per-observation metadata (docs/design/service.md §1.2): compact JSON in the `metadata` query parameter.
METADATA_MAX_BYTES = 4096
METADATA_MAX_DEPTH = 8
#: The largest integer magnitude metadata may hold: 2^53 - 1, JavaScript's `Number.MAX_SAFE_INTEGER` and
#: I-JSON's bound (RFC 7493 §2.2). A larger integer reaches a JSON reader that uses doubles (the viewer,
#: most clients) rounded, or as Infinity past ~1.8e308: send it as a string (an id).
METADATA_MAX_INT = 2**53 - 1
#: The accepted pose coordinates, |x| and |y| at most this (docs/design/service.md §1.2): 10^6 km covers
#: every Earth frame in metres (UTM northings reach 10^7, ECEF 6.4 x 10^6) with room; a larger value is a
#: unit or sensor fault, and at 10^16 the doubles are 2 m apart, so it could not say where anyway.
POSE_MAX_ABS = 1e9
#: The accepted |yaw|, radians: an odometry that does not wrap its heading may count turns (10^6 rad is
#: some 160,000 of them, still exact to 10^-10 rad); more is a unit fault, and the g2o export's
#: quaternion (sin and cos of yaw / 2) of 10^300 is noise.
YAW_MAX_ABS = 1e6
#: The latest `stamp` accepted, in seconds since the epoch (10^11 s: the year 5138). Stamps are seconds:
#: one in milliseconds (~1.7 x 10^12 today), microseconds or nanoseconds read as seconds lies far beyond
#: it, and would quietly turn off what the service reads in stamps (a drive's gap and speed, §1.2).
STAMP_MAX_S = 1e11
#: Stored observations per page of `GET /v1/maps/{id}/observations`.
MAX_PAGE = 500

_BINARY_BODY = {"requestBody": {"required": True, "content": {
    t: {"schema": {"type": "string", "format": "binary"}} for t in IMAGE_MEDIA_TYPES}}}


class _Pose(BaseModel):
    model_config = ConfigDict(extra="allow", strict=True)  # strict: `true` is not a coordinate
    x: float = Field(ge=-POSE_MAX_ABS, le=POSE_MAX_ABS)
    y: float = Field(ge=-POSE_MAX_ABS, le=POSE_MAX_ABS)
    yaw: float | None = Field(None, ge=-YAW_MAX_ABS, le=YAW_MAX_ABS)
    frame_id: str | None = None


#: A camera's focal lengths and principal point, in pixels, are at most this (a 100-megapixel sensor's
#: focal length in pixels is ~10^4; more is a unit fault).
CAMERA_MAX_PX = 1e6
#: OpenCV's distortion vector lengths: none, (k1 k2 p1 p2), + k3, + k4 k5 k6, + s1..s4, + taux tauy.
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


class _Camera(BaseModel):
    """The stream's pinhole camera (docs/design/science.md §12.3), given once per stream or with each
    frame: pixels of the frame as posted, OpenCV's distortion coefficients."""

    model_config = ConfigDict(extra="forbid", strict=True)
    fx: float = Field(gt=0, le=CAMERA_MAX_PX)
    fy: float = Field(gt=0, le=CAMERA_MAX_PX)
    cx: float = Field(ge=-CAMERA_MAX_PX, le=CAMERA_MAX_PX)
    cy: float = Field(ge=-CAMERA_MAX_PX, le=CAMERA_MAX_PX)
    distortion: list[float] = Field(default_factory=list)

    @field_validator("distortion")
    @classmethod
    def _lengths(cls, v: list[float]) -> list[float]:
        if len(v) not in DISTORTION_LENGTHS:
            raise ValueError(f"distortion has {len(v)} coefficients; OpenCV takes "
                             f"{', '.join(map(str, DISTORTION_LENGTHS))}")
        if not all(math.isfinite(x) and abs(x) <= 1e3 for x in v):
            raise ValueError("distortion coefficients must be finite, |k| <= 1000")
        return v


#: A stamp sent as text that is a number: ASCII decimal, an optional sign, fraction and exponent.
_NUMERIC_STAMP = re.compile(r"[+-]?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][+-]?[0-9]+)?")


class _Metadata(BaseModel):
    """What the service reads in metadata; any other small JSON members are kept as they are."""

    model_config = ConfigDict(extra="allow", strict=True)
    stamp: float | str | None = None
    pose: _Pose | None = None
    camera: _Camera | None = None
    # the short-term memory the stream shares (docs/design/science.md §11.6): a stream name
    trail: str | None = Field(None, pattern=STREAM_PATTERN)

    @field_validator("stamp")
    @classmethod
    def _seconds(cls, v: float | str | None) -> float | str | None:
        if isinstance(v, str) and not _NUMERIC_STAMP.fullmatch(v):
            # text that is no plain number must be ISO 8601: Python's float() also reads " 17 ", "1_7" and
            # other scripts' digits, and an unreadable stamp was stored and read as none (an outside probe)
            try:
                datetime.fromisoformat(v)
            except ValueError:
                shown = v if len(v) <= 24 else v[:24] + "..."
                raise ValueError(f"{shown!r} is neither seconds written in plain decimal (ASCII digits, "
                                 "no spaces) nor ISO 8601 text") from None
        seconds = stamp_seconds({"stamp": v}, finite=False)
        # `not <=`: a numeric string that overflows a double ("1e400", 400 nines) reads as inf, and "nan" as
        # NaN; stored, either would read back as no stamp, so each is refused like "1e300"
        if seconds is not None and not abs(seconds) <= STAMP_MAX_S:
            shown = str(v) if len(str(v)) <= 24 else str(v)[:24] + "..."
            raise ValueError(f"{shown} read as seconds since the epoch is not a finite number within "
                             "±10^11 s (the year 5138): stamps are seconds (a millisecond or nanosecond stamp"
                             " divided by 10^3 or 10^9)")
        return v


def _depth(text: str) -> int:
    """The deepest nesting of objects and arrays in JSON `text`, read before parsing it (a parser
    recursing 2,000 brackets deep is itself the failure)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            escaped, in_string = (False, True) if escaped else (ch == "\\", ch != '"')
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _finite(literal: str) -> float:
    value = float(literal)
    if not math.isfinite(value):
        raise ValueError(f"{literal} is not a finite number")
    return value


def _safe_int(literal: str) -> int:
    value = int(literal)
    if abs(value) > METADATA_MAX_INT:
        shown = literal if len(literal) <= 24 else literal[:24] + "..."
        raise ValueError(f"integer {shown} is beyond +-(2^53 - 1), which a JSON reader using doubles "
                         "cannot hold exactly; send it as a string")
    return value


def _no_constant(name: str) -> float:
    raise ValueError(f"{name} is not JSON")


def parse_metadata(text: str) -> dict[str, Any]:
    """The `metadata` query parameter as a JSON object. Raises Problem 422 invalid-metadata: longer than
    `METADATA_MAX_BYTES`, not JSON, not an object, nested deeper than `METADATA_MAX_DEPTH`, or a
    `stamp` / `pose` of the wrong shape, or an object that gives a member twice."""
    def bad(message: str, **members: Any) -> Problem:
        return Problem(422, "invalid-metadata", f"metadata: {message}", **members)

    size = len(text.encode())
    if size > METADATA_MAX_BYTES:
        raise bad(f"{size} bytes, more than {METADATA_MAX_BYTES}", max_bytes=METADATA_MAX_BYTES)
    if _depth(text) > METADATA_MAX_DEPTH:
        raise bad(f"nested deeper than {METADATA_MAX_DEPTH} levels", max_depth=METADATA_MAX_DEPTH)
    try:
        # Only numbers every JSON reader holds as sent (NaN, Infinity and 1e400 would be stored as null, a
        # 400-digit integer read as Infinity by JavaScript) and only text that is valid UTF-8 once stored
        # (a lone surrogate escape such as "\ud800" is not).
        value = json.loads(text, parse_float=_finite, parse_int=_safe_int, parse_constant=_no_constant)
        json.dumps(value, ensure_ascii=False).encode()
    except (ValueError, UnicodeEncodeError) as e:
        raise bad(f"not JSON that can be stored ({e})") from e
    if not isinstance(value, dict):
        raise bad(f"must be a JSON object, not {type(value).__name__}")
    if twice := duplicate_keys(text):  # stored, one of the two would be lost without a word
        raise bad(f"member(s) given more than once in one object: {', '.join(map(repr, twice[:10]))}",
                  errors=[{"location": "query", "name": f"metadata.{name}", "message": "given more than once"}
                          for name in twice[:10]])
    try:
        _Metadata.model_validate(value)
    except ValidationError as e:
        raise bad("; ".join(f"{'.'.join(map(str, err['loc']))}: {err['msg']}" for err in e.errors()),
                  errors=[{"location": "query", "name": "metadata." + ".".join(map(str, err["loc"])),
                           "message": err["msg"]} for err in e.errors()]) from e
    return value


def _frame(body: bytes, media: str, encoding: str | None, width: int | None,
           height: int | None) -> bytes | images.RawFrame:
    """The body as the decoder takes it: a raw frame when `encoding` is given, else encoded bytes."""
    if encoding is None:
        if width is not None or height is not None:
            raise Problem(400, "invalid-parameter", "width and height describe a raw frame: send encoding",
                          errors=[{"location": "query", "name": "encoding", "message": "required"}])
        return body
    missing = [name for name, v in (("width", width), ("height", height)) if v is None]
    if missing or media != "application/octet-stream":
        raise Problem(400, "invalid-parameter",
                      f"a raw frame is sent as application/octet-stream with encoding, width and height"
                      f" (missing: {', '.join(missing) or 'none'}; Content-Type {media!r})",
                      errors=[{"location": "query", "name": n, "message": "required"} for n in missing])
    assert width is not None and height is not None
    return images.RawFrame(body, encoding, width, height)


@router.post("/{map_id}/observations", dependencies=[ApiKeyDep], openapi_extra=_BINARY_BODY,
             response_model=ObservationModel,
             responses=problem_responses(400, 401, 404, 409, 413, 415, 422, 503, 507))
async def post_observation(
    request: Request,
    map_id: MapId,
    registry: RegistryDep,
    settings: SettingsDep,
    metrics: MetricsDep,
    learn: Annotated[bool, Query(description="true: mapping (stored, learned); false: localisation")] = True,
    top_k: Annotated[int, Query(ge=0, description="matches to return (0: none; `place` is still answered)"),
                     DECIMAL] = 5,
    stream: StreamQuery = "default",
    label: Annotated[str | None, Query(max_length=200)] = None,
    encoding: Annotated[str | None, Query(max_length=16, description="a raw frame's pixels: "
                                          + " | ".join(images.RAW_ENCODINGS))] = None,
    width: Annotated[int | None, Query(ge=1, description="a raw frame's width in pixels"), DECIMAL] = None,
    height: Annotated[int | None, Query(ge=1, description="a raw frame's height in pixels"), DECIMAL] = None,
    metadata: Annotated[str | None, Query(description="a compact JSON object stored with the "
                                          "observation: stamp, pose {x, y, yaw, frame_id}, ...")] = None,
    idempotency_key: IdempotencyKey = None,
) -> ObservationModel | Response:
    """Post one camera frame as the raw body: `image/jpeg`, `image/png`, `image/webp`, `image/bmp`, or
    `application/octet-stream` (sniffed; a raw frame with `encoding`, `width` and `height`)."""
    t_start = time.perf_counter()
    if top_k > settings.max_top_k:
        raise Problem(400, "invalid-parameter", f"top_k must be at most {settings.max_top_k}",
                      errors=[{"location": "query", "name": "top_k", "message": f"<= {settings.max_top_k}"}])
    meta = parse_metadata(metadata) if metadata is not None else None
    rt = registry.get(map_id)
    rt.require_ready(learn)  # a localising frame is answered while a tail replays
    media = (request.headers.get("content-type") or "").split(";")[0].strip().lower()
    if media not in IMAGE_MEDIA_TYPES:
        raise Problem(415, "unsupported-media-type", f"Content-Type {media or '(none)'!r} is not accepted",
                      allowed=list(IMAGE_MEDIA_TYPES), detected=media or None)
    frame = _frame(await request.body(), media, encoding, width, height)
    # Every input check runs before anything stateful: the header (size, pixels, aspect, decoding cost)
    # here, off the event loop (a chunk walk may take milliseconds), the full decode in the encoder pool.
    info = await anyio.to_thread.run_sync(functools.partial(
        images.probe, frame, max_bytes=settings.max_upload_bytes, max_pixels=settings.max_pixels))
    if media in _DECLARED and _DECLARED[media] != info.format:
        raise Problem(415, "unsupported-media-type", f"declared {media} but the bytes are {info.format}",
                      allowed=list(IMAGE_MEDIA_TYPES), detected=info.format)
    rid = getattr(request.state, "request_id", None)

    def reply(result: ObservationResult) -> ObservationModel:
        timings = {**result.timings_ms, "total": (time.perf_counter() - t_start) * 1e3}
        desc = registry.encoders.get(result.backbone).describe()  # the map's own backbone's encoder
        return ObservationModel(
            request_id=rid, map_id=result.map_id, stream=result.stream, learned=result.learned,
            observation_id=result.observation_id, seq=result.seq,
            sequence=SequenceModel.from_result(result.sequence),
            matches=[MatchModel.from_result(m) for m in result.matches], place=result.place,
            timings_ms={k: round(v, 3) for k, v in timings.items()},
            versions=Versions(api="v1", code=request.app.version, backbone=result.backbone,
                              encoder=result.encoder, resize=result.resize, weights=desc["weights"],
                              runtime=desc["runtime"],
                              device=desc["device"],
                              projection=f"sha256:{result.projection_sha256}", map_seq=result.map_seq),
            metadata=result.metadata, consolidated_into=result.consolidated_into,
            loop_closure_id=result.loop_closure_id)

    post = None
    if idempotency_key is not None:
        data = frame.data if isinstance(frame, images.RawFrame) else frame
        digest = await anyio.to_thread.run_sync(lambda: hashlib.sha256(data).hexdigest())
        post = idempotency.IdempotentPost(
            idempotency_key, idempotency.fingerprint(
                digest, learn=learn, top_k=top_k, stream=stream, label=label, metadata=meta, media=media,
                encoding=encoding, width=width, height=height),
            seal=lambda result: reply(result).model_dump_json())
        # A retry of a stored post is answered before any encoding.
        earlier = await rt.stored_reply(post)
        if earlier is not None:
            return _replayed(earlier)
    async with _departure(request) as gone:
        out = await rt.observe(request.app.state.encoder_pool, request.app.state.extractions, frame,
                               learn=learn, stream=stream, top_k=top_k, label=label, metadata=meta, post=post,
                               gone=gone)
    if isinstance(out, idempotency.Reply):
        if out.replayed:
            return _replayed(out)
        first = ObservationModel.model_validate_json(out.body)
        _count(metrics, map_id, learn, first.timings_ms)
        rt.recent.add(first.stream, _recent(first), out.thumbnail)  # replays are not added
        return Response(out.body, media_type="application/json")
    model = reply(out)
    _count(metrics, map_id, learn, model.timings_ms)
    rt.recent.add(model.stream, _recent(model), out.thumbnail)
    return model


@contextlib.asynccontextmanager
async def _departure(request: Request) -> AsyncIterator[Departure]:
    """An event set once the client goes away (the ASGI `http.disconnect`, which `receive()` gives once
    the body was read), watched while the post is worked on, so the work not yet started is skipped
    (`MapRuntime.observe`: its encoding cancelled where not yet in a batch)."""
    gone = Departure()

    async def watch() -> None:
        while (await request.receive())["type"] != "http.disconnect":
            pass
        gone.set()

    watcher = asyncio.ensure_future(watch())
    try:
        yield gone
    finally:
        watcher.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await watcher


def _recent(reply: ObservationModel) -> ObservationModel:
    """The reply as the viewer's window keeps it (GET .../recent): as sent, with its top match only, so
    256 replies of up to 100 matches with 4 KiB of metadata each cannot hold 100 MB per map."""
    return reply.model_copy(update={"matches": reply.matches[:1]})


def _replayed(earlier: idempotency.Reply) -> Response:
    return Response(earlier.body, media_type="application/json", headers={REPLAY_HEADER: "true"})


def _count(metrics: Any, map_id: str, learn: bool, timings: dict[str, float]) -> None:
    for stage, ms in timings.items():
        if stage != "total":
            metrics.observe_stage(stage, ms / 1e3)
    metrics.count_observation(map_id, learn)


@router.get("/{map_id}/observations", responses=problem_responses(404, 503))
async def list_observations(
    map_id: MapId, registry: RegistryDep,
    after_seq: Annotated[int, Query(ge=0, le=MAX_SEQ, description="the page starts after this seq"),
                         DECIMAL] = 0,
    limit: Annotated[int, Query(ge=1, le=MAX_PAGE), DECIMAL] = 100,
) -> StoredObservationList:
    """Stored observations in seq order, without their codes (a map's trajectory, from the poses)."""
    rt = registry.get(map_id)
    rt.require_ready(learns=False)
    assert rt.store is not None
    found = await anyio.to_thread.run_sync(stored.page, rt.store, after_seq, limit)
    return StoredObservationList(observations=[StoredObservationModel.from_result(o) for o in found],
                                 next_after_seq=found[-1].seq if len(found) == limit else None,
                                 epoch=rt.epoch)


@router.get("/{map_id}/observations/{seq}",
            responses=problem_responses(404, 503))
async def get_observation(map_id: MapId, seq: Seq, registry: RegistryDep) -> StoredObservationModel:
    rt = registry.get(map_id)
    rt.require_ready(learns=False)
    assert rt.store is not None
    found = await anyio.to_thread.run_sync(stored.observation, map_id, rt.store, seq)
    return StoredObservationModel.from_result(found)


@router.get("/{map_id}/observations/{seq}/thumbnail",
            response_class=Response, responses={**problem_responses(404, 503), 200: {
                "content": {"image/jpeg": {"schema": {"type": "string", "format": "binary"}}}}})
async def get_thumbnail(map_id: MapId, seq: Seq, registry: RegistryDep) -> Response:
    """The small JPEG kept with a learned observation of a map made with `thumbnails: true`."""
    rt = registry.get(map_id)
    rt.require_ready(learns=False)
    assert rt.store is not None
    jpeg = await anyio.to_thread.run_sync(stored.thumbnail, map_id, rt.store, seq)
    return Response(jpeg, media_type="image/jpeg")
