"""Experiments of docs/results.md §10.11: a stream's short-term memory (docs/design/science.md §11.6) on
the stress routes, one learning stream through the service's step (`models.pipeline.observe` on a
served map's model, as `service_path.slam_replay` drives it), one JSON line per route, window and seed.

    cortexloc eval short-term \
        slow3,slow10,flat,shortloop,seasons,noise,park,repeat,seasons30,seasons60 1,7,42 0,200,400,600 '{}'

Arguments: routes, map seeds, the windows' first files (`tune`: 0-694, `test`: 894-1588), and the maps'
localiser options as JSON (`'{"short_term": 0}'`: the memory off, the consolidation rules of science
§11.6 kept: the code before issue 35 is d8683e8, which the tables' "before" ran). Routes, from the window
of files [lo, lo + 200) of ../shared/data/nordland_tiny_64x32 (labels = file index): `slow3` and `slow10`
(each frame 3 times, or the first 60 frames 10 times, σ 4 pixel noise), `park` (60 frames, 200 copies of
the next with σ 2 noise, 59 more), `flat` (blurred, contrast cut to 35 %), `repeat` (100 frames, then 40
of them shifted and noisy), `shortloop` (40 frames three times, exact), `seasons` and `noise` (the
window, then in winter or with σ 8 noise), `seasons30` and `seasons60` (the window's first 30 or 60
files, then in winter). Truth: `slam.revisit_truth` (tolerance 1). Each line: `false` (revisits called
that are no true revisit named right), `hit` of `true` revisits, `merged_places` (places whose rows'
labels differ by more than 1, visits counted with the row they went into), `wrong_visits` (frames
consolidated into a row of another label), `rows`, and `lags` (rows between the stream's last row and
each false answer). The route builder differs from `cortexloc eval slam --suite`
(service/evaluation/stress.py) in its noise seeds and the exact short loop; the suite is the maintained
form.
"""

from __future__ import annotations

import functools
import hashlib
import json
import time
from pathlib import Path

import cv2
import numpy as np

from models.evaluation import datasets, sequences, slam
from models.frontend.embedding import Embedder
from models.localisation.localiser import reaches
from models.pipeline import Stream, observe
from service.evaluation import service_path, stress
from service.frontend import resolve_backbone
from service.settings import Settings

DATA = datasets.nordland_dir()
CACHE = Path.home() / ".cache/cortexloc/features"


@functools.cache
def _setup() -> tuple[Settings, str, Embedder, list[str]]:
    """(settings, backbone, embedder, the route's file names), made when an experiment runs, not at
    import (importing the module reads no data: the benchmarks' import smoke test runs without it)."""
    settings = Settings.from_env()
    backbone = resolve_backbone(settings).backbone
    return (settings, backbone, Embedder({"backbone": backbone, "resize": "squash"}),
            sequences.paired_names(DATA / "summer", DATA / "winter"))


def img(season: str, i: int) -> np.ndarray:
    return cv2.imread(str(DATA / season / _setup()[3][i]), cv2.IMREAD_COLOR)


def variant(season: str, i: int, kind: str, seed: int) -> bytes:
    """`stress.variant` of file i (`noise4` here is its `noise:4`)."""
    return stress.variant(img(season, i), kind.replace("noise", "noise:"), seed)


def feats_of(pngs: list[bytes]) -> np.ndarray:
    enc = _setup()[2]
    digest = b"".join(hashlib.sha256(p).digest() for p in pngs) + enc.identity.encode()
    key = hashlib.sha256(digest).hexdigest()
    path = CACHE / f"stress-{key}.npy"
    if path.exists():
        return np.load(path)
    f = np.concatenate([enc.embed(pngs[i:i + 64]).features for i in range(0, len(pngs), 64)])
    path.parent.mkdir(parents=True, exist_ok=True)
    np.save(path, f.astype(np.float32))
    return f


def build(name: str, lo: int) -> tuple[list[bytes], np.ndarray, np.ndarray]:
    """(PNGs, labels, laps) of a route starting at file `lo`."""
    P: list[bytes] = []
    L: list[int] = []
    K: list[int] = []

    def add(season: str, idx, kind: str | None = None, lap: int = 0, seed: int = 0) -> None:
        for j, i in enumerate(idx):
            P.append(variant(season, i, kind, seed + j) if kind else stress.png(img(season, i)))
            L.append(i)
            K.append(lap)

    if name in ("slow3", "slow10"):
        copies, places = (3, 200) if name == "slow3" else (10, 60)
        for i in range(lo, lo + places):
            for c in range(copies):
                add("summer", [i], "noise4", 0, 1000 * c + i)
    elif name == "park":
        add("summer", range(lo, lo + 60))
        for c in range(200):
            add("summer", [lo + 60], "noise2", 0, 5000 + c)
        add("summer", range(lo + 61, lo + 120))
    elif name == "flat":
        add("summer", range(lo, lo + 200), "flat", 0, 7)
    elif name == "repeat":
        add("summer", range(lo, lo + 100))
        add("summer", range(lo + 20, lo + 60), "shift", 0, 99)
    elif name == "shortloop":
        for k in range(3):
            add("summer", range(lo, lo + 40), None, k)
    elif name in ("seasons30", "seasons60", "seasons"):
        n = {"seasons30": 30, "seasons60": 60, "seasons": 200}[name]
        add("summer", range(lo, lo + n), None, 0)
        add("winter", range(lo, lo + n), None, 1)
    elif name == "noise":
        add("summer", range(lo, lo + 200), None, 0)
        add("summer", range(lo, lo + 200), "noise8", 1, 3)
    else:
        raise SystemExit(f"unknown route {name}")
    return P, np.array(L), np.array(K)


def run(name: str, lo: int, seed: int, localiser: dict | None) -> dict:
    pngs, labels, _ = build(name, lo)
    feats = feats_of(pngs)
    contrast = service_path.contrasts(pngs)
    settings, backbone = _setup()[:2]
    model, hasher, config = service_path._model(feats.shape[1], max_observations=len(feats),
                                                backbone=backbone, preset=settings.default_preset, seed=seed,
                                                memory="tm", localiser=localiser, create=None)
    robot, codes, frame_of = Stream(), {}, {}
    T = len(feats)
    best, conf = np.full(T, -1), np.zeros(T)
    visit_of: dict[int, int] = {}
    place_rows: dict[int, list[int]] = {}
    for i, y in enumerate(hasher.project(feats)):
        seq = len(codes) + 1
        st = observe(model, robot, y, learn=True, stream="robot", top_k=0, seq=seq, code_of=codes.__getitem__,
                     threshold=config.revisit_threshold, contrast=float(contrast[i]))
        if st.visit is None:
            codes[seq], frame_of[seq] = st.code, i
            pl = st.joined if st.joined >= 0 else seq
        else:
            visit_of[i] = st.visit
            pl = int(model.place_map.graph.place[st.visit])
        place_rows.setdefault(int(pl), []).append(int(labels[i]))
        if st.place is not None:
            best[i] = frame_of[st.place.seq]
            conf[i] = st.place.confidence if st.place.informative else 0
    truth = slam.revisit_truth(labels, 1)
    called = (best >= 0) & reaches(conf, config.revisit_threshold)
    right = (best >= 0) & (np.abs(labels[np.maximum(best, 0)] - labels) <= 1)
    false = np.flatnonzero(called & ~(truth & right))
    row_of = {f: q for q, f in frame_of.items()}
    lags = [sum(1 for f in frame_of.values() if f <= i) - row_of[int(best[i])] for i in false]
    return {"lags": lags, "route": name, "lo": lo, "seed": seed, "frames": T, "rows": len(codes),
            "true": int(truth.sum()), "called": int(called.sum()), "false": int(false.size),
            "hit": int((called & truth & right).sum()),
            "merged_places": sum(1 for v in place_rows.values() if max(v) - min(v) > 1),
            "wrong_visits": sum(1 for i, r in visit_of.items() if abs(labels[frame_of[r]] - labels[i]) > 1)}


def main(*, routes: list[str], seeds: list[int], starts: list[int], localiser: dict | None) -> None:
    """`cortexloc eval short-term`: one JSON line per route, window start and seed."""
    for r in routes:
        for lo in starts:
            for s in seeds:
                t = time.time()
                o = run(r, lo, s, localiser)
                o["s"] = round(time.time() - t, 1)
                print(json.dumps(o), flush=True)
