"""A map's loop-closure log, read back (docs/design/service.md §1.2, docs/design/science.md §11.6): a page
in log order, and the export of candidate pairs for pose-graph back ends that verify pairs themselves
(CSV or JSON lines). Reads only: `MapStore` is safe to read from any thread while the writer appends."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterator
from datetime import datetime
from typing import Any

from service.maps.results import LoopClosureResult, StoredRow
from storage.mapstore import LoopClosure, MapStore

__all__ = ["EXPORT_COLUMNS", "EXPORT_FORMATS", "export", "page"]

#: The export's fields, in CSV column order: both stamps in seconds, both ids, the confidence, both
#: poses where the client gave them (x, y, yaw); empty (CSV) or null (JSON) where not.
EXPORT_COLUMNS = ("stamp", "observation_id", "seq", "stream", "place_stamp", "place_observation_id",
                  "place_seq", "place_stream", "confidence", "support", "x", "y", "yaw", "place_x",
                  "place_y", "place_yaw")
#: Export media types by format.
EXPORT_FORMATS = {"csv": "text/csv; charset=utf-8", "jsonl": "application/jsonl"}
_EXPORT_PAGE = 1000  # log entries read per query while streaming an export


def _result(c: LoopClosure) -> LoopClosureResult:
    return LoopClosureResult(id=c.id, stream=c.stream, seq=c.seq, observation_id=c.observation_id,
                             metadata=c.metadata, confidence=c.confidence, support=c.support,
                             created_at=c.created_at,
                             place=StoredRow(seq=c.place_seq, observation_id=c.place_observation_id,
                                             stream=c.place_stream, label=c.place_label,
                                             metadata=c.place_metadata))


def page(store: MapStore, after: int, limit: int) -> list[LoopClosureResult]:
    """At most `limit` logged loop closures after log id `after`, oldest first."""
    return [_result(c) for c in store.closures(after, limit)]


def stamp_seconds(metadata: dict[str, Any] | None) -> float | None:
    """`metadata.stamp` in seconds: a number as it is, a numeric string or ISO 8601 text converted;
    None without one (a string that is neither)."""
    stamp = (metadata or {}).get("stamp")
    if isinstance(stamp, bool) or stamp is None:
        return None
    if isinstance(stamp, int | float):
        return float(stamp) if math.isfinite(stamp) else None
    try:
        return float(stamp)
    except ValueError:
        pass
    try:
        return datetime.fromisoformat(str(stamp)).timestamp()
    except ValueError:
        return None


def _pose(metadata: dict[str, Any] | None) -> tuple[Any, Any, Any]:
    pose = (metadata or {}).get("pose")
    return (pose.get("x"), pose.get("y"), pose.get("yaw")) if isinstance(pose, dict) else (None, None, None)


def _record(c: LoopClosure) -> dict[str, Any]:
    x, y, yaw = _pose(c.metadata)
    px, py, pyaw = _pose(c.place_metadata)
    return {"stamp": stamp_seconds(c.metadata), "observation_id": c.observation_id, "seq": c.seq,
            "stream": c.stream, "place_stamp": stamp_seconds(c.place_metadata),
            "place_observation_id": c.place_observation_id, "place_seq": c.place_seq,
            "place_stream": c.place_stream, "confidence": c.confidence, "support": c.support,
            "x": x, "y": y, "yaw": yaw, "place_x": px, "place_y": py, "place_yaw": pyaw}


def export(store: MapStore, fmt: str) -> Iterator[str]:
    """The whole log as candidate pairs, oldest first, in `fmt` (`csv`: a header line, then one line per
    closure; `jsonl`: one JSON object per line), read a page at a time (bounded memory)."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}")
    if fmt == "csv":
        yield ",".join(EXPORT_COLUMNS) + "\n"
    after = 0
    while found := store.closures(after, _EXPORT_PAGE):
        for c in found:
            rec = _record(c)
            if fmt == "jsonl":
                yield json.dumps(rec, separators=(",", ":")) + "\n"
            else:
                buf = io.StringIO()
                csv.writer(buf, lineterminator="\n").writerow(["" if rec[k] is None else rec[k]
                                                             for k in EXPORT_COLUMNS])
                yield buf.getvalue()
        after = found[-1].id
