"""The latest answers of a map, for watching it work (docs/design/service.md §1.7): the observation
replies as they were sent, from the map's in-memory ring (`service.maps.runtime.recent`), not from the
store."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from service.deps import RegistryDep
from service.errors import problem_responses
from service.maps.runtime.recent import RECENT_CAPACITY, kept_thumbnail
from service.routes.params import DECIMAL, AnswerId, MapId
from service.schemas import STREAM_PATTERN, RecentList, RecentModel

router = APIRouter(prefix="/v1/maps", tags=["observations"])


@router.get("/{map_id}/recent", responses=problem_responses(400, 401, 404))
async def recent_answers(
    map_id: MapId,
    registry: RegistryDep,
    limit: Annotated[int, Query(ge=1, le=RECENT_CAPACITY, description="newest answers to return"),
                     DECIMAL] = 50,
    stream: Annotated[str | None, Query(pattern=STREAM_PATTERN,
                                        description="only this stream's answers")] = None,
) -> RecentList:
    """The map's newest answers (learned and localised), oldest first. Not durable: empty after a
    restart."""
    rt = registry.get(map_id)
    entries = rt.recent.last(limit, stream)
    thumbs = rt.recent.with_thumbnails([e.answer_id for e in entries])
    return RecentList(map_id=map_id, capacity=rt.recent.capacity,
                      answers=[RecentModel(answer_id=e.answer_id, received_at=e.received_at,
                                           has_thumbnail=e.answer_id in thumbs, reply=e.reply)
                               for e in entries])


@router.get("/{map_id}/recent/{answer_id}/thumbnail", response_class=Response,
            responses={**problem_responses(400, 401, 404), 200: {
                "content": {"image/jpeg": {"schema": {"type": "string", "format": "binary"}}}}})
async def recent_thumbnail(map_id: MapId, answer_id: AnswerId, registry: RegistryDep) -> Response:
    """The query frame's small JPEG kept with a recent answer (maps made with `thumbnails: true`): a
    localised frame's image is kept nowhere else. In memory only, like the answers."""
    return Response(kept_thumbnail(map_id, registry.get(map_id).recent, answer_id), media_type="image/jpeg")
