"""`cortexloc eval images --methods service,service-without-tm`: the service's own code path over a
database traverse (learned) then a query traverse (localised, one stream), scored per query
(docs/design/service.md §1.2, docs/design/science.md §11.4).

Not a re-implementation: the map's configuration is resolved and checked as a created map's
(`service.maps.config.resolve`), its projection is made as the registry makes it
(`service.maps.encoding.projection.for_map`), and every frame goes through `models.pipeline.observe`,
the step the map's writer runs (`MapRuntime._step`), on a `MapModel` built as a served map's
(`config.map_model`). The rules the writer applies around that step are the writer's own functions:
forgetting at the map's row cap (`models.localisation.forgetting.to_forget`, docs/design/science.md
§11.9) before a learned frame, and on a map with keyframes the verification of a revisit candidate
(`service.maps.keyframes.verify_candidate`, §12) on the frame's local features, taken from the frame as
the service takes them (`extract_frame`). Nothing is stored: the rows' seqs are 1, 2, ... as a fresh
map's would be, and the keyframes are held in memory (`_Keyframes`). Only the decoding and the backbone
are done before, once per folder (the feature cache), with the same encoder.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from models import geometry
from models.evaluation.online import OnlineAnswers
from models.frontend import images as frontend_images
from models.frontend import slsbh
from models.localisation import Place, SequenceGraph, forgetting
from models.localisation.motion import NO_MOTION, Motion
from models.pipeline import MapModel, Stream, drop, observe
from service.maps import keyframes
from service.maps.config import MapConfig, MapOptions, map_model, resolve
from service.maps.encoding import projection as map_projection
from service.maps.results import VerificationResult
from service.settings import Settings

__all__ = ["METHODS", "SLAM_METHODS", "experiment", "forget", "operating_point", "replay", "slam_replay"]

#: The service's methods and their map option `memory`.
METHODS = {"service": "tm", "service-without-tm": "none"}
#: The same as one learning stream (loop closure while mapping, docs/design/science.md §11.6).
SLAM_METHODS = {"service-slam": "tm", "service-slam-without-tm": "none"}


def _model(feature_dim: int, *, backbone: str, preset: str, seed: int, memory: str,
           localiser: dict[str, Any] | None, create: dict[str, Any] | None,
           max_observations: int | None = None) -> tuple[MapModel, slsbh.Hasher, MapConfig]:
    """A served map's pipeline model and projection, from the same configuration (`resolve`), with the
    served row cap (`CORTEXLOC_MAX_OBSERVATIONS`) unless `max_observations` gives another."""
    options = MapOptions(preset=preset, seed=seed, memory=memory, backbone=backbone, localiser=localiser,
                         **(create or {}))
    config = resolve(options, default_preset=preset, default_backbone=backbone)
    defaults = Settings()  # a served map's caps, as the registry applies them
    _, P = map_projection.for_map(config, feature_dim, defaults.max_streams, defaults.max_map_bytes)
    hasher = slsbh.Hasher(P, float(config.sections.slsbh.s))
    cap = defaults.max_observations if max_observations is None else max_observations
    return map_model(config, max_observations=cap), hasher, config


def forget(model: MapModel) -> list[int]:
    """Before a learned frame, as the map writer (`MapRuntime.apply`): the rows the cap rule forgets
    (`forgetting.to_forget`, docs/design/science.md §11.9; none under the cap), out of the model."""
    gone = forgetting.to_forget(model.index, model.place_map)
    drop(model, gone)
    return gone


class _Keyframes:
    """A map's keyframes held in memory as its store holds them (`keyframes.KeyframeSource`), and the
    verification of its revisit candidates as the writer's (`MapRuntime._verified`,
    docs/design/science.md §12): the frame's features taken as the service takes them (`extract_frame`,
    decoded in grey at native resolution), a made row's keyframe kept after its step's verification (the
    writer verifies before the row is stored), every candidate verified with `verify_candidate` within
    `CORTEXLOC_VERIFY_NEIGHBOURS` links, and the answer a revisit by `revisit_stands`.

    Args:
        config: the map's configuration (its `keyframes`, `verify_revisit` and `revisit_threshold`).
        frames: the encoded images, indexed as the caller's frames.
        camera: the camera they were taken with ({fx, fy, cx, cy, distortion}), given with the first
            frame and checked against it (`InvalidCamera`); None: none.
    """

    def __init__(self, config: MapConfig, frames: Sequence[bytes], camera: dict[str, Any] | None) -> None:
        self.config, self.frames, self.camera = config, frames, camera
        self.neighbours = Settings().verify_neighbours
        self.held: dict[int, tuple[bytes, dict[str, Any] | None]] = {}

    def keyframes(self, seqs: Iterable[int]) -> dict[int, tuple[bytes, dict[str, Any] | None]]:
        return {int(s): self.held[int(s)] for s in seqs if int(s) in self.held}

    def query(self, i: int) -> keyframes.QueryFrame | None:
        """Frame i's local features and camera (None: it cannot be decoded)."""
        options = self.config.sections.keyframes
        assert options is not None
        return keyframes.extract_frame(frontend_images.decode, self.frames[i], options,
                                       self.camera, given=self.camera is not None and i == 0)

    def verify(self, place: Place, query: keyframes.QueryFrame | None, graph: SequenceGraph, *, stream: str,
               place_stream: str) -> tuple[bool, VerificationResult | None]:
        """(the answer is a revisit, its verification or None where it is no candidate)."""
        revisit = place.is_revisit(self.config.revisit_threshold)
        if not revisit:
            return False, None
        v = keyframes.verify_candidate(self, graph, place.seq, place_stream, query, stream=stream,
                                       neighbours=self.neighbours)
        return keyframes.revisit_stands(revisit, v, self.config.verify_revisit), v

    def made(self, seq: int, query: keyframes.QueryFrame | None) -> None:
        """The keyframe a learned row `seq` stores (none where its frame had no features)."""
        if query is not None:
            self.held[seq] = (geometry.pack(query.features), query.camera)


def _keyframes(config: MapConfig, frames: Sequence[bytes] | None, camera: dict[str, Any] | None,
               n: int) -> _Keyframes | None:
    """The map's keyframes where it has them (None where not); ValueError where they lack the frames."""
    if config.keyframes is None:
        return None
    if frames is None or len(frames) != n:
        raise ValueError(f"a map with keyframes verifies its revisits on the frames: give the {n} encoded "
                         f"images (frames), got {None if frames is None else len(frames)}")
    return _Keyframes(config, frames, camera)


def slam_replay(feats: np.ndarray, *, encoder_id: str, backbone: str, preset: str, seed: int,
                memory: str = "tm", localiser: dict[str, Any] | None = None,
                create: dict[str, Any] | None = None, contrast: np.ndarray | None = None,
                progress: Callable[[int, int], None] | None = None,
                trace: dict[str, Any] | None = None, max_observations: int | None = None,
                frames: Sequence[bytes] | None = None,
                camera: dict[str, Any] | None = None,
                motions: Sequence[Motion] | None = None,
                streams: Sequence[str] | None = None) -> tuple[OnlineAnswers, float]:
    """A whole route as ONE learning stream (every frame learned, `models.pipeline.observe` as the map
    writer calls it, forgetting at the cap and verifying as it does): loop closure while mapping
    (docs/design/science.md §11.6).

    Args:
        feats: (T, D) backbone features in driven order (all laps). Other arguments as `replay`.
        trace: filled, where given, with what the map made of the frames: "row_frame" (R,) the frame
            each made row came from (row seq - 1), "row_place" (R,) each row's place id at the end,
            "row_held" (R,) bool, the row is still held at the end (not forgotten at the cap nor dropped
            over its place's cap, §11.9), "visit" (T,) the row a consolidated frame went into (-1: it
            made a row), "revisit" (T,) bool, the answer is a revisit as the service replies it
            (after its verification), "verification" (T,) each answer's `VerificationResult` or None
            (no candidate, or a map without keyframes).
        motions: (T,) each frame's pose, stamp and trail (`Motion`, as a served map reads them from
            `metadata`; docs/design/science.md §11.6); None: none.
        streams: (T,) the stream that posts each frame (a robot's two cameras, each its own stream,
            naming one trail in `motions`); None: every frame one stream's, `robot`.

    Returns:
        (answers over the route's own frames: best = the frame the `place` names, -1 in warm-up;
        confidence 0 where the frame cannot be a revisit: too flat, §11.7, too wide a span, §11.11, or
        `verify_revisit` refused it, §12.2; S is empty (0, T)), and the map's `revisit_threshold`.
    """
    del encoder_id
    T = len(feats)
    model, hasher, config = _model(int(feats.shape[1]), backbone=backbone, preset=preset, seed=seed,
                                   memory=memory, localiser=localiser, create=create,
                                   max_observations=max_observations)
    kf = _keyframes(config, frames, camera, T)
    robots: dict[str, Stream] = {}
    codes, frame_of, stream_of = {}, {}, {}
    best, confidence, support = np.full(T, -1, np.int64), np.zeros(T), np.zeros(T, np.int64)
    visit = np.full(T, -1, np.int64)
    revisit, verification = np.zeros(T, bool), [None] * T
    for i, y in enumerate(hasher.project(feats)):  # a consolidated frame makes no row (§11.8)
        seq = len(codes) + 1
        forget(model)
        query = None if kf is None else kf.query(i)
        name = "robot" if streams is None else streams[i]
        step = observe(model, robots.setdefault(name, Stream()), y, learn=True, stream=name, top_k=0,
                       seq=seq, code_of=codes.__getitem__, threshold=config.revisit_threshold,
                       contrast=_at(contrast, i), motion=NO_MOTION if motions is None else motions[i])
        if step.place is not None:
            revisit[i], verification[i] = _answered(step.place, config, kf, query, model.place_map.graph,
                                                    name, stream_of.get(step.place.seq, name))
            refused = verification[i] is not None and not revisit[i]
            best[i], confidence[i] = frame_of[step.place.seq], _decided(step.place, refused)
            support[i] = step.place.support
        if step.visit is None:
            codes[seq], frame_of[seq], stream_of[seq] = step.code, i, name
            if kf is not None:
                kf.made(seq, query)
        else:
            visit[i] = step.visit
        if progress:
            progress(i + 1, T)
    if trace is not None:
        seqs = np.array(sorted(frame_of), np.int64)
        trace["row_frame"] = np.array([frame_of[q] for q in seqs], np.int64)
        trace["row_place"] = model.place_map.graph.place[seqs].astype(np.int64)
        trace["row_held"] = model.place_map.used[seqs] >= 0
        trace["visit"] = visit
        trace["revisit"], trace["verification"] = revisit, verification
    return OnlineAnswers(best, confidence, support, np.zeros((0, T))), config.revisit_threshold


def contrasts(images: Iterable[bytes]) -> np.ndarray:
    """(n,) each encoded image's contrast as the service measures it at decode (`images.contrast`,
    docs/design/science.md §11.7), for the `contrast` of `replay` and `slam_replay`."""
    return np.array([frontend_images.contrast(frontend_images.decode(b)) for b in images])


def _at(contrast: np.ndarray | None, i: int) -> float | None:
    return None if contrast is None else float(contrast[i])


def _decided(place: Place, refused: bool = False) -> float:
    """The confidence the revisit decision compares: 0 for a frame too flat to be a revisit at any
    threshold or whose span is wider than `span_max` (`Place.is_revisit`, docs/design/science.md §11.7,
    §11.11), and for a candidate its verification
    `refused` on a map with `verify_revisit` (`keyframes.revisit_stands`, §12.2)."""
    return 0.0 if refused else place.decided


def _answered(place: Place, config: MapConfig, kf: _Keyframes | None, query: keyframes.QueryFrame | None,
              graph: SequenceGraph, stream: str, place_stream: str) -> tuple[bool, VerificationResult | None]:
    """(the answer is a revisit as the service replies it, its verification or None): verified on a map
    with keyframes (`_Keyframes.verify`), else the revisit decision alone (`Place.is_revisit`)."""
    if kf is None:
        return place.is_revisit(config.revisit_threshold), None
    return kf.verify(place, query, graph, stream=stream, place_stream=place_stream)


def replay(db_feats: np.ndarray, q_feats: np.ndarray, *, encoder_id: str, backbone: str, preset: str,
           seed: int, memory: str = "tm", localiser: dict[str, Any] | None = None,
           create: dict[str, Any] | None = None, contrast: np.ndarray | None = None,
           progress: Callable[[int, int], None] | None = None, max_observations: int | None = None,
           frames: Sequence[bytes] | None = None, camera: dict[str, Any] | None = None,
           trace: dict[str, Any] | None = None) -> OnlineAnswers:
    """Learn `db_feats` as one traverse (stream `database`), then localise `q_feats` (stream `query`),
    forgetting at the map's row cap before each learned frame and verifying revisit candidates on a map
    with keyframes, as the map writer does (docs/design/science.md §11.9, §12).

    Args:
        db_feats, q_feats: (n_db, D), (n_q, D) backbone features in driven order (`Embedder.embed`).
        encoder_id, backbone: the encoder they came from (a served map freezes them; here the backbone
            is checked like a created map's, `encoder_id` only names them).
        preset, seed, memory, localiser: the map's `CreateMap` fields; `create`: any further ones.
        contrast: (n_db + n_q,) each frame's contrast (`models.frontend.images.contrast`), or None.
        progress: called with (frames done, frames in all).
        max_observations: the map's row cap (None: the served one, `CORTEXLOC_MAX_OBSERVATIONS`).
        frames: (n_db + n_q) the encoded images, required on a map with keyframes (`create`'s
            `keyframes`): its revisit candidates are verified on their local features. camera: the
            camera they were taken with (`_Keyframes`), or None.
        trace: filled, where given: "row_held" (n_db,) bool, the database row is still held at the end
            (§11.9); "revisit" (n_q,) bool, the query's answer is a revisit as the service replies it
            (after its verification); "verification" (n_q,) its `VerificationResult` or None;
            "span" (n_q,) int, the answer's span (§11.11; 0: no answer) and "span_rows" (n_q,) its
            `span_seqs` as database rows (seq - 1; empty: no answer).

    Returns:
        `OnlineAnswers` over database rows 0..n_db-1: the `place` answers (best -1 during warm-up,
        confidence (0 for a frame that cannot be a revisit: too flat, §11.7, too wide a span, §11.11, or
        one `verify_revisit` refused, §12.2), support) and S, the query stream's beam scores after each
        frame (-inf elsewhere).
    """
    del encoder_id  # the features are the encoder's; a map would freeze its identity
    n_db, n_q = len(db_feats), len(q_feats)
    model, hasher, config = _model(int(db_feats.shape[1]), backbone=backbone, preset=preset, seed=seed,
                                   memory=memory, localiser=localiser, create=create,
                                   max_observations=max_observations)
    kf = _keyframes(config, frames, camera, n_db + n_q)
    codes: dict[int, np.ndarray] = {}
    database, query = Stream(), Stream()
    for i, y in enumerate(hasher.project(db_feats)):
        forget(model)
        frame = None if kf is None else kf.query(i)
        step = observe(model, database, y, learn=True, stream="database", top_k=0, seq=i + 1,
                       code_of=codes.__getitem__, contrast=_at(contrast, i))
        # (the writer verifies the traverse's own candidates too: that changes only its replies)
        codes[i + 1] = step.code
        if kf is not None:
            kf.made(i + 1, frame)
        if progress:
            progress(i + 1, n_db + n_q)
    best, confidence = np.full(n_q, -1, np.int64), np.zeros(n_q)
    support, S = np.zeros(n_q, np.int64), np.full((n_db, n_q), -np.inf)
    revisit, verification = np.zeros(n_q, bool), [None] * n_q
    span, span_rows = np.zeros(n_q, np.int64), [()] * n_q
    for j, y in enumerate(hasher.project(q_feats)):
        frame = None if kf is None else kf.query(n_db + j)
        place = observe(model, query, y, learn=False, stream="query", top_k=0,
                        code_of=codes.__getitem__, contrast=_at(contrast, n_db + j)).place
        state = query.localiser
        assert state is not None
        live = state.rows >= 0
        np.maximum.at(S[:, j], state.rows[live] - 1, state.scores[live])  # seq s is database row s - 1
        if place is not None:
            revisit[j], verification[j] = _answered(place, config, kf, frame, model.place_map.graph, "query",
                                                    "database")
            refused = verification[j] is not None and not revisit[j]
            best[j], confidence[j] = place.seq - 1, _decided(place, refused)
            support[j] = place.support
            span[j], span_rows[j] = place.span, tuple(s - 1 for s in place.span_seqs)
        if progress:
            progress(n_db + j + 1, n_db + n_q)
    if trace is not None:
        trace["row_held"] = model.place_map.used[1:n_db + 1] >= 0
        trace["revisit"], trace["verification"] = revisit, verification
        trace["span"], trace["span_rows"] = span, span_rows
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
               map_conf: dict[str, Any], progress: Callable[[int, int], None] | None = None,
               contrast: np.ndarray | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
    """The service methods over seeds, scored like the others (`sequences.evaluate`).

    Args:
        methods: keys of METHODS. columns: (n_q,) bool, the scored queries (file order).
        map_conf: `replay`'s map keywords (encoder_id, backbone, preset, localiser, create).
        contrast: (n_db + n_q,) each frame's contrast in file order (`contrasts`), or None.
        Other arguments as `models.evaluation.sequences.image_experiment`.

    Returns:
        ({method: summary entry as image_experiment's}, {method: the first seed's answers and curves}).
    """
    from models.evaluation import sequences

    summary: dict[str, Any] = {}
    first: dict[str, Any] = {}
    children = np.random.SeedSequence(seed).spawn(seeds)
    q_driven = q_feats[::-1] if reverse_query else q_feats
    if contrast is not None and reverse_query:
        contrast = np.r_[contrast[:len(db_feats)], contrast[len(db_feats):][::-1]]
    for m in methods:
        runs = []
        for child in children:
            run_seed = int(child.generate_state(1)[0]) % 2**31
            t0 = time.perf_counter()
            found = replay(db_feats, q_driven, seed=run_seed, memory=METHODS[m], progress=progress,
                           contrast=contrast, **map_conf)
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
