"""Experiments of docs/results.md §10.8: where the localiser's new rows start (the jump level J of
docs/design/science.md §11.2, §11.5), tried on the `cortexloc eval` commands. Not the service's code:
each replaces `SequenceLocaliser._jump_level` for the run only, so the rest of the path is the service's.

    cortexloc eval null-entry entry:10 eval slam --data $D --half tune
    cortexloc eval null-entry rows eval unknown --db $D/summer ...

Variants (J; `c` = `jump_cost`, `best` = the live rows' best decayed score, `null` = the null's):
- `adopted`: the service's rule, max(best, null) - c; 0 - c without a row path;
- `rows`: before issue 21's change, best - c (0 - c without a row path): rows never born from the null;
- `entry:K`: the null entered at its own cost K, max(best - c, null - K) (0 - c for best without rows);
  `entry:0` is free entry from the null;
- `first`: the change's first version, max(best, null) - c also without a row path (null - c);
- `level`: max(best, null) - c, and level with the null (no cost) without a row path.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from models.localisation import localiser as loc


def jump_level(variant: str):
    kind, _, value = variant.partition(":")

    def level(self, past: np.ndarray, null: float) -> float:
        c = float(self.options.jump_cost)
        best = float(past.max()) if past.size else None
        if kind == "adopted":
            return (max(best, null) if best is not None else 0.0) - c
        if kind == "rows":
            return (best if best is not None else 0.0) - c
        if kind == "entry":
            return max((best if best is not None else 0.0) - c, null - float(value))
        if kind == "first":
            return max([b for b in (best, null) if b is not None and np.isfinite(b)], default=0.0) - c
        if kind == "level":
            if best is not None:
                return max(best, null) - c
            return null if np.isfinite(null) else -c
        raise SystemExit(f"unknown variant {variant!r}; see the module docstring")

    return level


def main(*, variant: str, command: list[str], run_command: Callable[[list[str]], object]) -> None:
    """`cortexloc eval null-entry VARIANT COMMAND...`: install `variant` for this process, then run
    `command` (another `cortexloc` command line) through `run_command`."""
    loc.SequenceLocaliser._jump_level = jump_level(variant)
    run_command(command)
