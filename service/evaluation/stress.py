"""The loop-closure stress suite: one robot mapping while it drives, on routes made to break the own-trail
rules (issue 35; docs/design/science.md §11.6, docs/results.md §10.11).

    cortexloc eval slam --suite --data ../shared/data/nordland_tiny_64x32 [--quick] [--json out.json]

Every case is a route made from a 200-frame window of a Nordland half (labels = file index), driven as
ONE learning stream through the service's path (`service_path.slam_replay`), at 3 map seeds (1, 7 and
42, a new map's), with the memory and without it (the ablation), beside the localise mode on the same
lap-2 frames and OpenSeqSLAM run online (`models.evaluation.slam.openseqslam_online`):
- `rate1`, `rate3`, `rate10`: one pass at 1x, and each frame posted 3 or 10 times with pixel noise
  (σ 4): a slower robot, a faster camera. No frame is a true revisit (`slam.revisit_truth`).
- `parked`: 60 frames, one frame posted 200 times (σ 2: a parked robot, 10x the short-term memory),
  60 frames on. No true revisit.
- `flat`: the window blurred and flattened (low texture: a plateau, a bare corridor). No true revisit.
- `repeat`: 100 frames, then 40 of them again with other noise and shifted crops, inside one lap. The
  labels come back, so the truth calls them revisits: without poses the service cannot tell a place
  that looks the same from the same place (with distinct poses they would not be a loop).
- `short-loop`: 40 frames driven three times (a real short loop must still close).
- `seasons`, `noise`: the window, then again in winter or with pixel noise (σ 8): lap 2 is a revisit.
- `faster`: the window, then every other file of it in winter: lap 2 at twice the pace the map was
  learned at (a faster drive, frames shed under load; docs/results.md §10.27-§10.28).
- `cameras`: the window posted by a robot's two cameras as two streams, `front` (the frames) and `rear`
  (each frame again with σ 4 noise: nearly one view, as a stereo pair's), both naming one trail
  (`metadata.trail`), both frames of a moment with its stamp: each camera's frames are the other's
  recent rows, its short-term memory; then again in winter by both (lap 2: a revisit for each camera).

Per case and seed: false revisits while mapping (every call not a true revisit named right), merged
places (places whose rows' labels differ by more than the tolerance), wrong consolidations (frames
consolidated into a row of another label), and for lap 2 precision, recall and recall at 100 %
precision. The full suite covers every window of both halves slid by 100; `--quick` one window of
`tune`, five cases, two seeds, the memory only (what `make test` runs, tests/service/evaluation).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from models.evaluation import seqslam, sequences, slam
from models.frontend.embedding import Embedder
from models.localisation.motion import Motion
from service.evaluation import service_path
from service.evaluation.slam import grey
from service.maps.config import DEFAULT_REVISIT_THRESHOLD

#: Every case of the full suite, in the order they are run.
CASES = ("rate1", "rate3", "rate10", "parked", "flat", "repeat", "short-loop", "seasons", "noise", "cameras",
         "faster")
#: What `--quick` runs: one case of each failure (a slower robot, low texture, a robot's two cameras) and
#: of each real loop.
QUICK_CASES = ("rate3", "flat", "cameras", "short-loop", "noise")
#: The `cameras` case's frames: both streams name one trail (`metadata.trail`, docs/design/science.md §11.6)
TRAIL = Motion(trail="robot")
#: The map seeds every case is read over; 42 is a new map's (`CreateMap.seed`'s default).
SEEDS = (1, 7, 42)
QUICK_SEEDS = (1, 42)
WINDOW, STRIDE = 200, 100
HALVES = {"tune": (0, 894), "test": (894, 1788)}
TOLERANCE = 1


@dataclass(frozen=True)
class Route:
    """A case's frames: `pngs` (T,) encoded, `labels` (T,) place labels, `laps` (T,) lap of each."""

    name: str
    pngs: list[bytes]
    labels: np.ndarray
    laps: np.ndarray
    #: (T,) the stream posting each frame, all naming the trail `robot` (None: one stream, `robot`)
    streams: tuple[str, ...] | None = None
    #: (T,) each frame's stamp in seconds, its `metadata.stamp` (None: unstamped)
    stamps: tuple[float, ...] | None = None


class Frames:
    """A Nordland folder's frames as (H, W, 3) uint8 arrays and PNGs, and features by content."""

    def __init__(self, data: Path, enc: Embedder, cache: Path) -> None:
        self.names = sequences.paired_names(data / "summer", data / "winter")
        self.data, self.enc, self.cache = data, enc, cache

    def image(self, season: str, i: int) -> np.ndarray:
        img = cv2.imread(str(self.data / season / self.names[i]), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"{self.data / season / self.names[i]}: not an image")
        return img

    def features(self, pngs: list[bytes]) -> np.ndarray:
        """(T, D) the encoder's features of `pngs`, cached by their bytes and the encoder's identity."""
        digest = hashlib.sha256(self.enc.identity.encode())
        for b in pngs:
            digest.update(hashlib.sha256(b).digest())
        path = self.cache / f"stress-{digest.hexdigest()}.npy"
        if path.exists():
            return np.load(path)
        feats = np.concatenate([self.enc.embed(pngs[i:i + 64]).features for i in range(0, len(pngs), 64)])
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, feats.astype(np.float32))
        return feats


def png(img: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", np.clip(img, 0, 255).astype(np.uint8))
    assert ok
    return buf.tobytes()


def variant(img: np.ndarray, kind: str, seed: int) -> bytes:
    """A view of `img`: `noise:<σ>` pixel noise, `flat` blurred and its contrast cut to 35 % (low
    texture), `shift` a crop moved up to 3 px sideways with σ 4 noise; seeded."""
    a = img.astype(np.float32)
    rng = np.random.default_rng(seed)
    if kind.startswith("noise:"):
        a = a + rng.normal(0.0, float(kind[6:]), a.shape)
    elif kind == "flat":
        a = cv2.GaussianBlur(a, (0, 0), 3.0)
        a = a.mean() + 0.35 * (a - a.mean()) + rng.normal(0.0, 1.5, a.shape)
    elif kind == "shift":
        a = np.roll(a, int(rng.integers(-3, 4)), axis=1) + rng.normal(0.0, 4.0, a.shape)
    else:
        raise ValueError(f"unknown variant {kind!r}")
    return png(a)


def route(frames: Frames, case: str, lo: int) -> Route:
    """The case's route from the window of files [lo, lo + 200) (module docstring)."""
    pngs: list[bytes] = []
    labels: list[int] = []
    laps: list[int] = []

    def add(season: str, idx: range | list[int], kind: str | None = None, lap: int = 0,
            seed: int = 0) -> None:
        for j, i in enumerate(idx):
            img = frames.image(season, i)
            pngs.append(png(img) if kind is None else variant(img, kind, seed + 7919 * j + i))
            labels.append(i)
            laps.append(lap)

    if case == "rate1":
        add("summer", range(lo, lo + WINDOW))
    elif case in ("rate3", "rate10"):
        copies = 3 if case == "rate3" else 10
        for i in range(lo, lo + (WINDOW if copies == 3 else 60)):
            for c in range(copies):
                add("summer", [i], "noise:4", 0, 1000 * c)
    elif case == "parked":
        add("summer", range(lo, lo + 60))
        add("summer", [lo + 60] * 200, "noise:2", 0, 5000)
        add("summer", range(lo + 61, lo + 120))
    elif case == "flat":
        add("summer", range(lo, lo + WINDOW), "flat", 0, 7)
    elif case == "repeat":
        add("summer", range(lo, lo + 100))
        add("summer", range(lo + 20, lo + 60), "shift", 0, 99)
    elif case == "short-loop":
        for k in range(3):
            add("summer", range(lo, lo + 40), None if k == 0 else "noise:4", k, 300 * k)
    elif case == "seasons":
        add("summer", range(lo, lo + WINDOW))
        add("winter", range(lo, lo + WINDOW), None, 1)
    elif case == "noise":
        add("summer", range(lo, lo + WINDOW))
        add("summer", range(lo, lo + WINDOW), "noise:8", 1, 3)
    elif case == "faster":
        add("summer", range(lo, lo + WINDOW))
        add("winter", range(lo, lo + WINDOW, 2), None, 1)
    elif case == "cameras":
        for season, lap in (("summer", 0), ("winter", 1)):
            for i in range(lo, lo + WINDOW):
                add(season, [i], None, lap)
                add(season, [i], "noise:4", lap, 2000)
        streams = ("front", "rear") * (2 * WINDOW)
        # both cameras' frames of one moment carry its stamp, as a robot's drivers stamp them
        stamps = tuple(float(k // 2) for k in range(len(streams)))
        return Route(case, pngs, np.asarray(labels, np.int64), np.asarray(laps, np.int64), streams, stamps)
    else:
        raise ValueError(f"unknown case {case!r}; known: {', '.join(CASES)}")
    return Route(case, pngs, np.asarray(labels, np.int64), np.asarray(laps, np.int64))


def merges(labels: np.ndarray, trace: dict[str, Any], tolerance: int = TOLERANCE) -> dict[str, int]:
    """What a learning run merged wrongly: places whose rows' labels differ by more than `tolerance`,
    and frames consolidated into a row of another label.

    Args:
        labels: (T,) the route's labels. trace: `service_path.slam_replay`'s trace of the run.
    """
    row_label = labels[trace["row_frame"]]
    places = trace["row_place"]
    order = np.argsort(places, kind="stable")
    p, lab = places[order], row_label[order]
    starts = np.r_[0, np.flatnonzero(p[1:] != p[:-1]) + 1]
    spread = np.maximum.reduceat(lab, starts) - np.minimum.reduceat(lab, starts) if p.size else np.zeros(0)
    visit = trace["visit"]
    frames = np.flatnonzero(visit >= 0)
    wrong = np.abs(labels[trace["row_frame"][visit[frames] - 1]] - labels[frames]) > tolerance
    return {"merged_places": int((spread > tolerance).sum()), "wrong_consolidations": int(wrong.sum())}


def _lap2(s: dict[str, Any]) -> dict[str, Any]:
    lap = s["lap"].get(1)
    keys = ("precision", "recall", "recall_at_100p", "revisits_true", "revisits_called")
    return {k: lap.get(k) for k in keys} if lap else {}


def _motions(r: Route) -> list[Motion] | None:
    """Each frame's motion in a case of several streams: the trail `robot`, and the frame's stamp."""
    if r.streams is None:
        return None
    return [TRAIL._replace(stamp=None if r.stamps is None else r.stamps[i]) for i in range(len(r.streams))]


def run_case(frames: Frames, case: str, lo: int, seeds: tuple[int, ...], methods: tuple[str, ...],
             map_conf: dict[str, Any]) -> dict[str, Any]:
    """One case on one window: every method at every seed, scored at the map's revisit threshold."""
    r = route(frames, case, lo)
    feats = frames.features(r.pngs)
    contrast = service_path.contrasts(r.pngs)
    truth = slam.revisit_truth(r.labels, TOLERANCE)
    out: dict[str, Any] = {"frames": len(r.pngs), "revisits_true": int(truth.sum())}
    n1 = int((r.laps == 0).sum())
    for m in methods:
        per_seed = []
        for seed in seeds if m != "openseqslam" else (None,):
            trace: dict[str, Any] = {}
            extra = None
            if m in service_path.SLAM_METHODS:
                found, threshold = service_path.slam_replay(
                    feats, seed=seed, memory=service_path.SLAM_METHODS[m], contrast=contrast, trace=trace,
                    streams=r.streams, motions=_motions(r),
                    **map_conf)
                best, conf = found.best, found.confidence
            elif m == "service":  # the localise mode: lap 1 learned, the rest localised by another robot
                if r.laps.max() < 1:
                    continue
                found = service_path.replay(feats[:n1], feats[n1:], seed=seed, memory="tm",
                                            contrast=contrast, **map_conf)
                best, conf = np.r_[np.full(n1, -1), found.best], np.r_[np.zeros(n1), found.confidence]
                threshold = (map_conf.get("create") or {}).get("revisit_threshold", DEFAULT_REVISIT_THRESHOLD)
                extra = slam.localise_truth(r.labels, r.laps, TOLERANCE)
            else:  # OpenSeqSLAM online: no threshold of its own, read at 100 % precision
                F = grey(r.pngs)
                best, conf = slam.openseqslam_online(seqslam.mean_abs_difference(F, F))
                threshold = float("inf")
            s = slam.score(best, conf, r.labels, threshold, TOLERANCE, r.laps, extra)
            entry = {"seed": seed, "false_revisits": s["false_revisits"], **_lap2(s)}
            if trace:
                entry.update(merges(r.labels, trace))
            per_seed.append(entry)
        if per_seed:
            out[m] = per_seed
    return out


def windows(quick: bool) -> Iterator[tuple[str, int]]:
    """(half, first file) of each window: one of `tune` (quick), else every window of both halves."""
    if quick:
        yield "tune", 100
        return
    for half, (lo, hi) in HALVES.items():
        for start in range(lo, hi - WINDOW + 1, STRIDE):
            yield half, start


def suite(frames: Frames, *, quick: bool, map_conf: dict[str, Any],
          progress: Callable[[str], None] | None = None,
          cases: tuple[str, ...] | None = None) -> dict[str, Any]:
    """The whole suite (module docstring): {"cases": [{half, lo, case, <run_case>}], "summary"};
    `cases`: only these (default: `QUICK_CASES` with `quick`, else `CASES`)."""
    cases = cases or (QUICK_CASES if quick else CASES)
    seeds = QUICK_SEEDS if quick else SEEDS
    methods = ("service-slam",) if quick else ("service-slam", "service-slam-without-tm", "service",
                                              "openseqslam")
    results = []
    for half, lo in windows(quick):
        for case in cases:
            res = {"half": half, "lo": lo, "case": case,
                   **run_case(frames, case, lo, seeds, methods, map_conf)}
            results.append(res)
            if progress:
                progress(json.dumps(res))
    return {"cases": results, "summary": summary(results)}


def summary(results: list[dict[str, Any]]) -> dict[str, Any]:
    """Per case and method over windows and seeds: total and worst false revisits and merges, and lap-2
    precision and recall: mean and worst."""
    out: dict[str, Any] = {}
    for res in results:
        for m, runs in res.items():
            if not isinstance(runs, list):
                continue
            acc = out.setdefault(res["case"], {}).setdefault(m, {
                "runs": 0, "false_revisits": 0, "false_revisits_worst": 0, "merged_places": 0,
                "wrong_consolidations": 0, "precision": [], "recall": [], "recall_at_100p": []})
            for e in runs:
                acc["runs"] += 1
                acc["false_revisits"] += e["false_revisits"]
                acc["false_revisits_worst"] = max(acc["false_revisits_worst"], e["false_revisits"])
                acc["merged_places"] += e.get("merged_places", 0)
                acc["wrong_consolidations"] += e.get("wrong_consolidations", 0)
                for k in ("precision", "recall", "recall_at_100p"):
                    if e.get(k) is not None:
                        acc[k].append(e[k])
    for per_method in out.values():
        for acc in per_method.values():
            for k in ("precision", "recall", "recall_at_100p"):
                vals = acc.pop(k)
                acc[f"{k}_mean"] = float(np.mean(vals)) if vals else None
                acc[f"{k}_worst"] = float(np.min(vals)) if vals else None
    return out


def suite_runs(*, data: Path, quick: bool, backbone: str | None = None, json_path: Path | None = None,
               localiser: dict[str, Any] | None = None, threshold: float | None = None,
               cases: tuple[str, ...] | None = None) -> dict[str, Any]:
    """`cortexloc eval slam --suite`: the suite on `data` at the service's defaults (the maps'
    `localiser` options over them, for an ablation; `threshold`: the maps made with that
    `revisit_threshold`, to choose the default, docs/results.md §10.14), each case printed as a JSON line
    as it ends, then the summary; written to `json_path` too."""
    from service.evaluation.slam import encoder_setup

    enc, cache, map_conf = encoder_setup(backbone, localiser)
    if threshold is not None:
        map_conf["create"] = {"revisit_threshold": threshold}
    result = suite(Frames(data, enc, cache), quick=quick, map_conf=map_conf,
                   progress=lambda line: print(line, flush=True), cases=cases)
    for case, per_method in result["summary"].items():
        for m, acc in per_method.items():
            shown = {k: round(v, 3) if isinstance(v, float) else v for k, v in acc.items()}
            print(case, m, shown, flush=True)
    if json_path:
        json_path.write_text(json.dumps(result) + "\n")
    return result
