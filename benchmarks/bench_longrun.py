"""Long run: 10^6 Temporal Memory steps with the default preset, RSS, caps and the forgetting curve.

Run: `cortexloc bench longrun [--steps N] [--quick]` (`make bench` runs 10^6 steps, which
takes about 2.5 hours on one shared core here with `cortexloc-default`). Writes
benchmarks/results/longrun.json after every checkpoint, so a run that is stopped early still leaves
its numbers.

What it does, with the map's own classes (TemporalMemory, InvertedIndex) and the preset named
`cortexloc-default` (refer to it by name: its parameters may change):

1. An *early loop*: a route of `--places` places (fixed random SDRs of the preset's 2n active columns
   out of columnDimensions), driven `--laps` times with noise (`--noise` of the columns replaced at each
   visit), learning on; each learned step's winner cells go into an inverted index, as in the service.
2. Then novel input until `--steps` steps in total: new routes of `--places` places, each driven twice
   with noise and followed by a reset (a new mission), learning on (`--novel random`: a never-repeating
   random SDR every step, the worst case for the caps).
3. Every `steps/10` steps (the checkpoints): RSS of the process, segments/synapses against capacity,
   evictions (segment cap) and overruns (synapse cap), median ms/step of the last window, and the recall
   of the early loop: one more noisy lap with learning off in a fresh context, each step's winner cells
   ranked by Dice against the stored descriptors of the early loop (top-1), correct when the best match
   is a visit of the same place. The evaluation lap uses the same noise every time, so the curve is
   comparable across checkpoints; it changes nothing learned (learn=False).

The steps where the caps start to bind are the first eviction (a cell already has maxSegmentsPerCell
segments and the least recently used one is reused) and the first synapse overrun (a segment at
maxSynapsesPerSegment drops its weakest synapse), checked every 100 steps.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import RESULTS, quick_mode, rss_mib, write_json
from models import presets
from models.frontend import slsbh
from models.localisation.index import InvertedIndex
from models.memory.temporal_memory import StreamContext, TemporalMemory

CHECK_EVERY = 100  # steps between looks at the eviction/overrun counters


def noisy(base: np.ndarray, n_replace: int, columns: int, rng: np.random.Generator) -> np.ndarray:
    """`base` with `n_replace` of its columns swapped for columns outside it (a noisy revisit).

    Args:
        base: (a,) sorted distinct active columns.
        n_replace: how many to replace.
        columns: size of the column space.

    Returns:
        (a,) sorted distinct columns, same count as `base`.
    """
    if n_replace <= 0:
        return base
    keep = rng.choice(base, base.size - n_replace, replace=False)
    fresh = np.setdiff1d(rng.choice(columns, 4 * n_replace + 8, replace=False), base)[:n_replace]
    rng.shuffle(fresh)
    return np.sort(np.concatenate([keep, fresh[:n_replace]]))


def random_places(n: int, columns: int, active: int, rng: np.random.Generator) -> list[np.ndarray]:
    """n random SDRs, each (active,) sorted distinct columns."""
    return [np.sort(rng.choice(columns, active, replace=False)) for _ in range(n)]


class LongRun:
    """The state of one long run: the memory, the early loop's descriptors, counters and results."""

    def __init__(self, preset: str, places: int, laps: int, noise: float, seed: int) -> None:
        self.preset = preset
        self.params = presets.tm_params(preset)
        s_conf = presets.slsbh_params(preset)
        self.columns = int(self.params["columnDimensions"])
        self.active = 2 * slsbh.n_ones(int(s_conf["k"]), float(s_conf["s"]))  # the codes' ones (2n)
        self.n_replace = round(noise * self.active)
        self.n_places, self.laps = places, laps
        self.rng = np.random.Generator(np.random.PCG64(seed))
        self.eval_seed = seed + 1_000_003
        self.tm = TemporalMemory(presets.TmOptions.of(self.params))
        self.ctx = StreamContext()
        self.index = InvertedIndex(self.tm.n_cells, 10_000_000)
        self.place_of_row: list[int] = []
        self.early = random_places(places, self.columns, self.active, self.rng)
        self.steps = 0
        self.step_times: list[float] = []
        self.first_eviction: int | None = None
        self.first_overrun: int | None = None

    def step(self, x: np.ndarray) -> np.ndarray:
        t0 = time.perf_counter()
        w = self.tm.compute(x, learn=True, context=self.ctx)
        self.step_times.append(time.perf_counter() - t0)
        self.steps += 1
        if self.steps % CHECK_EVERY == 0:
            self._check_caps()
        return w

    def _check_caps(self) -> None:
        c = self.tm.counters  # [evictions, overruns, decay, empty] (models.memory._tm_synapses.C_*)
        if self.first_eviction is None and c[0] > 0:
            self.first_eviction = self.steps
        if self.first_overrun is None and c[1] > 0:
            self.first_overrun = self.steps

    def learn_early_loop(self) -> None:
        """`laps` noisy laps of the early route, learning on; every step stored in the index."""
        self.ctx.reset()
        for _ in range(self.laps):
            for p, base in enumerate(self.early):
                w = self.step(noisy(base, self.n_replace, self.columns, self.rng))
                self.index.add(len(self.place_of_row) + 1, w, "early")
                self.place_of_row.append(p)
        self.ctx.reset()

    def recall(self) -> dict[str, float]:
        """Recall@1 of one noisy lap of the early loop with learning off (and of the raw inputs)."""
        rng = np.random.Generator(np.random.PCG64(self.eval_seed))  # same noise at every checkpoint
        ctx = StreamContext()
        tm_hits = 0
        dice_best = []
        for p, base in enumerate(self.early):
            x = noisy(base, self.n_replace, self.columns, rng)
            w = self.tm.compute(x, learn=False, context=ctx)
            m = self.index.rank(w, 1)
            if m and self.place_of_row[m[0].seq - 1] == p:
                tm_hits += 1
            dice_best.append(m[0].score if m else 0.0)
        return {"recall_at_1": tm_hits / self.n_places, "best_dice_median": float(np.median(dice_best))}

    def input_recall(self) -> float:
        """Recall@1 of the same evaluation lap on the input SDRs themselves (no memory): the ceiling."""
        rng = np.random.Generator(np.random.PCG64(self.eval_seed))
        stored = np.zeros((self.n_places, self.columns), dtype=bool)
        for p, base in enumerate(self.early):
            stored[p, base] = True
        hits = 0
        for p, base in enumerate(self.early):
            x = noisy(base, self.n_replace, self.columns, rng)
            hits += int(np.argmax(stored[:, x].sum(axis=1)) == p)
        return hits / self.n_places

    def novel_block(self, mode: str, limit: int) -> None:
        """Up to `limit` steps of novel input: a new route driven twice then a reset, or random SDRs."""
        if mode == "random":
            for _ in range(limit):
                self.step(np.sort(self.rng.choice(self.columns, self.active, replace=False)))
            return
        route = random_places(self.n_places, self.columns, self.active, self.rng)
        done = 0
        for _ in range(2):
            for base in route:
                if done == limit:
                    return
                self.step(noisy(base, self.n_replace, self.columns, self.rng))
                done += 1
        self.ctx.reset()

    def checkpoint(self, t_start: float) -> dict[str, Any]:
        size = self.tm.size()
        s_cap = int(self.params["maxSegmentsPerCell"])
        cells_full = int(np.count_nonzero(self.tm._seg_count >= s_cap))  # cells whose segment cap binds
        window = np.asarray(self.step_times) * 1e3
        self.step_times = []
        return {
            "step": self.steps, "elapsed_s": round(time.perf_counter() - t_start, 1),
            "rss_mib": round(rss_mib(), 1),
            "segments": size["segments"], "segment_capacity": size["segment_capacity"],
            "synapses": size["synapses"], "synapse_capacity": size["synapse_capacity"],
            "segment_fill": round(size["segments"] / size["segment_capacity"], 4),
            "synapse_fill": round(size["synapses"] / size["synapse_capacity"], 4),
            "cells_at_segment_cap": cells_full, "evictions": size["evictions"],
            "overrun_synapses": size["overrun_destroyed"], "decay_destroyed": size["decay_destroyed"],
            "ms_per_step_median": float(np.median(window)) if window.size else None,
            "ms_per_step_p90": float(np.percentile(window, 90)) if window.size else None,
            **self.recall(),
        }


def main(*, steps: int | None, checkpoints: int, preset: str, places: int, laps: int, noise: float,
         novel: str, seed: int, quick: bool, out: Path | None) -> None:
    if out is None:
        out = RESULTS / "longrun.json"
    quick = quick_mode(quick)
    steps = steps or (20_000 if quick else 1_000_000)
    every = max(1, steps // checkpoints)

    run = LongRun(preset, places, laps, noise, seed)
    # Compile the kernels before measuring anything (numba caches on disk; the first call still loads).
    warm = TemporalMemory(presets.TmOptions.of({**run.params, "columnDimensions": 64,
                                                "maxSegmentsPerCell": 2}))
    for x in random_places(20, 64, 8, np.random.default_rng(1)):
        warm.compute(x, learn=True)
        warm.compute(x, learn=False)
    del warm
    size = run.tm.size()
    print(f"longrun: preset {preset!r}, {run.columns} columns x {run.tm.cells_per_column} cells, "
          f"{run.active} active, caps {run.params['maxSegmentsPerCell']} seg/cell x "
          f"{run.params['maxSynapsesPerSegment']} syn/seg, preallocated {size['bytes'] / 2**20:.1f} MiB; "
          f"{steps} steps, checkpoint every {every}", flush=True)
    t_start = time.perf_counter()
    rss_alloc = rss_mib()
    run.learn_early_loop()
    cp0 = run.checkpoint(t_start)
    input_ceiling = run.input_recall()
    print(f"  after the early loop ({run.steps} steps): recall@1 {cp0['recall_at_1']:.2f} "
          f"(inputs alone {input_ceiling:.2f}), RSS {cp0['rss_mib']} MiB", flush=True)
    points = [cp0]
    result: dict[str, Any] = {}

    def save(done: bool) -> None:
        rss = [c["rss_mib"] for c in points]
        result.update({
            "config": {"preset": preset, "tm": run.params, "active": run.active, "steps": steps,
                       "places": places, "laps": laps, "noise": noise, "novel": novel,
                       "seed": seed, "quick": quick},
            "finished": done, "steps_done": run.steps, "preallocated_mib": size["bytes"] / 2**20,
            "rss_after_alloc_mib": round(rss_alloc, 1),
            # Flatness: the largest RSS at any checkpoint against the first one (memory is preallocated).
            "rss_growth_pct": round(100 * (max(rss) / rss[0] - 1), 2),
            "first_eviction_step": run.first_eviction, "first_overrun_step": run.first_overrun,
            "input_recall_at_1": input_ceiling, "checkpoints": points,
        })
        write_json(out.name, result, out)

    save(False)
    next_cp = (run.steps // every + 1) * every  # the first checkpoint after the early loop
    last_print = time.perf_counter()
    while run.steps < steps:
        run.novel_block(novel, min(next_cp, steps) - run.steps)
        if time.perf_counter() - last_print > 30:
            last_print = time.perf_counter()
            el = last_print - t_start
            print(f"  step {run.steps}/{steps} ({el:.0f} s, {run.steps / el:.0f} steps/s)", flush=True)
        if run.steps >= next_cp or run.steps >= steps:
            cp = run.checkpoint(t_start)
            points.append(cp)
            print(f"  checkpoint {cp['step']}: RSS {cp['rss_mib']} MiB, segments {cp['segment_fill']:.1%} "
                  f"synapses {cp['synapse_fill']:.1%} of capacity, "
                  f"cells at cap {cp['cells_at_segment_cap']}, "
                  f"evictions {cp['evictions']}, overruns {cp['overrun_synapses']}, "
                  f"{cp['ms_per_step_median']:.2f} ms/step, early-loop recall@1 {cp['recall_at_1']:.2f}",
                  flush=True)
            save(run.steps >= steps)
            next_cp += every
    print(f"longrun: RSS growth {result['rss_growth_pct']}% after allocation; first eviction at step "
          f"{run.first_eviction}, first synapse overrun at step {run.first_overrun}; recall@1 of the early "
          f"loop {points[0]['recall_at_1']:.2f} -> {points[-1]['recall_at_1']:.2f}", flush=True)

