"""The request parameters every router shares, each declared once (docs/design/service.md §1).

The patterns come from their one home: map and snapshot ids from `storage.catalog` (the rules the store
itself enforces), stream names from `service.schemas.STREAM_PATTERN`.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query

from service.maps.ids import SNAPSHOT_ID_RE
from service.schemas import MAP_ID_PATTERN, STREAM_PATTERN

__all__ = ["MAX_SEQ", "AnswerId", "MapId", "Seq", "SnapshotId", "StreamName", "StreamQuery"]

MapId = Annotated[str, Path(pattern=MAP_ID_PATTERN, description="map identifier")]
SnapshotId = Annotated[str, Path(pattern=SNAPSHOT_ID_RE.pattern)]
#: SQLite's integers are 64-bit: a larger seq is a 400, never an overflow inside the store.
MAX_SEQ = 2**63 - 1
Seq = Annotated[int, Path(ge=1, le=MAX_SEQ, description="a stored observation's seq")]
AnswerId = Annotated[int, Path(ge=1, le=MAX_SEQ, description="a recent answer's `answer_id`")]
#: A stream in a path: ROS-style names carry '/', sent percent-encoded (`robot1%2Fcam0`).
StreamName = Annotated[str, Path(pattern=STREAM_PATTERN, description="stream name ('/' allowed)")]
StreamQuery = Annotated[str, Query(pattern=STREAM_PATTERN, description="stream name ('/' allowed)")]
