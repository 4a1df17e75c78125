"""The latest answers of a map, for watching it work (docs/design/service.md §1.7): the observation
replies as they were sent, from the map's in-memory ring (`service.maps.recent`), not from the store."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query

from service.deps import RegistryDep
from service.errors import problem_responses
from service.maps.recent import RECENT_CAPACITY
from service.routes.params import MapId
from service.schemas import STREAM_PATTERN, RecentList, RecentModel

router = APIRouter(prefix="/v1/maps", tags=["observations"])


@router.get("/{map_id}/recent", responses=problem_responses(400, 401, 404))
async def recent_answers(
    map_id: MapId,
    registry: RegistryDep,
    limit: Annotated[int, Query(ge=1, le=RECENT_CAPACITY, description="newest answers to return")] = 50,
    stream: Annotated[str | None, Query(pattern=STREAM_PATTERN,
                                        description="only this stream's answers")] = None,
) -> RecentList:
    """The map's newest answers (learned and localised), oldest first. Not durable: empty after a
    restart."""
    rt = registry.get(map_id)
    return RecentList(map_id=map_id, capacity=rt.recent.capacity,
                      answers=[RecentModel(received_at=e.received_at, reply=e.reply)
                               for e in rt.recent.last(limit, stream)])
