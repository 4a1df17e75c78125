"""Experiment of docs/results.md §10.24: a robot that parks, on new ground beside a map of other ground and
on ground the map knows, with poses and without, with the standing-view rule (docs/design/science.md
§11.2 step 2) and without it.

    cortexloc eval parked 42,1,7 > parked.jsonl
    cortexloc eval parked sum < parked.jsonl    # the totals over every window and seed

Per window (`stress.windows`: every 200-file window of both halves slid by 100, from
../shared/data/nordland_tiny_64x32, labels = file index) and map seed, the robot learns one drive: files
lo..lo+59, then file lo+60 posted PARKED times with σ 2 pixel noise (a parked robot, 5x the short-term
memory), then files lo+61..lo+119. Posed, a file is 10 m on from the last and a frame a second; parked,
its pose stays within a few cm. The map it learns into holds, first, another drive (stream `map`, posed
far away, learn=true):
- `new`: the other half's files, every one (new ground: no frame of the robot is a true revisit; a
  revisit is false unless it names a row of the robot's own drive within the tolerance of one file);
- `known`: the window's own files lo..lo+119, clean, so the robot's drive (with σ 4 noise off the stop) is
  a revisit; a revisit is right when it names a row of that file within one file.

Modes: `poses` (the service's rule), `poses_off` (the same with the rule off, `stand_metres` 0: every
frame is evidence, as before the rule) and `no_poses` (the rule cannot apply: every frame is a move).
Per mode: revisits called before the stop, while parked and after it, and how many were wrong. Through
the service's per-frame step (`models.pipeline.observe`), at the map's defaults. Deterministic.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from benchmarks.experiments import per_window
from models.localisation.motion import NO_MOTION, Motion
from models.pipeline import Stream, observe
from service.evaluation import service_path, stress

#: Frames the robot stands for (the short-term memory is 20 moves).
PARKED = 100
#: Files driven before the stop and after it.
BEFORE, AFTER = 60, 59
MODES = ("poses", "poses_off", "no_poses")
GROUNDS = ("new", "known")
PHASES = ("before", "parked", "after")


def drive(frames: stress.Frames, lo: int) -> tuple[list[bytes], list[int], list[int]]:
    """The robot's PNGs, their files and their phase (0 before the stop, 1 parked, 2 after)."""
    pngs, files, phase = [], [], []
    for i in range(lo, lo + BEFORE):
        pngs.append(stress.variant(frames.image("summer", i), "noise:4", 300 + i))
        files.append(i)
        phase.append(0)
    stop = lo + BEFORE
    for j in range(PARKED):
        pngs.append(stress.variant(frames.image("summer", stop), "noise:2", 5000 + j))
        files.append(stop)
        phase.append(1)
    for i in range(stop + 1, stop + 1 + AFTER):
        pngs.append(stress.variant(frames.image("summer", i), "noise:4", 300 + i))
        files.append(i)
        phase.append(2)
    return pngs, files, phase


def poses(files: list[int], phase: list[int], offset: float) -> list[Motion]:
    """A file 10 m on, a frame a second; parked, a few cm of pose noise."""
    return [Motion((offset + 10.0 * f + (0.02 * np.sin(k) if p == 1 else 0.0), 0.0), float(k))
            for k, (f, p) in enumerate(zip(files, phase, strict=True))]


def run(frames: stress.Frames, half: str, lo: int, seed: int, map_conf: dict[str, Any]) -> dict[str, Any]:
    robot_pngs, files, phase = drive(frames, lo)
    robot = frames.features(robot_pngs)
    contrast = service_path.contrasts(robot_pngs)
    other_lo, other_hi = next(v for k, v in stress.HALVES.items() if k != half)
    grounds = {"new": list(range(other_lo, other_hi)), "known": list(range(lo, lo + BEFORE + 1 + AFTER))}
    out: dict[str, Any] = {"half": half, "lo": lo, "seed": seed}
    for ground, stored in grounds.items():
        map_pngs = [stress.png(frames.image("summer", i)) for i in stored]
        feats, cons = frames.features(map_pngs), service_path.contrasts(map_pngs)
        out[ground] = {}
        for mode in MODES:
            model, hasher, config = service_path._model(
                int(feats.shape[1]), max_observations=4000, seed=seed, memory="tm", create=None,
                localiser={"stand_metres": 0.0} if mode == "poses_off" else None,
                **{k: v for k, v in map_conf.items() if k not in ("encoder_id", "localiser")})
            thr = config.revisit_threshold
            codes: dict[int, np.ndarray] = {}
            file_of: dict[int, int] = {}

            def learn(stream: str, ys: np.ndarray, cs: np.ndarray, fs: list[int], ms: list[Motion],
                      model=model, codes=codes, file_of=file_of, thr=thr) -> list:
                st, places = Stream(), []
                for y, c, f, m in zip(ys, cs, fs, ms, strict=True):
                    seq = len(codes) + 1
                    step = observe(model, st, y, learn=True, stream=stream, top_k=0, seq=seq,
                                   code_of=codes.__getitem__, threshold=thr, contrast=float(c), motion=m)
                    if step.visit is None:
                        codes[seq], file_of[seq] = step.code, f
                    places.append(step.place)
                return places

            posed = mode != "no_poses"
            learn("map", hasher.project(feats), cons, stored,
                  poses(stored, [0] * len(stored), 1e6) if posed else [NO_MOTION] * len(stored))
            places = learn("robot", hasher.project(robot), contrast, files,
                           poses(files, phase, 0.0) if posed else [NO_MOTION] * len(files))
            counts = {p: {"called": 0, "wrong": 0} for p in PHASES}
            for place, f, p in zip(places, files, phase, strict=True):
                if place is None or not place.is_revisit(thr):
                    continue
                c = counts[PHASES[p]]
                c["called"] += 1
                c["wrong"] += int(abs(file_of[place.seq] - f) > stress.TOLERANCE)
            out[ground][mode] = counts
    return out


def main(*, seeds: list[int]) -> None:
    per_window(run, seeds)


def total(lines: list[dict[str, Any]]) -> None:
    """Per ground and mode, revisits called and wrong before the stop, parked and after, summed over every
    line; and the windows with a wrong one."""
    for ground in GROUNDS:
        for mode in MODES:
            sums = {p: {k: sum(line[ground][mode][p][k] for line in lines) for k in ("called", "wrong")}
                    for p in PHASES}
            bad = sorted({(line["half"], line["lo"], line["seed"]) for line in lines
                          if any(line[ground][mode][p]["wrong"] for p in PHASES)})
            print(ground, mode, json.dumps(sums), "windows with a wrong revisit:", len(bad), bad[:6])
    print("frames per drive:", BEFORE + PARKED + AFTER, "parked:", PARKED, "lines:", len(lines))
