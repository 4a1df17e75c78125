"""Experiments of docs/results.md §10.9: the echo, a path that follows the trail a learning stream lays
(docs/design/science.md §11.6), and what was tried against it, on the `cortexloc eval` commands. Not the
service's code: each variant replaces `OwnTrail.laid_behind` (or the step's candidates) for the run only,
so the rest of the path is the service's.

    cortexloc eval echo off eval slam --data $D --half tune
    cortexloc eval echo kill eval slam --grid $G --thresholds 0.5
    cortexloc eval echo off synthetic
    cortexloc eval echo codes:61 eval slam --data $D --half tune \
        --routes stop --methods service-slam --thresholds 0.9

`codes:N`: the service's rule, and after the run the Dice of the last stream's frame N (0-based) with
the 20 rows stored before it, nearest first, beside its background likeness (§10.9).

`synthetic`: the synthetic echo of tests/models/localisation/test_trail.py (`drifting`: 120 frames, a
pool of 100 of 300 bits swapping 2 or 5 a frame, no revisit) through `online.loop_closure`, 12 seeds:
the lowest and highest of each seed's highest confidence.

Variants:
- `adopted`: the service's rule: a path ends on a row of the stream's own trail stored after it began,
  unless the frame is more like the row than like the trail's last `exclusion` + 1 rows;
- `off`: no such rule (before §10.9): only the rows the stream has not left end a path;
- `kill`: the rule without its likeness test (every such row ends the path);
- `absolute`: the likeness test at an absolute level, Dice >= b + `consolidate` * (1 - b) (§11.8's);
- `between`: no path rule; instead an own-trail row behind the window is a candidate only if the frame
  is more like it than the least alike trail frame stored since it (went away and came back by looks).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from models.localisation import localiser as loc
from models.localisation import trail


def install(variant: str) -> None:
    adopted = trail.OwnTrail.laid_behind

    def no_test(self, graph, rows, began):
        return adopted(self._replace(code_of=None), graph, rows, began)

    def absolute(self, graph, rows, began):
        laid = adopted(self._replace(code_of=None), graph, rows, began)
        if laid.any():
            c = float(loc.LocaliserOptions().consolidate)
            # the absolute level needs the frame's background likeness, captured at `own_trail` (below)
            level = trail.above_background(STATS["b"], c)
            laid[laid] = [trail.code_dice(self.code, np.asarray(self.code_of(int(r)))) < level
                          for r in np.asarray(rows)[laid]]
        return laid

    if variant == "adopted":
        return
    if variant.startswith("codes:"):
        frame, own_trail = int(variant.partition(":")[2]), loc.SequenceLocaliser.own_trail

        def record(self, state, graph, last, code, code_of, stats, informative=True):
            if last is None:  # a stream's first frame: count again
                SEEN.clear()
            if len(SEEN) == frame:
                behind, row = [], last if last is not None else -1
                while row >= 0 and len(behind) < 20:  # the rows stored before it, nearest first
                    behind.append(np.asarray(code_of(row)))
                    row = int(graph.prev[row])
                SEEN.append((np.asarray(code), stats.background(code), behind))
            elif len(SEEN) < frame:
                SEEN.append(None)
            return own_trail(self, state, graph, last, code, code_of, stats, informative)

        loc.SequenceLocaliser.own_trail = record
        return
    if variant in ("off", "between"):
        trail.OwnTrail.laid_behind = lambda self, graph, rows, began: np.zeros(len(rows), bool)
    elif variant == "kill":
        trail.OwnTrail.laid_behind = no_test
    elif variant == "absolute":
        trail.OwnTrail.laid_behind = absolute
    else:
        raise SystemExit(f"unknown variant {variant!r}; see the module docstring")
    own_trail = loc.SequenceLocaliser.own_trail

    def capture(self, state, graph, last, code, code_of, stats, informative=True):
        STATS["b"] = stats.background(code)
        return own_trail(self, state, graph, last, code, code_of, stats, informative)

    loc.SequenceLocaliser.own_trail = capture
    if variant == "between":
        step = loc.SequenceLocaliser.step

        def filtered(self, state, graph, seqs, scores, own=None, *rest, **kw):
            seqs, scores = np.asarray(seqs, np.int64), np.asarray(scores, np.float64)
            if own is not None and own.code_of is not None and seqs.size:
                keep = np.ones(seqs.size, bool)
                for i in np.flatnonzero((graph.trail[seqs] == own.trail) & (seqs < own.first)):
                    row = np.asarray(own.code_of(int(seqs[i])))
                    now, u, back = trail.code_dice(own.code, row), int(graph.next[seqs[i]]), False
                    while 0 <= u <= own.last and graph.trail[u] == own.trail and not back:
                        back = trail.code_dice(np.asarray(own.code_of(u)), row) < now
                        u = int(graph.next[u])
                    keep[i] = back
                seqs, scores = seqs[keep], scores[keep]
            return step(self, state, graph, seqs, scores, own, *rest, **kw)

        loc.SequenceLocaliser.step = filtered


STATS: dict[str, float] = {"b": 0.0}
SEEN: list = []  # `codes:N`: None for a stream's frames before N, then (code, background, rows' codes)


def synthetic() -> None:
    from models.evaluation import online
    from models.sdr import dice_matrix
    from tests.models.localisation.test_trail import drifting

    for drift in (2, 5):
        highest = []
        for seed in range(12):
            codes = drifting(120, seed, drift=drift)
            highest.append(online.loop_closure(dice_matrix(codes), codes).confidence.max())
        print(f"{drift} bits a frame: highest confidence {min(highest):.3f}-{max(highest):.3f} over 12 seeds")


def main(*, variant: str, command: list[str], run_command: Callable[[list[str]], object]) -> None:
    """`cortexloc eval echo VARIANT COMMAND...`: install `variant` for this process, then run `command`
    (another `cortexloc` command line, through `run_command`) or, for `synthetic`, the synthetic echo."""
    install(variant)
    if command == ["synthetic"]:
        synthetic()
        return
    try:
        run_command(command)
    finally:
        if variant.startswith("codes:") and len(SEEN) > int(variant.partition(":")[2]) and SEEN[-1]:
            code, background, behind = SEEN[-1]
            print(f"frame {len(SEEN) - 1}: background likeness {background:.3f}; Dice with the rows 1..20 "
                  "behind it: " + " ".join(f"{trail.code_dice(code, c):.2f}" for c in behind))

