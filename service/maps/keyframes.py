"""A map's keyframes and the verification of a revisit candidate (docs/design/science.md §12,
docs/design/service.md §1.2): the glue between the map runtime, the store's `keyframes` table and the
pure geometry of `models.geometry`.

The query's features are taken in a worker thread while the backbone encodes the frame (`extract_frame`);
the writer verifies only a revisit candidate (`verify_place`), against the place's keyframe first and then
its route neighbours (along the map's links), stopping at the first that verifies.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from models import geometry
from models.frontend.images import ImageError, RawFrame
from service.maps.results import VerificationResult
from storage.mapstore import MapStore

__all__ = ["QueryFrame", "camera_of", "extract_frame", "verify_place"]


@dataclass(frozen=True)
class QueryFrame:
    """A frame's features and the camera it was taken with (a dict as stored, or None), and the
    milliseconds its extraction took."""

    features: geometry.Features
    camera: dict[str, Any] | None
    ms: float


def extract_frame(decode: Callable[[bytes | RawFrame], np.ndarray], body: bytes | RawFrame,
                  keyframes: dict[str, Any], camera: dict[str, Any] | None) -> QueryFrame | None:
    """Worker thread: decode the frame at its native resolution with the map's encoder (`decode`: its
    byte and pixel limits, the service's settings) and take its features (the map's `keyframes` option).
    None when it cannot be decoded: the encoder reports that error."""
    t0 = time.perf_counter()
    try:
        rgb = decode(body)
    except ImageError:
        return None
    f = geometry.extract(rgb, keyframes["features"], int(keyframes["max"]))
    return QueryFrame(f, camera, (time.perf_counter() - t0) * 1e3)


def camera_of(value: dict[str, Any] | None) -> geometry.Camera | None:
    """A stored camera dict ({fx, fy, cx, cy, distortion}, checked at the HTTP boundary) as a Camera."""
    if value is None:
        return None
    return geometry.Camera(float(value["fx"]), float(value["fy"]), float(value["cx"]), float(value["cy"]),
                           tuple(float(d) for d in value.get("distortion") or ()))


def verify_place(store: MapStore, place_seq: int, place_stream: str, route: Iterable[int],
                 query: QueryFrame, *, stream: str) -> VerificationResult:
    """Writer: verify the query against the keyframe of `place_seq`, then those of its `route`
    neighbours (the rows within `CORTEXLOC_VERIFY_NEIGHBOURS` links of it, `SequenceGraph.within`),
    nearest first; the first verified one is the answer, else the candidate with the most inliers
    (docs/design/science.md §12.2).

    A keyframe without a camera is taken with the query's when both come from one stream (one robot's
    camera); otherwise the pose is left out (`no-camera`). `stream`: the query's."""
    t0 = time.perf_counter()
    # Along a link chain seqs increase, so |seq - place_seq| orders each side by links.
    order = sorted({place_seq, *(int(s) for s in route)}, key=lambda s: (abs(s - place_seq), s))
    stored = store.keyframes(order)
    q_cam = camera_of(query.camera)
    best: tuple[int, geometry.Verification] | None = None
    for seq in order:
        if seq not in stored:
            continue
        blob, cam = stored[seq]
        k_cam = camera_of(cam) if cam is not None else (q_cam if place_stream == stream else None)
        v = geometry.verify(query.features, geometry.unpack(blob), q_cam, k_cam)
        if best is None or (v.verified, v.inliers) > (best[1].verified, best[1].inliers):
            best = (seq, v)
        if v.verified:
            break
    ms = (time.perf_counter() - t0) * 1e3
    if best is None:
        return VerificationResult(verified=False, reason="no-keyframe", ms=ms)
    return VerificationResult.of(best[1], keyframe_seq=best[0], ms=ms)
