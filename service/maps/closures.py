"""A map's loop-closure log, read back (docs/design/service.md §1.2, docs/design/science.md §11.6): a page
in log order, and the export of candidate pairs for pose-graph back ends (CSV or JSON lines, with the
geometric verification and relative pose where the map keeps keyframes, docs/design/science.md §12), or
of the verified ones as g2o edges. Reads only: `MapStore` is safe to read from any thread while the
writer appends."""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterator
from datetime import UTC, datetime
from typing import Any

import numpy as np

from models.geometry import quaternion
from service.maps.results import LoopClosureResult, StoredRow, VerificationResult
from storage.mapstore import LoopClosure, MapStore

__all__ = ["EXPORT_COLUMNS", "EXPORT_FORMATS", "export", "g2o_edge", "page"]

#: The export's fields, in CSV column order: both stamps in seconds, both ids, the confidence, both
#: poses where the client gave them (x, y, yaw); empty (CSV) or null (JSON) where not.
#: Then the geometric verification (maps with keyframes; empty elsewhere): verified, the keyframe row it
#: verified against, inliers, model, and the relative pose X_query = R X_keyframe + t as a quaternion
#: (qx, qy, qz, qw) and a unit translation (tx, ty, tz; empty where unobservable).
EXPORT_COLUMNS = ("stamp", "observation_id", "seq", "stream", "place_stamp", "place_observation_id",
                  "place_seq", "place_stream", "confidence", "support", "x", "y", "yaw", "place_x",
                  "place_y", "place_yaw", "verified", "keyframe_seq", "inliers", "model", "qx", "qy", "qz",
                  "qw", "tx", "ty", "tz")
#: Export media types by format.
EXPORT_FORMATS = {"csv": "text/csv; charset=utf-8", "jsonl": "application/jsonl",
                  "g2o": "text/plain; charset=utf-8"}
#: The g2o edges' information for the rotation, per component of the quaternion's vector part (g2o's
#: EdgeSE3 error, about half the angle for small rotations): a standard deviation of 0.01 there is 0.02
#: rad (1.15 degrees) of rotation, above the worst rotation error of docs/results.md §12 (0.13 degrees,
#: ORB) with room for scenes harder than those. Translation carries no information: two
#: views give its direction, never its length, so a back end takes the length from odometry.
G2O_ROTATION_INFORMATION = 1e4
_EXPORT_PAGE = 1000  # log entries read per query while streaming an export


def _result(c: LoopClosure) -> LoopClosureResult:
    return LoopClosureResult(id=c.id, stream=c.stream, seq=c.seq, observation_id=c.observation_id,
                             metadata=c.metadata, confidence=c.confidence, support=c.support,
                             created_at=c.created_at,
                             place=StoredRow(seq=c.place_seq, observation_id=c.place_observation_id,
                                             stream=c.place_stream, label=c.place_label,
                                             metadata=c.place_metadata),
                             verification=None if c.verification is None
                             else VerificationResult(**c.verification))


def page(store: MapStore, after: int, limit: int) -> list[LoopClosureResult]:
    """At most `limit` logged loop closures after log id `after`, oldest first."""
    return [_result(c) for c in store.closures(after, limit)]


def stamp_seconds(metadata: dict[str, Any] | None) -> float | None:
    """`metadata.stamp` in seconds: a number as it is, a numeric string or ISO 8601 text converted;
    None without one (a string that is neither)."""
    stamp = (metadata or {}).get("stamp")
    if isinstance(stamp, bool) or stamp is None:
        return None
    try:
        seconds = float(stamp)  # a number, or a numeric string ("NaN" and "1e999" included)
    except ValueError:
        try:
            when = datetime.fromisoformat(str(stamp))
        except ValueError:
            return None
        # ISO text without an offset is UTC: the export must not depend on the server's time zone
        seconds = (when if when.tzinfo else when.replace(tzinfo=UTC)).timestamp()
    return seconds if math.isfinite(seconds) else None  # JSON has no NaN or Infinity


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
            "x": x, "y": y, "yaw": yaw, "place_x": px, "place_y": py, "place_yaw": pyaw,
            **_verification(c.verification)}


def _verification(v: dict[str, Any] | None) -> dict[str, Any]:
    """The export's verification fields of a logged closure (None everywhere without one)."""
    v = v or {}
    q = quaternion(np.array(v["rotation"])) if v.get("rotation") else (None,) * 4
    t = v.get("translation") or (None,) * 3
    return {"verified": v.get("verified"), "keyframe_seq": v.get("keyframe_seq"), "inliers": v.get("inliers"),
            "model": v.get("model"), **dict(zip(("qx", "qy", "qz", "qw"), q, strict=True)),
            **dict(zip(("tx", "ty", "tz"), t, strict=True))}


def g2o_edge(c: LoopClosure) -> str | None:
    """A verified closure with a relative rotation, between two stored rows, as a g2o
    `EDGE_SE3:QUAT keyframe_seq seq  x y z  qx qy qz qw  information` line; None otherwise.

    Vertex ids are the map's seqs (a localising stream's closure has no row: it is in the CSV and JSON
    exports, with its stamp). The measurement is the query camera's pose in the keyframe camera's frame
    (camera axes: x right, y down, z ahead): X_keyframe = R^T X_query - R^T t. Its translation is the
    unit direction where observable, else zero, and carries zero information either way; the rotation's
    information is G2O_ROTATION_INFORMATION (upper triangle of the 6 x 6 matrix, row-major)."""
    v = c.verification or {}
    if not v.get("verified") or not v.get("rotation") or c.seq is None:
        return None
    R = np.array(v["rotation"], np.float64)
    t = -R.T @ np.array(v.get("translation") or (0.0, 0.0, 0.0), np.float64)
    info = np.diag([0.0, 0.0, 0.0] + [G2O_ROTATION_INFORMATION] * 3)[np.triu_indices(6)]
    values = [*t, *quaternion(R.T), *info]
    return (f"EDGE_SE3:QUAT {int(v.get('keyframe_seq') or c.place_seq)} {c.seq} "
            + " ".join(f"{x:.9g}" for x in values) + "\n")


def export(store: MapStore, fmt: str) -> Iterator[str]:
    """The whole log as candidate pairs, oldest first, in `fmt` (`csv`: a header line, then one line per
    closure; `jsonl`: one JSON object per line; `g2o`: one `EDGE_SE3:QUAT` line per verified closure with
    a pose between two stored rows, `g2o_edge`), read a page at a time (bounded memory)."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}")
    if fmt == "csv":
        yield ",".join(EXPORT_COLUMNS) + "\n"
    after = 0
    while found := store.closures(after, _EXPORT_PAGE):
        for c in found:
            if fmt == "g2o":
                if (edge := g2o_edge(c)) is not None:
                    yield edge
                continue
            rec = _record(c)
            if fmt == "jsonl":
                yield json.dumps(rec, separators=(",", ":")) + "\n"
            else:
                buf = io.StringIO()
                csv.writer(buf, lineterminator="\n").writerow(["" if rec[k] is None else rec[k]
                                                             for k in EXPORT_COLUMNS])
                yield buf.getvalue()
        after = found[-1].id
