"""`cortexloc eval images --methods service,service-without-tm`: the service's own code path over a
database traverse (learned) then a query traverse (localised, one stream), scored per query
(docs/design/service.md §1.2, docs/design/science.md §11.4).

Not a re-implementation: a real `MapRegistry` on a temporary data directory creates the map (the same
parameters, projection, Temporal Memory, store, index and localiser as a served map), and every frame
goes through `MapRuntime.apply` in the map's writer thread, the step `MapRuntime.observe` queues once
the encoder pool has projected the image. Only the decoding and the backbone are done before, once per
folder (the feature cache), with the same encoder; the projection is the map's own (`rt.hasher`).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from models.evaluation.online import OnlineAnswers
from service.maps.encoders import Encoders
from service.maps.registry import MapRegistry
from service.maps.runtime import MapRuntime
from service.settings import Settings

__all__ = ["METHODS", "SLAM_METHODS", "FeaturesOnly", "experiment", "operating_point", "replay",
           "slam_replay"]

#: The service's methods and their map option `memory`.
METHODS = {"service": "tm", "service-without-tm": "none"}
#: The same as one learning stream (loop closure while mapping, docs/design/science.md §11.6).
SLAM_METHODS = {"service-slam": "tm", "service-slam-without-tm": "none"}


@dataclass(frozen=True)
class FeaturesOnly:
    """What a `MapRegistry` reads of an encoder when the features come from elsewhere (the cache)."""

    identity: str
    feature_dim: int


def _step(rt: MapRuntime, y: np.ndarray, *, learn: bool, stream: str) -> Any:
    sha = hashlib.sha256(np.ascontiguousarray(y).tobytes()).hexdigest()
    step = functools.partial(rt.apply, y, sha, learn=learn, stream=stream, top_k=0, label=None)
    return rt.submit(step).result()


@contextlib.contextmanager
def _eval_map(n_rows: int, feature_dim: int, *, encoder_id: str, backbone: str, preset: str, seed: int,
              memory: str, localiser: dict[str, Any] | None, create: dict[str, Any] | None
              ) -> Iterator[MapRuntime]:
    """A served map on a temporary data directory (the service's registry, store, index, localiser)."""
    with tempfile.TemporaryDirectory(prefix="cortexloc-eval-") as tmp:
        settings = Settings(data_dir=Path(tmp), snapshot_every=0, max_observations=max(n_rows, 1))
        encoders = Encoders.one(FeaturesOnly(encoder_id, feature_dim), backbone)
        registry = MapRegistry(Path(tmp), encoders, settings)
        try:
            rt = registry.create("eval", preset=preset, seed=seed, memory=memory, backbone=backbone,
                                 localiser=localiser, **(create or {}))
            assert rt.hasher is not None
            yield rt
        finally:
            registry.close()


def slam_replay(feats: np.ndarray, *, encoder_id: str, backbone: str, preset: str, seed: int,
                memory: str = "tm", localiser: dict[str, Any] | None = None,
                create: dict[str, Any] | None = None, stream: str = "robot",
                progress: Callable[[int, int], None] | None = None) -> tuple[OnlineAnswers, float]:
    """Post a whole route as ONE learning stream (`learn=true` every frame): loop closure while mapping.

    Args:
        feats: (T, D) backbone features in driven order (all laps). Other arguments as `replay`.

    Returns:
        (answers over the route's own frames: best = the frame the `place` names, -1 in warm-up; S is
        empty (0, T)), and the map's `revisit_threshold`.
    """
    T = len(feats)
    with _eval_map(T, int(feats.shape[1]), encoder_id=encoder_id, backbone=backbone, preset=preset,
                   seed=seed, memory=memory, localiser=localiser, create=create) as rt:
        assert rt.hasher is not None
        frame_of = np.full(T + 2, -1, np.int64)  # seq -> frame
        best, confidence, support = np.full(T, -1, np.int64), np.zeros(T), np.zeros(T, np.int64)
        for i, y in enumerate(rt.hasher.project(feats)):
            result = _step(rt, y, learn=True, stream=stream)
            frame_of[result.seq] = i
            if result.place is not None:
                best[i], confidence[i], support[i] = (frame_of[result.place.seq], result.place.confidence,
                                                      result.place.support)
            if progress:
                progress(i + 1, T)
        return OnlineAnswers(best, confidence, support, np.zeros((0, T))), rt.revisit_threshold


def replay(db_feats: np.ndarray, q_feats: np.ndarray, *, encoder_id: str, backbone: str, preset: str,
           seed: int, memory: str = "tm", localiser: dict[str, Any] | None = None,
           create: dict[str, Any] | None = None,
           progress: Callable[[int, int], None] | None = None) -> OnlineAnswers:
    """Learn `db_feats` as one traverse (stream `database`), then localise `q_feats` (stream `query`).

    Args:
        db_feats, q_feats: (n_db, D), (n_q, D) backbone features in driven order (`Encoder.embed`).
        encoder_id, backbone: the encoder they came from (frozen into the map as a served map's are).
        preset, seed, memory, localiser: the map's `CreateMap` fields; `create`: any further ones.
        progress: called with (frames done, frames in all).

    Returns:
        `OnlineAnswers` over database rows 0..n_db-1: the `place` answers (best -1 during warm-up,
        confidence, support) and S, the query stream's beam scores after each frame (-inf elsewhere).
    """
    n_db, n_q = len(db_feats), len(q_feats)
    with _eval_map(n_db, int(db_feats.shape[1]), encoder_id=encoder_id, backbone=backbone, preset=preset,
                   seed=seed, memory=memory, localiser=localiser, create=create) as rt:
        assert rt.hasher is not None
        row_of = np.full(n_db + 2, -1, np.int64)  # seq -> database row
        for i, y in enumerate(rt.hasher.project(db_feats)):
            row_of[_step(rt, y, learn=True, stream="database").seq] = i
            if progress:
                progress(i + 1, n_db + n_q)
        best, confidence = np.full(n_q, -1, np.int64), np.zeros(n_q)
        support, S = np.zeros(n_q, np.int64), np.full((n_db, n_q), -np.inf)
        for j, y in enumerate(rt.hasher.project(q_feats)):
            place = _step(rt, y, learn=False, stream="query").place
            state = rt.streams["query"].localiser
            assert state is not None
            live = state.rows >= 0
            np.maximum.at(S[:, j], row_of[state.rows[live]], state.scores[live])
            if place is not None:
                best[j], confidence[j], support[j] = row_of[place.seq], place.confidence, place.support
            if progress:
                progress(n_db + j + 1, n_db + n_q)
    return OnlineAnswers(best, confidence, support, S)


def operating_point(confidence: np.ndarray, correct: np.ndarray, precision: float) -> dict[str, float] | None:
    """The lowest confidence threshold whose answers (confidence >= it) reach `precision`, per query.

    Args:
        confidence: (n,) each scored query's confidence; correct: (n,) bool, its answer is right.
        precision: the precision wanted, in (0, 1].

    Returns:
        {"threshold", "precision", "recall"} (recall = right answers kept / queries), or None when no
        threshold reaches it.
    """
    confidence, correct = np.asarray(confidence, np.float64), np.asarray(correct, bool)
    order = np.argsort(-confidence, kind="stable")
    c, ok = confidence[order], correct[order]
    hits = np.cumsum(ok)
    prec = hits / np.arange(1, c.size + 1)
    last = np.r_[c[1:] != c[:-1], True]  # a threshold keeps every query of equal confidence
    reach = np.flatnonzero(last & (prec >= precision))
    if reach.size == 0:
        return None
    i = int(reach[-1])
    return {"threshold": float(c[i]), "precision": float(prec[i]), "recall": float(hits[i] / c.size)}


def experiment(db_feats: np.ndarray, q_feats: np.ndarray, *, methods: list[str], columns: np.ndarray,
               tolerance: int, gt: np.ndarray | None, seeds: int, seed: int, reverse_query: bool,
               map_conf: dict[str, Any], progress: Callable[[int, int], None] | None = None
               ) -> tuple[dict[str, Any], dict[str, Any]]:
    """The service methods over seeds, scored like the others (`sequences.evaluate`).

    Args:
        methods: keys of METHODS. columns: (n_q,) bool, the scored queries (file order).
        map_conf: `replay`'s map keywords (encoder_id, backbone, preset, localiser, create).
        Other arguments as `models.evaluation.sequences.image_experiment`.

    Returns:
        ({method: summary entry as image_experiment's}, {method: the first seed's answers and curves}).
    """
    from models.evaluation import sequences

    summary: dict[str, Any] = {}
    first: dict[str, Any] = {}
    children = np.random.SeedSequence(seed).spawn(seeds)
    q_driven = q_feats[::-1] if reverse_query else q_feats
    for m in methods:
        runs = []
        for child in children:
            run_seed = int(child.generate_state(1)[0]) % 2**31
            t0 = time.perf_counter()
            found = replay(db_feats, q_driven, seed=run_seed, memory=METHODS[m], progress=progress,
                           **map_conf)
            seconds = time.perf_counter() - t0
            S, best, conf = found.S, found.best, found.confidence
            if reverse_query:
                S, best, conf = S[:, ::-1], best[::-1], conf[::-1]
            r = sequences.evaluate(S, tolerance, gt, columns, (best, conf))
            first.setdefault(m, {key: r[key] for key in ("P", "R", "query_P", "query_R", "best", "confidence",
                                                        "correct")} | {"S": S})
            runs.append({"seed": {"map": run_seed}, **{key: float(r[key]) for key in sequences.METRICS},
                         "seconds": seconds, "support_mean": float(found.support[found.best >= 0].mean())})
        entry: dict[str, Any] = {"memory": METHODS[m]}
        for key in sequences.METRICS:
            vals = np.array([r[key] for r in runs])
            entry.update({f"{key}_mean": float(vals.mean()), f"{key}_min": float(vals.min()),
                          f"{key}_max": float(vals.max())})
        entry["seconds_mean"] = float(np.mean([r["seconds"] for r in runs]))
        entry["per_seed"] = runs
        summary[m] = entry
    return summary, first
