"""What a frame's metadata says of the robot's motion (docs/design/science.md §11.6, docs/design/service.md
§1.2): its pose, its stamp and the trail it names. Pure: the service validates metadata at the HTTP
boundary (`service.routes.observations.parse_metadata`); this reads what was stored, and reads anything it
cannot use as absent, so a row stored before the check (or by a client that sent no pose) replays as it
was learned.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from datetime import UTC, datetime
from typing import Any, NamedTuple

__all__ = ["NO_MOTION", "Motion", "stamp_seconds"]


def stamp_seconds(metadata: Mapping[str, Any] | None, *, finite: bool = True) -> float | None:
    """`metadata.stamp` in seconds: a number as it is, a numeric string or ISO 8601 text converted;
    None without one (a string that is neither). A numeric string beyond a double ("1e400") or "nan"
    reads as None too, unless `finite` is False: then as the inf or NaN it is, for the HTTP check that
    refuses it (a stored row's is read as absent, as it was learned)."""
    stamp = (metadata or {}).get("stamp")
    if isinstance(stamp, bool) or stamp is None:
        return None
    try:
        seconds = float(stamp)  # a number, or a numeric string ("NaN" and "1e999" included)
    except (TypeError, ValueError):
        try:
            when = datetime.fromisoformat(str(stamp))
        except ValueError:
            return None
        # ISO text without an offset is UTC: the export must not depend on the server's time zone
        seconds = (when if when.tzinfo else when.replace(tzinfo=UTC)).timestamp()
    return seconds if math.isfinite(seconds) or not finite else None  # JSON has no NaN or Infinity


def _coordinate(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


class Motion(NamedTuple):
    """A learned frame's motion, as its metadata gives it (each part None where not given).

    Attributes:
        pose: (x, y) in metres (`metadata.pose`; its yaw plays no part: turning on the spot is no move).
        stamp: `metadata.stamp` in seconds (`stamp_seconds`).
        trail: `metadata.trail`, the short-term memory the frame's stream shares (a stream name; None:
            the stream's own, §11.6).
    """

    pose: tuple[float, float] | None = None
    stamp: float | None = None
    trail: str | None = None

    @classmethod
    def of(cls, metadata: Mapping[str, Any] | None) -> Motion:
        """The motion `metadata` (a frame's stored metadata, or None) gives."""
        if not metadata:
            return NO_MOTION
        pose = metadata.get("pose")
        xy = None
        if isinstance(pose, Mapping):
            x, y = _coordinate(pose.get("x")), _coordinate(pose.get("y"))
            xy = None if x is None or y is None else (x, y)
        trail = metadata.get("trail")
        return cls(xy, stamp_seconds(metadata), trail if isinstance(trail, str) and trail else None)


#: No motion given (no pose, no stamp, the stream's own trail).
NO_MOTION = Motion()
