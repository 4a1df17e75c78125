"""Many passes of one route through the service's path: place identity, consolidation and the map's
growth (docs/results.md §11, docs/design/science.md §11.8, §11.9).

    cortexloc eval passes --data ../shared/data/nordland_tiny_64x32 --half test --frames 200 \
        --passes 1,2,3,5,10 --json out.json

A route is `--frames` consecutive frames of a Nordland half (`--start` in it). A pass is the route
driven once as its own learning stream (`pass-k`, learn=true, every frame through
`models.pipeline.observe` with the map's revisit threshold and the frame's contrast as the service
measures it at decode, so flat frames are judged as the map writer judges them), in:
- `same` conditions: summer, each pass after the first with fresh pixel noise (σ 8, seed = the pass);
- `alternating` conditions: summer, winter, summer (noise), winter, ...
After N passes another pass is localised (learn=false): the winter pass for `same`, a summer pass with
noise no learned pass had for `alternating`. Reported per N: revisits called and right in that pass
(precision, recall = right revisits / frames), rows added by each pass, rows, places, visits and index
bytes; beside it the same map options with consolidation off (`consolidate: 1`, a row per frame) and
a place cap no pass reaches.

`--stream`: one learning stream drives the route three times (lap 1, 2, 3): revisits of each lap.
`--month`: three robots (streams) each drive the route `--month-passes` times, alternating seasons
between days, noise per drive; rows per day (growth), and a held-out localised pass after each day.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from models.evaluation.passes import Pass, localise_score, summary_row
from models.pipeline import MapModel, Stream, observe
from service.evaluation import service_path
from service.evaluation.slam import HALVES, Frames
from service.settings import Settings

__all__ = ["passes_runs"]

#: The ablation's options: a row per frame (no consolidation) and no cap a route reaches.
NO_CONSOLIDATION = {"consolidate": 1.0, "appearances": 1024}


class Shown(NamedTuple):
    """The frames of one pass: `feats` (T, D) their features, `contrast` (T,) each one's contrast as the
    service measures it at decode (`images.contrast`, docs/design/science.md §11.7)."""

    feats: np.ndarray
    contrast: np.ndarray


class Driver:
    """One map's pure pipeline (`service_path._model`, forgetting at the served cap as the writer does:
    `service_path.forget`), with the codes of its rows and their labels."""

    def __init__(self, dim: int, *, memory: str, localiser: dict[str, Any], map_conf: dict[str, Any]) -> None:
        self.model: MapModel
        self.model, self.hasher, config = service_path._model(
            dim, memory=memory, localiser=localiser, create=None, **map_conf)
        self.threshold = float(config.revisit_threshold)
        self.codes: dict[int, np.ndarray] = {}
        self.labels: dict[int, int] = {}
        self.seq = 0

    def drive(self, shown: Shown, labels: np.ndarray, stream: str, *, learn: bool,
              st: Stream | None = None) -> Pass:
        """One pass of `shown` frames; its answers (row label, confidence) and what it added."""
        feats, contrast = shown
        st = st or Stream()
        out = Pass(np.full(len(labels), -1, np.int64), np.zeros(len(labels)), labels, 0, 0)
        for i, y in enumerate(self.hasher.project(feats)):
            seq = self.seq + 1 if learn else None
            if learn:
                service_path.forget(self.model)
            step = observe(self.model, st, y, learn=learn, stream=stream, top_k=0, seq=seq,
                           code_of=self.codes.__getitem__, threshold=self.threshold,
                           contrast=float(contrast[i]))
            if learn and step.visit is None:
                self.seq += 1
                self.codes[self.seq], self.labels[self.seq] = step.code, int(labels[i])
                out.rows += 1
            elif learn:
                out.visits += 1
            if step.place is not None:
                out.best[i] = self.labels[step.place.seq]
                out.confidence[i] = step.place.confidence
        return out

    def size(self) -> dict[str, int]:
        place_map = self.model.place_map
        return {"rows_held": place_map.held, "rows_made": self.seq, "places": place_map.places(),
                "index_bytes": self.model.index.nbytes()}


def _season(frames: Frames, idx: np.ndarray, season: str) -> Shown:
    """A season's frames `idx` as they are: features and contrasts."""
    return Shown(frames.feats[season][idx],
                 service_path.contrasts([frames.images[season][int(i)] for i in idx]))


def _noisy(frames: Frames, idx: np.ndarray, seed: int) -> Shown:
    """Summer frames `idx` with pixel noise of σ 8 (`seed`): features and contrasts."""
    feats, pngs = frames.noisy(idx, 8.0, seed)
    return Shown(feats, service_path.contrasts(pngs))


def _conditions(frames: Frames, idx: np.ndarray, kind: str, k: int) -> Shown:
    """Pass k of a route in `same` or `alternating` conditions (module docstring)."""
    if kind == "alternating" and k % 2 == 1:
        return _season(frames, idx, "winter")
    if k == 0:
        return _season(frames, idx, "summer")
    return _noisy(frames, idx, k)


def _passes(frames: Frames, idx: np.ndarray, labels: np.ndarray, counts: list[int], kind: str,
            memory: str, localiser: dict[str, Any], map_conf: dict[str, Any], tolerance: int) -> list[dict]:
    query = _season(frames, idx, "winter") if kind == "same" else _noisy(frames, idx, 999)
    dim = int(query.feats.shape[1])
    out = []
    for n in counts:
        d = Driver(dim, memory=memory, localiser=localiser, map_conf=map_conf)
        added = [d.drive(_conditions(frames, idx, kind, k), labels, f"pass-{k}", learn=True).rows
                 for k in range(n)]
        q = d.drive(query, labels, "query", learn=False)
        out.append({"passes": n, "rows_added": added, **d.size(),
                    **localise_score(q, d.threshold, tolerance)})
    return out


def _stream(frames: Frames, idx: np.ndarray, labels: np.ndarray, memory: str, localiser: dict[str, Any],
            map_conf: dict[str, Any], tolerance: int, laps: int = 3) -> list[dict]:
    """One learning stream drives the route `laps` times (same conditions): each lap's revisits."""
    d = Driver(int(frames.feats["summer"].shape[1]), memory=memory, localiser=localiser,
               map_conf=map_conf)
    st = Stream()
    out = []
    for k in range(laps):
        p = d.drive(_conditions(frames, idx, "same", k), labels, "robot", learn=True, st=st)
        out.append({"lap": k + 1, **localise_score(p, d.threshold, tolerance), **d.size()})
    return out


def _month(frames: Frames, idx: np.ndarray, labels: np.ndarray, days: int, memory: str,
           localiser: dict[str, Any], map_conf: dict[str, Any], tolerance: int) -> list[dict]:
    """Three robots drive the route once a day each, the season alternating by day; after each day a
    held-out pass (noisy summer on summer days, winter's frames with noise on winter days is not
    available, so the other season's clean frames) is localised."""
    d = Driver(int(frames.feats["summer"].shape[1]), memory=memory,
               localiser=localiser, map_conf=map_conf)
    robots = {f"robot-{r}": Stream() for r in range(3)}
    out = []
    for day in range(days):
        rows = 0
        for r, (name, st) in enumerate(robots.items()):
            k = 1 + day * 3 + r  # a fresh noise seed per drive
            shown = _season(frames, idx, "winter") if day % 2 else _noisy(frames, idx, k)
            st.break_sequence()
            rows += d.drive(shown, labels, name, learn=True, st=st).rows
        q = d.drive(_noisy(frames, idx, 999) if day % 2 else _season(frames, idx, "winter"), labels,
                    "query", learn=False)
        out.append({"day": day + 1, "rows_added": rows, **d.size(),
                    **localise_score(q, d.threshold, tolerance)})
    return out


def passes_runs(*, data: Path, half: str = "test", start: int = 0, frames_n: int = 200,
                passes: str = "1,2,3,5,10", kinds: str = "same,alternating", memory: str = "tm",
                month_days: int = 0, stream: bool = True, tolerance: int = 2, backbone: str | None = None,
                seed: int = 1, json_path: Path | None = None) -> dict[str, Any]:
    """The experiment (module docstring), printed and returned."""
    from models.frontend.embedding import Embedder
    from service.frontend import resolve_backbone

    if half not in HALVES:
        raise ValueError(f"--half must be one of {', '.join(sorted(HALVES))}")
    settings = Settings.from_env()
    backbone = backbone or resolve_backbone(settings).backbone
    enc = Embedder({"backbone": backbone, "resize": "squash"})
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    frames = Frames(data, half, enc, cache)
    idx = np.arange(start, start + frames_n)
    if idx[-1] >= len(frames.paths["summer"]):
        raise ValueError(f"--start + --frames must be at most {len(frames.paths['summer'])}")
    labels = idx + frames.lo
    map_conf = {"backbone": backbone, "preset": settings.default_preset, "seed": seed}
    counts = [int(x) for x in passes.split(",") if x]
    result: dict[str, Any] = {"config": {"half": half, "start": start, "frames": frames_n, "memory": memory,
                                         "backbone": backbone, "tolerance": tolerance}}
    for label, loc in (("consolidated", {}), ("without-consolidation", NO_CONSOLIDATION)):
        for kind in kinds.split(","):
            rows = _passes(frames, idx, labels, counts, kind, memory, loc, map_conf, tolerance)
            result[f"{kind} {label}"] = rows
            for r in rows:
                print(kind, label, summary_row(r), flush=True)
        if stream:
            result[f"stream {label}"] = laps = _stream(frames, idx, labels, memory, loc, map_conf, tolerance)
            for r in laps:
                print("stream", label, summary_row(r), flush=True)
        if month_days:
            result[f"month {label}"] = days = _month(frames, idx, labels, month_days, memory, loc, map_conf,
                                                     tolerance)
            for r in days:
                print("month", label, summary_row(r), flush=True)
        if json_path:
            json_path.write_text(json.dumps(result) + "\n")
    return result
