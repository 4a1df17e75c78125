"""A map's loop-closure log, read back (docs/design/service.md §1.2, docs/design/science.md §11.6): a page
in log order, and the export of candidate pairs for pose-graph back ends (CSV or JSON lines, with the
geometric verification and relative pose where the map keeps keyframes, docs/design/science.md §12), or
of the verified ones as a g2o graph (their vertices at the posted poses, the edges in the same body axes,
`g2o_lines`). Reads only: `MapStore` is safe to read from any thread while the
writer appends.

An export is rendered whole, every entry checked, before its body starts (`render`): what is not a
finite number is left empty, so no entry can fail it halfway, and a failure to render answers an
error instead of a short file. Its text cells are neutralised against spreadsheet formulas
(`csv_cell`)."""

from __future__ import annotations

import csv
import io
import json
import math
import tempfile
from collections.abc import Iterator, Mapping
from typing import IO, Any

import numpy as np

from models.geometry import quaternion
from models.geometry.verify import is_rotation
from models.localisation.motion import stamp_seconds
from service.maps.results import LoopClosurePage, LoopClosureResult, StoredRow, VerificationResult
from storage.mapstore import LoopClosure, MapStore

__all__ = ["BODY_FROM_OPTICAL", "EXPORT_COLUMNS", "EXPORT_FORMATS", "VISIT_VERTEX_BASE", "body_relative_pose",
           "chunks", "csv_cell", "g2o_lines", "g2o_retracted", "page", "render"]

#: The export's fields, in CSV column order: both stamps in seconds, both ids, the confidence, both
#: poses where the client gave them (x, y, yaw); empty (CSV) or null (JSON) where not.
#: Then the geometric verification (maps with keyframes; empty elsewhere): verified, the keyframe row it
#: verified against, inliers, model, and the relative pose X_query = R X_keyframe + t as a quaternion
#: (qx, qy, qz, qw) and a unit translation (tx, ty, tz; empty where unobservable). Then the frame's
#: vertex id in the g2o export (`vertex_id`; empty for a localising stream's frame). Then the entry's log
#: `id`, its `kind` (`closure`, or `retraction`: a repair withdrew closure `retracts`, docs/design/science.md
#: §11.6; the retraction repeats that closure's pair with confidence and support 0, no verification, and a
#: back end drops the edge it made for it). Last, the answer's span (docs/design/science.md §11.11): how
#: many places the stream may have been at, and their best rows (CSV: space-separated; JSON: a list),
#: empty or null for an entry logged before schema 11 and for a retraction.
EXPORT_COLUMNS = ("stamp", "observation_id", "seq", "stream", "place_stamp", "place_observation_id",
                  "place_seq", "place_stream", "confidence", "support", "x", "y", "yaw", "place_x",
                  "place_y", "place_yaw", "verified", "keyframe_seq", "inliers", "model", "qx", "qy", "qz",
                  "qw", "tx", "ty", "tz", "vertex", "id", "kind", "retracts", "span", "span_seqs")
#: Export media types by format.
EXPORT_FORMATS = {"csv": "text/csv; charset=utf-8", "jsonl": "application/jsonl",
                  "g2o": "text/plain; charset=utf-8"}
#: The g2o edges' information for the rotation, per component of the quaternion's vector part (g2o's
#: EdgeSE3 error, about half the angle for small rotations): a standard deviation of 0.01 there is 0.02
#: rad (1.15 degrees) of rotation, above the worst rotation error of docs/results.md §12 (0.13 degrees,
#: ORB) with room for scenes harder than those. Translation carries no information: two
#: views give its direction, never its length, so a back end takes the length from odometry.
G2O_ROTATION_INFORMATION = 1e4
#: The g2o vertex of a consolidated frame (a visit: it has no row) is this plus its closure's log id; a
#: stored row's is its seq. g2o reads ids as 32-bit ints, so both
#: stay below 2^31: a map's seqs below 10^9 (decades of learning at 1 row a second), log ids below
#: 2^31 - 10^9. An entry past them is in the CSV and JSON exports only.
VISIT_VERTEX_BASE = 1_000_000_000
_G2O_MAX_ID = 2**31 - 1
#: The g2o export's axes from the camera's optical axes: X_body = BODY_FROM_OPTICAL X_optical. Optical: x
#: right, y down, z ahead (the verification's, docs/design/science.md §12.3; REP 103's `_optical` frame).
#: Body: x ahead, y left, z up (REP 103), the axes of a `metadata.pose` (x, y, yaw about z) for a camera
#: that looks along its pose's heading, level: all a planar pose can say of it.
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: A CSV text cell starting with one of these is read as a formula by spreadsheets (OWASP's CSV
#: injection guidance): it is written with a leading single quote.
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
_EXPORT_PAGE = 1000  # log entries read per query while rendering an export
#: An export is rendered into memory up to this many bytes, into a temporary file beyond.
_SPOOL_BYTES = 8 * 2**20
_CHUNK = 64 * 1024


def _result(c: LoopClosure) -> LoopClosureResult:
    return LoopClosureResult(id=c.id, stream=c.stream, seq=c.seq, observation_id=c.observation_id,
                             metadata=c.metadata, confidence=c.confidence, support=c.support,
                             created_at=c.created_at,
                             place=StoredRow(seq=c.place_seq, observation_id=c.place_observation_id,
                                             stream=c.place_stream, label=c.place_label,
                                             metadata=c.place_metadata),
                             verification=None if c.verification is None
                             else VerificationResult(**c.verification),
                             consolidated_into=c.consolidated_into, retracts=c.retracts, span=c.span,
                             span_seqs=None if c.span_seqs is None else list(c.span_seqs))


def page(store: MapStore, after: int, limit: int) -> LoopClosurePage:
    """At most `limit` logged loop closures after log id `after`, oldest first, and the oldest and newest
    ids (read after them, `LoopClosurePage`)."""
    entries = [_result(c) for c in store.closures(after, limit)]
    return LoopClosurePage(entries=entries, oldest=store.oldest_closure_id(), newest=store.last_closure_id())


def _finite(value: Any) -> Any:
    """`value` where it is JSON with finite numbers only: a non-finite float is None (JSON has no NaN)."""
    return None if isinstance(value, float) and not math.isfinite(value) else value


def _pose(metadata: dict[str, Any] | None) -> tuple[Any, Any, Any]:
    pose = (metadata or {}).get("pose")
    if not isinstance(pose, dict):
        return None, None, None
    return _finite(pose.get("x")), _finite(pose.get("y")), _finite(pose.get("yaw"))


def _record(c: LoopClosure) -> dict[str, Any]:
    x, y, yaw = _pose(c.metadata)
    px, py, pyaw = _pose(c.place_metadata)
    return {"stamp": stamp_seconds(c.metadata), "observation_id": c.observation_id, "seq": c.seq,
            "stream": c.stream, "place_stamp": stamp_seconds(c.place_metadata),
            "place_observation_id": c.place_observation_id, "place_seq": c.place_seq,
            "place_stream": c.place_stream, "confidence": _finite(c.confidence), "support": c.support,
            "x": x, "y": y, "yaw": yaw, "place_x": px, "place_y": py, "place_yaw": pyaw,
            **_verification(c.verification), "vertex": vertex_id(c), "id": c.id,
            "kind": "closure" if c.retracts is None else "retraction", "retracts": c.retracts,
            "span": c.span, "span_seqs": None if c.span_seqs is None else list(c.span_seqs)}


def _rotation(v: dict[str, Any]) -> np.ndarray | None:
    """A logged verification's rotation where it is a finite proper rotation (3, 3), else None: entries
    logged before verification refused non-finite poses (`no-pose`) may hold nulls or worse."""
    try:
        R = np.array(v.get("rotation"), np.float64)
    except (TypeError, ValueError):
        return None
    return R if is_rotation(R) else None


def _translation(v: dict[str, Any]) -> np.ndarray | None:
    """A logged verification's unit translation where it is 3 finite numbers, else None."""
    try:
        t = np.array(v.get("translation"), np.float64)
    except (TypeError, ValueError):
        return None
    return t if t.shape == (3,) and np.all(np.isfinite(t)) else None


def _verification(v: dict[str, Any] | None) -> dict[str, Any]:
    """The export's verification fields of a logged closure (None everywhere without one; the pose
    fields None where they are not finite)."""
    v = v or {}
    R, t = _rotation(v), _translation(v)
    q = quaternion(R) if R is not None else (None,) * 4
    return {"verified": v.get("verified"), "keyframe_seq": _finite(v.get("keyframe_seq")),
            "inliers": _finite(v.get("inliers")), "model": v.get("model"),
            **dict(zip(("qx", "qy", "qz", "qw"), q, strict=True)),
            **dict(zip(("tx", "ty", "tz"), (None,) * 3 if t is None else t.tolist(), strict=True))}


def vertex_id(c: LoopClosure) -> int | None:
    """The frame's g2o vertex id: its seq where it has a row, VISIT_VERTEX_BASE + its log id for a
    consolidated frame (a visit); None for a localising stream's frame (not part of the map's graph),
    and where the id would not be below 2^31 and apart from every row's (`VISIT_VERTEX_BASE`)."""
    if c.seq is not None:
        return c.seq if c.seq < VISIT_VERTEX_BASE else None
    if c.consolidated_into is None:
        return None
    vertex = VISIT_VERTEX_BASE + (c.id if c.retracts is None else c.retracts)  # a retraction: its closure's
    return vertex if vertex <= _G2O_MAX_ID else None


def body_relative_pose(R: np.ndarray, t: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The query camera's pose in the keyframe camera's frame, in body axes (`BODY_FROM_OPTICAL`: x ahead,
    y left, z up), from a verification's X_query = R X_keyframe + t in optical axes: the optical pose
    (R^T, -R^T t) turned into body axes, B R^T B^T and -B R^T t. Returns (position (3,): a unit direction,
    or zero where `t` is None, two views giving no scale; orientation (3, 3)). A camera turned left by
    yaw about the vertical (R about optical y by +yaw) is a rotation about z by +yaw."""
    B = BODY_FROM_OPTICAL
    position = -B @ R.T @ (np.zeros(3) if t is None else t)
    return position, B @ R.T @ B.T


def _estimate(metadata: dict[str, Any] | None) -> tuple[tuple[float, ...], bool]:
    """A vertex's estimate from `metadata.pose` (x, y, yaw about z, in the map's z-up frame) as g2o's x y z
    qx qy qz qw, and whether the pose was whole (0 stands for what it lacks)."""
    x, y, yaw = (p if isinstance(p, int | float) and not isinstance(p, bool) else None
                 for p in _pose(metadata))
    whole = x is not None and y is not None and yaw is not None
    x, y, yaw = (0.0 if p is None else float(p) for p in (x, y, yaw))
    return (x, y, 0.0, 0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)), whole


def _vertex(vertex: int, metadata: dict[str, Any] | None) -> str:
    """A vertex's declaration at its `metadata.pose`; a pose missing, or short of x, y or yaw, is preceded
    by `# NOPOSE id`: the estimate is a placeholder (the identity where nothing is known)."""
    estimate, whole = _estimate(metadata)
    line = f"VERTEX_SE3:QUAT {vertex} " + " ".join(f"{e:.9g}" for e in estimate) + "\n"
    return line if whole else f"# NOPOSE {vertex}\n" + line


def _edge(c: LoopClosure) -> tuple[int, int, str] | None:
    """(keyframe row, frame vertex, the `EDGE_SE3:QUAT` line) of a verified closure with a finite relative
    rotation (`g2o_lines`); None otherwise."""
    v = c.verification or {}
    R = _rotation(v)
    vertex = vertex_id(c)
    keyframe = v.get("keyframe_seq") or c.place_seq
    if (not v.get("verified") or R is None or vertex is None or not isinstance(keyframe, int)
            or isinstance(keyframe, bool) or not 0 < keyframe < VISIT_VERTEX_BASE or keyframe == vertex):
        return None
    t, Rb = body_relative_pose(R, _translation(v))
    info = np.diag([0.0, 0.0, 0.0] + [G2O_ROTATION_INFORMATION / max(c.span or 1, 1)] * 3)[np.triu_indices(6)]
    values = [*t, *quaternion(Rb), *info]
    return keyframe, vertex, (f"EDGE_SE3:QUAT {keyframe} {vertex} " + " ".join(f"{x:.9g}" for x in values)
                              + "\n")


def g2o_lines(c: LoopClosure, declared: set[int] | None = None,
              rows: Mapping[int, dict[str, Any] | None] | None = None) -> str | None:
    """A verified closure with a finite relative rotation as g2o text; None otherwise.

    The edge: `EDGE_SE3:QUAT keyframe_seq vertex  x y z  qx qy qz qw  information`, from the keyframe's
    row (its seq) to the frame's vertex (`vertex_id`: its seq, or for a consolidated frame, a visit,
    VISIT_VERTEX_BASE + the closure's log id; a localising stream's frame has none and no edge).

    **One convention for vertices and edges**: a vertex is a posted `metadata.pose` (x, y, yaw about z in
    the map's z-up frame, REP 103), `VERTEX_SE3:QUAT id x y 0 0 0 qz qw`; the edge is the query's pose in
    the keyframe's, in those body axes (x ahead, y left, z up): the verification's optical relative pose
    turned by `BODY_FROM_OPTICAL` (`body_relative_pose`), which holds for a camera that looks along its
    pose's heading, level (the ROS 2 node posts the camera's pose: odometry composed with `camera_mount`).
    So a camera turned by 8 degrees of yaw is an edge of 8 degrees about z, as the vertices' yaws differ.

    **Every id an edge names is declared** before it, once (`declared`: the ids the file has declared so
    far, updated; None: both of this edge's), at its pose: the frame's (its row's or its visit's) from
    `c.metadata`, the keyframe's from `rows[keyframe_seq]` (the rows' metadata by seq; the place's row
    from `c.place_metadata` where it is the keyframe). A vertex without a whole pose is declared at a
    placeholder after a `# NOPOSE id` comment (`_vertex`), so the file loads on its own; a back end
    merging it into its own graph keeps its own estimate for an id it holds.

    The translation is the unit direction where observable, else zero, and carries zero information either
    way; the rotation's information is G2O_ROTATION_INFORMATION divided by the answer's span (upper
    triangle of the 6 x 6 matrix, row-major): an answer that could have been any of k places is a k times
    weaker constraint (docs/design/science.md §11.11; an entry logged before the span, schema 11, counts
    1)."""
    edge = _edge(c)
    if edge is None:
        return None
    keyframe, vertex, line = edge
    declared = set() if declared is None else declared
    known = {c.place_seq: c.place_metadata, **(rows or {})}
    out = []
    for vid, metadata in ((keyframe, known.get(keyframe)), (vertex, c.metadata)):
        if vid not in declared:
            declared.add(vid)
            out.append(_vertex(vid, metadata))
    return "".join(out) + line


def csv_cell(value: Any) -> Any:
    """One CSV cell: None empty; a text starting with =, +, -, @, tab or CR prefixed with a single quote
    (OWASP: a spreadsheet would read it as a formula); numbers as they are (x = -1.5 stays -1.5)."""
    if value is None:
        return ""
    if isinstance(value, str) and value.startswith(_FORMULA_STARTS):
        return "'" + value
    return value


def g2o_retracted(c: LoopClosure) -> str | None:
    """The comment line standing for a retracted closure's edge in the g2o export (the edge, and the
    vertices only it named, are left out: a g2o reader skips `#` lines), None where `g2o_lines` makes no
    edge of it."""
    edge = _edge(c)
    if edge is None:
        return None
    keyframe, vertex, _ = edge
    return f"# RETRACTED {keyframe} {vertex} closure {c.id}\n"


def _keyframe_rows(store: MapStore, found: list[LoopClosure]) -> dict[int, dict[str, Any] | None]:
    """The metadata of the keyframe rows a page of closures verified against that are not their place's
    row (a route neighbour, docs/design/science.md §12.2): their vertices' poses. A row gone since is
    absent (its vertex has no pose)."""
    seqs = set()
    for c in found:
        keyframe = (c.verification or {}).get("keyframe_seq")
        if isinstance(keyframe, int) and not isinstance(keyframe, bool) and keyframe != c.place_seq:
            seqs.add(keyframe)
    return {seq: row.metadata for seq, row in store.get_many(seqs).items()} if seqs else {}


def _lines(store: MapStore, fmt: str) -> Iterator[str]:
    """The export's text, a line at a time, read a page of the log at a time."""
    if fmt == "csv":
        yield ",".join(EXPORT_COLUMNS) + "\n"
    retracted = store.retracted() if fmt == "g2o" else set()
    declared: set[int] = set()  # the g2o vertices written so far
    after = 0
    while found := store.closures(after, _EXPORT_PAGE):
        rows = _keyframe_rows(store, found) if fmt == "g2o" else {}
        for c in found:
            if fmt == "g2o":
                lines = g2o_retracted(c) if c.id in retracted else g2o_lines(c, declared, rows)
                if lines is not None:
                    yield lines
                continue
            rec = _record(c)
            if fmt == "jsonl":
                yield json.dumps(rec, separators=(",", ":"), allow_nan=False) + "\n"
            else:
                if rec["span_seqs"] is not None:
                    rec["span_seqs"] = " ".join(str(q) for q in rec["span_seqs"])
                buf = io.StringIO()
                csv.writer(buf, lineterminator="\n").writerow([csv_cell(rec[k]) for k in EXPORT_COLUMNS])
                yield buf.getvalue()
        after = found[-1].id


def render(store: MapStore, fmt: str) -> IO[bytes]:
    """Worker thread: the whole log as candidate pairs, oldest first, in `fmt` (`csv`: a header line,
    then one line per closure; `jsonl`: one JSON object per line; `g2o`: the verified closures with a
    finite pose, `g2o_lines`), rendered into a file (in memory up to _SPOOL_BYTES, on disk beyond),
    rewound, for `chunks`. A g2o export leaves a retracted closure's edge out (`g2o_retracted`). Every
    entry is rendered before the body starts, so an entry that cannot be rendered fails the request with
    an error, never a short file; the export holds the log as it was."""
    if fmt not in EXPORT_FORMATS:
        raise ValueError(f"format must be one of {', '.join(EXPORT_FORMATS)}")
    spool = tempfile.SpooledTemporaryFile(max_size=_SPOOL_BYTES)  # noqa: SIM115 - `chunks` closes it
    try:
        for text in _lines(store, fmt):
            spool.write(text.encode())
        spool.seek(0)
    except BaseException:
        spool.close()
        raise
    return spool


def chunks(spool: IO[bytes], chunk_bytes: int = _CHUNK) -> Iterator[bytes]:
    """A rendered export's bytes (`render`) in pieces of at most `chunk_bytes`, closed once read or
    abandoned. Should a read fail anyway, the exception ends the response without its final chunk: the
    client sees a broken transfer, never a short file passing for a whole one."""
    with spool:
        while data := spool.read(chunk_bytes):
            yield data
