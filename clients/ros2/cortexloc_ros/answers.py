"""The service's answer as the node publishes it: the JSON documents on `std_msgs/String` (the place
answer, a loop closure) and the planar poses the standard messages carry. No ROS here; `node.py` builds
the messages. The documents' fields are listed in the README ("With ROS 2") and below.

Place (`topics.place`, one per answered frame)::

    {"stamp": {"sec", "nanosec"}, "frame_id", "map_id", "stream", "learned", "seq", "consolidated_into",
     "pose": {"x", "y", "yaw", "frame_id"} | null,            # the frame's pose as posted (camera's)
     "place": null | {"seq", "place_id", "observation_id", "stream", "label", "confidence", "revisit",
                      "support", "low_information", "span", "span_seqs", "lagging",
                      "stamp": Time | null, "pose": Pose | null,
                      "verification": {...} | null},            # the service's place (§1.2)
     "matches": [{"rank", "seq", "stream", "score", "overlap", "stamp": Time | null, "pose": Pose | null}],
     "latency_ms", "request_id"}

Loop closure (`topics.loop_closures`, one per answer whose place is a revisit: the service logs the same,
`id` its entry in the map's loop-closure log; null where the log could not take it, a read-only map)::

    {"kind": "closure", "id", "stamp": Time, "frame_id", "map_id", "stream", "seq", "pose": Pose | null,
     "place_stamp": Time | null, "place_seq", "place_id", "place_stream", "place_pose": Pose | null,
     "confidence", "support", "verified": bool | null,
     "relative_pose": null | {"frame": "keyframe_camera_optical", "keyframe_seq", "inliers", "model",
                              "position": {"x", "y", "z"}, "orientation": {"x", "y", "z", "w"},
                              "rotation_deg"}}

`relative_pose` is the query camera's pose in the keyframe camera's frame (optical axes), with a unit
(or zero) position: two views give the direction, never the length.

Retraction (`topics.loop_closures` too, one per retraction of this stream's closures that the log gains
while the node runs: an operator's repair withdrew closure `retracts`; the back end drops its edge)::

    {"kind": "retraction", "id", "retracts", "map_id", "stream", "seq", "stamp": Time | null,
     "place_seq", "place_stream", "place_stamp": Time | null}

Epoch (`topics.loop_closures` too, when the map's log changes its epoch while the node runs: a restore
rolled it back, or a repair withdrew closures the log no longer kept, so closures published before may be
gone or withdrawn with no retraction; the back end rebuilds its edges from the service's export)::

    {"kind": "epoch", "map_id", "previous", "epoch"}
"""

from __future__ import annotations

from typing import Any

from cortexloc_client import Match, Observation, Place
from cortexloc_client.models import LoopClosure
from cortexloc_ros.core import Pose2D, Stamp, relative_pose

__all__ = ["DEFAULT_REVISIT_THRESHOLD", "closure_colour", "epoch_json", "loop_closure_json", "place_json",
           "place_pose", "retraction_json", "stored_stamp"]

#: A new map's `revisit_threshold` on the service (`service.maps.config.DEFAULT_REVISIT_THRESHOLD`; the node
#: is installed without the service, so tests/clients/ros2/test_core.py checks they are equal): the
#: markers' scale where the map's own is unknown (a server before `Map.revisit_threshold`).
DEFAULT_REVISIT_THRESHOLD = 0.91


def stored_stamp(metadata: Any) -> Stamp | None:
    """A stored observation's stamp: the exact `stamp_ns` this node sends, else `stamp` in seconds."""
    if metadata is None:
        return None
    extra = metadata.model_extra or {}
    return Stamp.parse(extra.get("stamp_ns")) or Stamp.parse(metadata.stamp)


def _time(stamp: Stamp | None) -> dict[str, int] | None:
    return None if stamp is None else stamp.as_json()


def _pose(pose: Pose2D | None) -> dict[str, Any] | None:
    return None if pose is None else pose.as_metadata()


def place_pose(place: Place | Match | None, default_frame: str) -> Pose2D | None:
    """The stored pose of the place (or match) the service named, if it was posted with one."""
    if place is None or place.metadata is None:
        return None
    return Pose2D.from_metadata(place.metadata.pose, default_frame)


def _match(m: Match, default_frame: str) -> dict[str, Any]:
    return {"rank": m.rank, "seq": m.seq, "stream": m.stream, "score": m.score, "overlap": m.overlap,
            "stamp": _time(stored_stamp(m.metadata)), "pose": _pose(place_pose(m, default_frame))}


def place_json(answer: Observation, stamp: Stamp, frame_id: str, pose: Pose2D | None, latency_ms: float,
               default_frame: str) -> dict[str, Any]:
    """The place document of one answered frame (module docstring)."""
    p = answer.place
    place = None if p is None else {
        "seq": p.seq, "place_id": p.place_id, "observation_id": p.observation_id, "stream": p.stream,
        "label": p.label, "confidence": p.confidence, "revisit": p.revisit, "support": p.support,
        "low_information": p.low_information, "span": p.span, "span_seqs": p.span_seqs,
        "lagging": p.lagging, "stamp": _time(stored_stamp(p.metadata)),
        "pose": _pose(place_pose(p, default_frame)),
        "verification": None if p.verification is None else p.verification.model_dump()}
    return {"stamp": stamp.as_json(), "frame_id": frame_id, "map_id": answer.map_id, "stream": answer.stream,
            "learned": answer.learned, "seq": answer.seq, "consolidated_into": answer.consolidated_into,
            "pose": _pose(pose), "place": place,
            "matches": [_match(m, default_frame) for m in answer.matches],
            "latency_ms": round(latency_ms, 3), "request_id": answer.request_id}


def loop_closure_json(answer: Observation, stamp: Stamp, frame_id: str, pose: Pose2D | None,
                      default_frame: str) -> dict[str, Any] | None:
    """The loop-closure document of an answer whose place is a revisit; None otherwise."""
    p = answer.place
    if p is None or not p.revisit:
        return None
    v = p.verification
    relative = None
    if v is not None and v.verified and v.rotation is not None:
        (x, y, z), (qx, qy, qz, qw) = relative_pose(v.rotation, v.translation)
        relative = {"frame": "keyframe_camera_optical", "keyframe_seq": v.keyframe_seq, "inliers": v.inliers,
                    "model": v.model, "position": {"x": x, "y": y, "z": z},
                    "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}, "rotation_deg": v.rotation_deg}
    return {"kind": "closure", "id": answer.loop_closure_id, "stamp": stamp.as_json(), "frame_id": frame_id,
            "map_id": answer.map_id, "stream": answer.stream, "seq": answer.seq, "pose": _pose(pose),
            "place_stamp": _time(stored_stamp(p.metadata)), "place_seq": p.seq, "place_id": p.place_id,
            "place_stream": p.stream, "place_pose": _pose(place_pose(p, default_frame)),
            "confidence": p.confidence, "support": p.support,
            # how many places the stream may have been at (docs/design/science.md §11.11): a back end
            # divides the edge's information by it, as the service's g2o export does (None: an older server)
            "span": p.span, "span_seqs": p.span_seqs,
            "verified": None if v is None else v.verified, "relative_pose": relative}


def retraction_json(entry: LoopClosure, map_id: str) -> dict[str, Any]:
    """The retraction document of a retraction entry of the loop-closure log (module docstring): it
    repeats the withdrawn closure's pair."""
    return {"kind": "retraction", "id": entry.id, "retracts": entry.retracts, "map_id": map_id,
            "stream": entry.stream, "seq": entry.seq, "stamp": _time(stored_stamp(entry.metadata)),
            "place_seq": entry.place.seq, "place_stream": entry.place.stream,
            "place_stamp": _time(stored_stamp(entry.place.metadata))}


def closure_colour(confidence: float, threshold: float | None) -> tuple[float, float]:
    """(red, green) of a loop closure's marker, each in [0, 1]: red at the map's `revisit_threshold` (the
    least confidence a closure can have), green at 1, linear between (`threshold` None: the service's
    default). A closure is never below the threshold it was called at; one below the threshold read (it
    was lowered since) is red, as is a confidence that is not a number. Scaled from 0 instead, every
    closure (confidence >= 0.91 on the default) drew about 91 % green."""
    t = DEFAULT_REVISIT_THRESHOLD if threshold is None else min(max(threshold, 0.0), 1.0)
    x = (confidence - t) / (1.0 - t) if t < 1.0 else float(confidence >= 1.0)
    x = min(x, 1.0) if x > 0.0 else 0.0  # a NaN fails `x > 0.0`: red
    return 1.0 - x, x


def epoch_json(map_id: str, previous: str, epoch: str) -> dict[str, Any]:
    """The epoch document (module docstring): the map's log changed its epoch."""
    return {"kind": "epoch", "map_id": map_id, "previous": previous, "epoch": epoch}
