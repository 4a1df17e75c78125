"""A map's keyframes and the verification of a revisit candidate (docs/design/science.md §12,
docs/design/service.md §1.2): the glue between the map runtime, the store's `keyframes` table and the
pure geometry of `models.geometry`.

The query's features are taken in a worker thread while the backbone encodes the frame (`extract_frame`),
at most `CORTEXLOC_MAX_EXTRACTIONS` at once over all maps, the maps in turn (`Extractions`: past as
many in flight for one map its post is refused 503 `overloaded`, and one whose client went away before
its extraction started is skipped); the writer
verifies only a revisit candidate (`verify_place`), against the place's keyframe first and then
its route neighbours (along the map's links), stopping at the first that verifies.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Hashable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from models import geometry
from models.frontend.images import ImageError, RawFrame
from models.frontend.turns import TurnPool
from models.localisation import SequenceGraph
from service.maps.errors import ClientGone, InvalidCamera, Overloaded
from service.maps.results import VerificationResult

__all__ = ["Extractions", "KeyframeSource", "QueryFrame", "camera_of", "extract_frame", "revisit_stands",
           "verify_candidate", "verify_place"]


class KeyframeSource(Protocol):
    """Where a verification reads the stored keyframes: the map's store (`MapStore.keyframes`), or the
    evaluation's keyframes held in memory (`service.evaluation.service_path`)."""

    def keyframes(self, seqs: Iterable[int]) -> dict[int, tuple[bytes, dict[str, Any] | None]]:
        """{seq: (packed features, camera or None)} of those of `seqs` that have a keyframe."""
        ...


@dataclass(frozen=True)
class QueryFrame:
    """A frame's features and the camera it was taken with (a dict as stored, or None), and the
    milliseconds its extraction took."""

    features: geometry.Features
    camera: dict[str, Any] | None
    ms: float


def extract_frame(decode: Callable[..., np.ndarray], body: bytes | RawFrame,
                  keyframes: geometry.KeyframeOptions, camera: dict[str, Any] | None,
                  given: bool = False) -> QueryFrame | None:
    """Worker thread: decode the frame in grey at its native resolution with the map's encoder
    (`decode(body, grey=True)`: its byte and pixel limits, the service's settings) and take its features
    (the map's `keyframes` option) at a bounded resolution (`geometry.EXTRACT_MAX_SIDE`), in native
    pixels. None when it cannot be decoded: the encoder reports that error.

    A camera `given` with this frame is checked against the decoded frame's size here, the first place
    that size is known after the EXIF rotation (`geometry.camera_problems`); a stream's earlier camera
    was checked with its own frame.

    Raises:
        InvalidCamera: the given camera makes no sense for this frame.
    """
    t0 = time.perf_counter()
    try:
        grey = decode(body, grey=True)
    except ImageError:
        return None
    if given and (problems := geometry.camera_problems(camera_of(camera), (grey.shape[1], grey.shape[0]))):
        raise InvalidCamera(problems)
    f = geometry.extract(grey, keyframes.features, int(keyframes.max))
    return QueryFrame(f, camera, (time.perf_counter() - t0) * 1e3)


class Extractions:
    """Keyframe extractions of all maps: at most `limit` run at once, in `limit` threads that take the
    maps in turn (`TurnPool`), and each map has at most `limit` in flight (waiting or running).

    A running extraction holds a decoded frame and a feature pyramid (~300 MB for a 25 MP SIFT frame,
    docs/benchmarks.md §13.1), so the threads bound that memory; a waiting one holds only its upload,
    which the upload budget bounds. The turns keep one map's burst from locking another map out: the
    other map's post waits for at most one extraction per map ahead of it, where a first-come cap of
    `limit` over all maps refused it for as long as the burst lasted (docs/design/service.md §6).
    """

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held: dict[Hashable, int] = {}
        self._lock = threading.Lock()
        self._threads = TurnPool(limit, "keyframes")

    @property
    def pending(self) -> int:
        """Extractions in flight (reserved, waiting or running), all maps together."""
        with self._lock:
            return sum(self._held.values())

    def reserve(self, key: Hashable) -> None:
        """Take one of `key`'s (a map's) slots for one extraction (`start` it, or `release` it).

        Raises:
            Overloaded: `key` has `limit` extractions in flight (nothing taken).
        """
        with self._lock:
            held = self._held.get(key, 0)
            if held >= self.limit:
                raise Overloaded(self.limit, what=f"map {key!r}'s keyframe extraction")
            self._held[key] = held + 1

    def release(self, key: Hashable) -> None:
        """Give back a slot `reserve` took and no extraction used."""
        with self._lock:
            held = self._held.pop(key) - 1
            if held:
                self._held[key] = held

    def start(self, key: Hashable, decode: Callable[..., np.ndarray], body: bytes | RawFrame,
              keyframes: geometry.KeyframeOptions, camera: dict[str, Any] | None, given: bool,
              gone: threading.Event) -> Future[QueryFrame | None]:
        """`extract_frame` in a worker, in turn with the other maps' and in the slot `reserve` took for
        `key`; its future raises ClientGone where `gone` was set before it started (the work is skipped:
        the client went away, or the post failed). The slot comes back when the future is done,
        cancelled before it ran included."""

        def run() -> QueryFrame | None:
            if gone.is_set():
                raise ClientGone("the client went away before its keyframe extraction started")
            return extract_frame(decode, body, keyframes, camera, given)

        try:
            fut = self._threads.submit(run, key)
        except BaseException:  # never queued (shut down)
            self.release(key)
            raise
        fut.add_done_callback(lambda _: self.release(key))
        return fut

    def close(self) -> None:
        self._threads.close()


def camera_of(value: dict[str, Any] | None) -> geometry.Camera | None:
    """A stored camera dict ({fx, fy, cx, cy, distortion}, checked at the HTTP boundary) as a Camera."""
    if value is None:
        return None
    return geometry.Camera(float(value["fx"]), float(value["fy"]), float(value["cx"]), float(value["cy"]),
                           tuple(float(d) for d in value.get("distortion") or ()))


def verify_candidate(store: KeyframeSource, graph: SequenceGraph, place_seq: int, place_stream: str,
                     query: QueryFrame | None, *, stream: str, neighbours: int) -> VerificationResult:
    """Writer (and the evaluation): a revisit candidate's verification on a map with keyframes
    (docs/design/science.md §12.2): `verify_place` along the rows within `neighbours` links of the place
    (`graph.within`); `no-features` where the query frame could not be decoded for features."""
    if query is None:
        return VerificationResult(verified=False, reason="no-features")
    return verify_place(store, place_seq, place_stream, graph.within(place_seq, neighbours), query,
                        stream=stream)


def revisit_stands(revisit: bool, verification: VerificationResult, verify_revisit: bool) -> bool:
    """The revisit decision after its verification: with the map's `verify_revisit` an unverified
    candidate is no revisit; without it verification only reports (docs/design/science.md §12.2)."""
    return revisit and (verification.verified or not verify_revisit)


def verify_place(store: KeyframeSource, place_seq: int, place_stream: str, route: Iterable[int],
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
