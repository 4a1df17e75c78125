"""Loop closure while mapping through the service's path: routes driven as ONE learning stream
(docs/results.md §10, docs/design/science.md §11.6).

    cortexloc eval slam --data ../shared/data/nordland_tiny_64x32 --half tune \
        --routes seasons,noise,short-lap,stop,excursion --json out.json

Routes, from the Nordland half (`tune`: files 1-894, `test`: 895-1788), labels = file index:
- `seasons`: the summer traverse then the winter one (lap 1, lap 2);
- `noise`: the summer traverse twice, the second with the pixel noise of `revisit_eval` (σ 8);
- `short-lap`: 40 summer frames driven three times;
- `stop`: 200 summer frames with a stop of 40 near-identical frames (σ 2 noise) in the middle;
- `excursion`: 150 summer frames out, then back the same way (driven backwards).
`--grid DIR` instead: the grid world's multi-loop walk (CBA 2020, both published SDR files) through the
same localiser as one learning stream (`models.evaluation.online.loop_closure`: the input SDRs, and the
Temporal Memory's winner cells learned online), labels = cells, tolerance 0.

Methods: `service-slam` and `service-slam-without-tm` (`service_path.slam_replay`: every frame posted
with learn=true on one stream), the localise mode on the same lap-2 frames (`service`: lap 1 learned,
lap 2 localised, `service_path.replay`), and `openseqslam` as an online loop-closure detector
(`models.evaluation.slam.openseqslam_online`). Scored per route by `models.evaluation.slam.score` at
the map's threshold and the `--thresholds`; `operating_point`: the lowest threshold with precision
>= 0.99 over every call of the route; `calibrated`: the per-map calibration tried (the `--rate`
quantile of the stream's own lap-1 confidences).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np

from models.evaluation import seqslam, sequences, slam
from models.frontend.embedding import Embedder
from service.evaluation import service_path
from service.evaluation.revisit import noisy_png
from service.maps.config import DEFAULT_REVISIT_THRESHOLD
from service.settings import Settings

HALVES = {"tune": (0, 894), "test": (894, 1788)}
ROUTES = ("seasons", "noise", "short-lap", "stop", "excursion")


class Frames:
    """One Nordland half: features and OpenSeqSLAM frames of summer, winter and noisy summer."""

    def __init__(self, data: Path, half: str, enc: Embedder, cache: Path) -> None:
        lo, hi = HALVES[half]
        names = sequences.paired_names(data / "summer", data / "winter")[lo:hi]
        self.lo, self.enc, self.cache = lo, enc, cache
        self.paths = {s: [data / s / n for n in names] for s in ("summer", "winter")}
        self.feats = {s: sequences.cached_features(enc, p, cache) for s, p in self.paths.items()}
        self.images = {s: [p.read_bytes() for p in ps] for s, ps in self.paths.items()}

    def noisy(self, idx: np.ndarray, sigma: float, seed: int) -> tuple[np.ndarray, list[bytes]]:
        """Features and PNGs of summer frames `idx` (half-relative) plus pixel noise, cached by content."""
        what = f"{self.enc.identity}|{self.lo}|{sigma}|{seed}|{idx.tolist()}"
        key = hashlib.sha256(what.encode()).hexdigest()
        pngs = [noisy_png(self.paths["summer"][i], sigma, seed + self.lo + int(i)) for i in idx]
        path = self.cache / f"features-noisy-{key}.npy"
        if path.exists():
            return np.load(path), pngs
        feats = np.concatenate([self.enc.embed(pngs[i:i + 32]).features for i in range(0, len(pngs), 32)])
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, feats.astype(np.float32))
        return feats, pngs


def route(frames: Frames, name: str) -> dict[str, Any]:
    """{"feats" (T, D), "images" T PNGs, "contrast" (T,) (`images.contrast`, what the service measures
    at decode), "labels" (T,), "laps" (T,)} of one route."""
    n = len(frames.paths["summer"])
    s_f, s_i = frames.feats["summer"], frames.images["summer"]
    idx = np.arange(n)
    if name == "seasons":
        parts = [(s_f, s_i, idx), (frames.feats["winter"], frames.images["winter"], idx)]
    elif name == "noise":
        q_f, q_i = frames.noisy(idx, 8.0, 0)
        parts = [(s_f, s_i, idx), (q_f, q_i, idx)]
    elif name == "short-lap":
        lap = np.arange(100, 140)
        parts = [(s_f[lap], [s_i[i] for i in lap], lap)] * 3
    elif name == "stop":
        before, after, at = np.arange(0, 101), np.arange(101, 200), np.full(40, 100)
        q_f, q_i = frames.noisy(at, 2.0, 1000)
        parts = [(s_f[before], [s_i[i] for i in before], before), (q_f, q_i, at),
                 (s_f[after], [s_i[i] for i in after], after)]
        parts = [(np.concatenate([p[0] for p in parts]), [b for p in parts for b in p[1]],
                  np.concatenate([p[2] for p in parts]))]
    elif name == "excursion":
        out_, back = np.arange(0, 150), np.arange(149, -1, -1)
        parts = [(s_f[out_], [s_i[i] for i in out_], out_), (s_f[back], [s_i[i] for i in back], back)]
    else:
        raise ValueError(f"unknown route {name!r}; known: {', '.join(ROUTES)}")
    pngs = [b for p in parts for b in p[1]]
    return {"feats": np.concatenate([p[0] for p in parts]), "images": pngs,
            "contrast": service_path.contrasts(pngs),
            "labels": np.concatenate([p[2] for p in parts]) + frames.lo,
            "laps": np.concatenate([np.full(len(p[2]), k) for k, p in enumerate(parts)])}


def grey(images: list[bytes]) -> np.ndarray:
    """OpenSeqSLAM's patch-normalised grey frames of PNG bytes (`seqslam.load_frames` on bytes)."""
    out = []
    for b in images:
        img = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_GRAYSCALE)
        if (img.shape[1], img.shape[0]) != seqslam.FRAME_SIZE:
            img = cv2.resize(img, seqslam.FRAME_SIZE, interpolation=cv2.INTER_AREA)
        out.append(img)
    return seqslam.patch_normalise(np.stack(out))


def evaluate(r: dict[str, Any], methods: list[str], map_conf: dict[str, Any], thresholds: list[float],
             tolerance: int, rate: float) -> dict[str, Any]:
    """Every method on one route: its scores at the map's threshold and at each of `thresholds`."""
    out: dict[str, Any] = {}
    labels, laps = r["labels"], r["laps"]
    for m in methods:
        if m in service_path.SLAM_METHODS:
            found, default = service_path.slam_replay(r["feats"], memory=service_path.SLAM_METHODS[m],
                                                      contrast=r["contrast"], **map_conf)
            best, conf = found.best, found.confidence
        elif m in service_path.METHODS:  # the localise mode: lap 1 learned, the rest localised
            if laps.max() < 1:
                continue
            n1 = int((laps == 0).sum())
            found = service_path.replay(r["feats"][:n1], r["feats"][n1:], memory=service_path.METHODS[m],
                                        contrast=r["contrast"], **map_conf)
            best = np.r_[np.full(n1, -1), found.best]
            conf = np.r_[np.zeros(n1), found.confidence]
            default = DEFAULT_REVISIT_THRESHOLD
        elif m == "openseqslam":
            F = grey(r["images"])
            best, conf = slam.openseqslam_online(seqslam.mean_abs_difference(F, F))
            default = None
        else:
            raise ValueError(f"unknown method {m!r}")
        entry: dict[str, Any] = {"default_threshold": default}
        default = None if default is None else float(default)
        # A localising stream is another robot: at a stored place, a right answer is no false revisit.
        extra = slam.localise_truth(labels, laps, tolerance) if m in service_path.METHODS else None
        truth = slam.revisit_truth(labels, tolerance) | (False if extra is None else extra)
        right = truth & (best >= 0) & (np.abs(labels[np.maximum(best, 0)] - labels) <= tolerance)
        answered = best >= 0
        entry["operating_point"] = service_path.operating_point(conf[answered], right[answered], 0.99)
        at = [t for t in ([default] if default is not None else []) + thresholds]
        if entry["operating_point"]:
            at.append(entry["operating_point"]["threshold"])
        if m in service_path.SLAM_METHODS:
            lap1 = conf[(laps == 0) & answered]
            entry["calibrated"] = float(np.quantile(lap1, 1.0 - rate)) if lap1.size else None
            if entry["calibrated"] is not None:
                at.append(entry["calibrated"])
        entry["at"] = {f"{t:.4f}": slam.score(best, conf, labels, t, tolerance, laps, extra) for t in at}
        entry["answers"] = {"best": best.tolist(), "confidence": np.round(conf, 6).tolist()}
        out[m] = entry
    return out


def grid(folder: Path, thresholds: list[float], seeds: int = 1) -> dict[str, Any]:
    """The grid world's loops as one learning stream, with and without the Temporal Memory, and
    OpenSeqSLAM's online detector on 1 − Dice of the SDRs; the memory over TM seeds 1..`seeds` (keys
    "... service-slam" for seed 1, "... service-slam seed N" for the others; without it the input SDRs
    are the codes, so one run)."""
    from models.evaluation import gridworld, online, runner
    from models.sdr import dice_matrix

    out: dict[str, Any] = {}
    for name in ("seq_multi_loop_noise0_al1.txt", "seq_multi_loop_noise05_al5.txt"):
        data = gridworld.load_published(folder / name, folder / "seq_multi_loop_noNoise_gt.txt")
        ids = {cell: i for i, cell in enumerate(sorted({tuple(p) for p in data.places}))}
        labels = np.array([ids[tuple(p)] for p in data.places])
        methods = {"service-slam-without-tm": dice_matrix(data.sdrs)}
        for seed in range(1, seeds + 1):
            winners, _ = runner.run_htm(data, "cortexloc-grid", seed)
            methods["service-slam" + (f" seed {seed}" if seed > 1 else "")] = dice_matrix(winners)
        for m, S in methods.items():
            found = online.loop_closure(S, data.sdrs)
            out[f"{name} {m}"] = {f"{t:.4f}": slam.score(found.best, found.confidence, labels, t, 0)
                                  for t in thresholds}
        best, conf = slam.openseqslam_online(1.0 - dice_matrix(data.sdrs))
        out[f"{name} openseqslam"] = {f"{t:.4f}": slam.score(best, conf, labels, t, 0) for t in thresholds}
    return out


def encoder_setup(backbone: str | None, localiser: dict[str, Any] | None
                  ) -> tuple[Embedder, Path, dict[str, Any]]:
    """(the encoder of `backbone`, default the service's; the feature cache; the maps' keywords of
    `service_path.slam_replay` and `replay` but the seed: the service's preset, `localiser`)."""
    from service.frontend import resolve_backbone  # the service's own resolution of its default

    settings = Settings.from_env()
    backbone = backbone or resolve_backbone(settings).backbone
    enc = Embedder({"backbone": backbone, "resize": "squash"})
    cache = Path(os.environ.get("CORTEXLOC_CACHE_DIR", Path.home() / ".cache" / "cortexloc")) / "features"
    return enc, cache, {"encoder_id": enc.identity, "backbone": backbone, "preset": settings.default_preset,
                        "localiser": localiser}


def slam_runs(*, data: Path | None = None, half: str = "tune", routes: str = ",".join(ROUTES),
              methods: str = "service-slam,service-slam-without-tm,service,openseqslam",
              thresholds: list[float] | None = None, tolerance: int = 1, rate: float = 0.001,
              backbone: str | None = None, seed: int = 1, json_path: Path | None = None,
              grid_dir: Path | None = None, adapt_tau: int = 0, seeds: int = 1,
              localiser: dict[str, Any] | None = None) -> None:
    """The experiment (module docstring), printed; `grid_dir`: the grid world's folder instead of `data`;
    `adapt_tau`: the maps made with that stream adaptation (docs/results.md §10.6); `seeds`: the grid
    world's memory over that many seeds; `localiser`: the maps' localiser options over the defaults
    (an ablation: `{"condition_frames": 0}` is the index without a stream's condition, §10.6).

    Raises:
        ValueError: neither `data` nor `grid_dir`, or an unknown `half`.
    """
    if half not in HALVES:
        raise ValueError(f"--half must be one of {', '.join(sorted(HALVES))}")
    args = SimpleNamespace(data=data, half=half, routes=routes, methods=methods, thresholds=thresholds or [],
                           tolerance=tolerance, rate=rate, backbone=backbone, seed=seed, json=json_path,
                           grid=grid_dir)
    if args.grid is not None:
        found = grid(args.grid, [DEFAULT_REVISIT_THRESHOLD, *args.thresholds], seeds)
        for key, by_t in found.items():
            for t, s in by_t.items():
                d = s["lap"][0]
                print(key, "at", t, {k: round(v, 3) if isinstance(v, float) else v for k, v in d.items()})
        if args.json:
            args.json.write_text(json.dumps(found) + "\n")
        return
    if args.data is None:
        raise ValueError("--data (or --grid) is required")
    enc, cache, map_conf = encoder_setup(args.backbone, localiser)
    frames = Frames(args.data, args.half, enc, cache)
    map_conf |= {"seed": args.seed, "create": {"slsbh": {"adapt_tau": adapt_tau}} if adapt_tau else None}
    result: dict[str, Any] = {"config": {**{k: str(v) for k, v in vars(args).items()},
                                         "backbone": map_conf["backbone"]}, "routes": {}}
    for name in args.routes.split(","):
        r = route(frames, name)
        result["routes"][name] = evaluate(r, args.methods.split(","), map_conf, args.thresholds,
                                          args.tolerance, args.rate)
        for m, e in result["routes"][name].items():
            summary = {t: {k: v for k, v in s["lap"].items()} for t, s in e["at"].items()}
            print(name, m, "op", e["operating_point"], "cal", e.get("calibrated"), flush=True)
            for t, s in summary.items():
                short = {lap: {k: round(v, 3) if isinstance(v, float) else v for k, v in d.items()}
                         for lap, d in s.items()}
                print("   at", t, short, flush=True)
        if args.json:
            args.json.write_text(json.dumps(result) + "\n")

