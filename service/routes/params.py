"""The request parameters every router shares, each declared once (docs/design/service.md §1).

The patterns come from their one home: map and snapshot ids from `storage.catalog` (the rules the store
itself enforces), stream names from `service.schemas.STREAM_PATTERN`.
"""

from __future__ import annotations

import json
import re
from collections import Counter
from typing import Annotated, Any

from fastapi import Header, Path, Query
from pydantic import BeforeValidator

from service.maps.ids import SNAPSHOT_ID_RE
from service.maps.runtime.idempotency import KEY_PATTERN
from service.schemas import MAP_ID_PATTERN, STREAM_PATTERN

__all__ = ["DECIMAL", "MAX_SEQ", "REPLAY_HEADER", "AnswerId", "IdempotencyKey", "MapId", "Seq", "SnapshotId",
           "StreamName", "StreamQuery", "duplicate_keys"]

_DECIMAL_RE = re.compile(r"-?(0|[1-9][0-9]*)")


def _decimal(value: Any) -> Any:
    """An integer parameter as plain decimal digits: Python's int() also reads " 5", "+3", "05" and
    "1_0" (10), which would name another seq or page than the one meant, so each is refused."""
    if isinstance(value, str) and not _DECIMAL_RE.fullmatch(value):
        raise ValueError("must be an integer in plain decimal digits (no sign, spaces, leading zeros "
                         "or underscores)")
    return value


#: Every integer query or path parameter carries it (`Annotated[int, Query(...), DECIMAL]`).
DECIMAL = BeforeValidator(_decimal)

MapId = Annotated[str, Path(pattern=MAP_ID_PATTERN, description="map identifier")]
SnapshotId = Annotated[str, Path(pattern=SNAPSHOT_ID_RE.pattern)]
#: SQLite's integers are 64-bit: a larger seq is a 400, never an overflow inside the store.
MAX_SEQ = 2**63 - 1
Seq = Annotated[int, Path(ge=1, le=MAX_SEQ, description="a stored observation's seq"), DECIMAL]
AnswerId = Annotated[int, Path(ge=1, le=MAX_SEQ, description="a recent answer's `answer_id`"), DECIMAL]
#: A stream in a path: ROS-style names carry '/', sent percent-encoded (`robot1%2Fcam0`).
StreamName = Annotated[str, Path(pattern=STREAM_PATTERN, description="stream name ('/' allowed)")]
StreamQuery = Annotated[str, Query(pattern=STREAM_PATTERN, description="stream name ('/' allowed)")]


def duplicate_keys(text: str | bytes) -> list[str]:
    """The member names that some object of JSON `text` gives more than once, sorted; [] for text that is
    no JSON (its parser says why). A JSON reader keeps one of the two silently (Python's the last), so
    `{"map_id": "a", "map_id": "b"}` would make map b."""
    found: set[str] = set()

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        found.update(name for name, n in Counter(name for name, _ in items).items() if n > 1)
        return dict(items)

    try:
        json.loads(text, object_pairs_hook=pairs)
    except (ValueError, RecursionError):
        return []
    return sorted(found)


#: An `Idempotency-Key` (docs/design/service.md §1.2): a retry with the key and the same request answers
#: what the first did, which is done once; a replayed answer carries `REPLAY_HEADER: true`.
IdempotencyKey = Annotated[str | None, Header(
    alias="Idempotency-Key", pattern=KEY_PATTERN,
    description="a repeat with this key and the same request answers the first's reply and does nothing")]
REPLAY_HEADER = "Idempotent-Replayed"
