"""Minicolumn network (MCN) baseline of Neubert et al., as restated by [CBA2020] (docs/design/science.md §4).

No spatial-pooler learning: minicolumns are created on demand, each with a fixed multiset of input
indices (FF). No dendritic segments: every cell has one set of binary outgoing "prediction connections",
learned in one shot; a cell is predicted if any cell active at t−1 connects to it. The column count
grows without bound, up to a `max_columns` cap that raises instead of truncating.

This is the working grid variant of [SIM] `miniColumn.py` plus the learning/inference split of
`miniColumn2.py`, without the defects listed in docs/design/science.md §4:

1. predictions are carried: `P_next` is a fresh array every step, never an alias of `P_prev`;
2. the "already connected from this column" check uses the previous winner's column;
3. storage grows by amortised doubling (no fixed 1000-column preallocation), there is no per-step
   columns × columns allocation, and every random draw comes from one seeded
   `numpy.random.Generator(PCG64(seed))`.

Cell id = column · nCellPerCol + i.

Example:
    >>> params = resolve_in_con(presets.mcn_params("mcn-grid"), mean_ones=40.6)
    >>> mcn = MCN(params, input_width=2048)
    >>> winners = mcn.step(np.array([3, 17, 40]), learn=True)  # sorted input ones -> sorted cell ids
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from models import presets, sdr

_CREATION_RULES = ("replace", "top_up")


class MCNCapacityError(RuntimeError):
    """Creating the columns a step needs would exceed `max_columns` (docs/design/science.md §4: never
    truncate)."""


@dataclass
class MCNStepStats:
    """Counts of the step just computed (docs/design/science.md §4, "report the column count after every
    step").

    Attributes:
        active_columns: |A|, including columns created by this step.
        predicted_columns: active columns with at least one cell predicted at t−1.
        bursting_columns: active columns without a predicted cell.
        predicted_cells: cells of active columns predicted at t−1 (they are the winners there);
            on a learned sequence the grid preset gives about one per active column.
        predictive_cells: cells with P_next > 0, i.e. predicted for the next step.
        winner_cells: number of winner cells returned.
        new_columns: columns created by this step.
        n_columns: column count after the step.
        n_connections: prediction connections after the step.
    """

    active_columns: int = 0
    predicted_columns: int = 0
    bursting_columns: int = 0
    predicted_cells: int = 0
    predictive_cells: int = 0
    winner_cells: int = 0
    new_columns: int = 0
    n_columns: int = 0
    n_connections: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


def _round_half_up(value: float) -> int:
    # [SIM] ran on Python 2, whose round() goes half away from zero; Python 3's round() goes half to
    # even. Both agree on every published configuration (40.56 → 41, 38.40 → 38, 0.25·38 = 9.5 → 10),
    # but half-up is the faithful choice for other data.
    return math.floor(value + 0.5)


def resolve_in_con(params: dict[str, Any], mean_ones: float) -> dict[str, Any]:
    """Fill in `nInConPerCol = round(mean ones per input)` when the preset leaves it `None`.

    docs/design/science.md §4 table: [SIM] `run00.py` sets nInConPerCol = round(count_nonzero(D) / rows),
    which is 41 for `noise0_al1` and 38 for `noise05_al5`. An explicit value is kept as it is.

    Args:
        params: full MCN parameters (`presets.mcn_params(...)`); not modified.
        mean_ones: mean number of ones per input SDR of the data the MCN will see.

    Returns:
        A copy of `params` with an integer `nInConPerCol`.
    """
    out = dict(params)
    if out.get("nInConPerCol") is None:
        if not mean_ones > 0:
            raise ValueError(f"mean_ones must be > 0 to derive nInConPerCol, got {mean_ones}")
        out["nInConPerCol"] = _round_half_up(float(mean_ones))
    return out


class MCN:
    """Minicolumn network of docs/design/science.md §4.

    Args:
        params: full parameter dict (`presets.mcn_params(...)`, then `resolve_in_con`); keys:
            nCellPerCol, nInConPerCol (int, resolved), minColumnActivity (fraction of nInConPerCol),
            strict (`>` instead of `>=`), nColsPerPattern (k_min), kActiveColumn (k_max or None),
            kMin, creation ("replace" | "top_up"), probAdditionalCon, max_columns, seed.
        input_width: size of the input index space (2048 for the grid world and sLSBH codes).

    Attributes:
        theta: activation threshold as a count, round(minColumnActivity · nInConPerCol).
        stats: `MCNStepStats` of the last step.
        column_counts: column count after every step so far (the paper's Fig. 8 curve).
    """

    def __init__(self, params: dict[str, Any], input_width: int) -> None:
        unknown = set(params) - set(presets.MCN_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown MCN parameter(s): {sorted(unknown)}")
        p = dict(presets.MCN_DEFAULTS)
        p.update(params)
        if p["nInConPerCol"] is None:
            raise ValueError(
                "nInConPerCol is None: resolve it from the data with resolve_in_con(params, mean_ones)"
            )
        if p["creation"] not in _CREATION_RULES:
            raise ValueError(f"creation must be one of {_CREATION_RULES}, got {p['creation']!r}")
        frac = float(p["minColumnActivity"])
        if not 0.0 <= frac <= 1.0:
            raise ValueError(f"minColumnActivity is a fraction of nInConPerCol in [0, 1], got {frac}")
        for name in ("nCellPerCol", "nInConPerCol", "nColsPerPattern", "max_columns"):
            if int(p[name]) < 1:
                raise ValueError(f"{name} must be >= 1, got {p[name]}")
        if p["kActiveColumn"] is not None and int(p["kActiveColumn"]) < 1:
            raise ValueError(f"kActiveColumn must be >= 1 or None, got {p['kActiveColumn']}")
        if p["creation"] == "replace" and p["kMin"] is None:
            raise ValueError("creation rule 'replace' needs kMin")
        if not 0.0 <= float(p["probAdditionalCon"]) <= 1.0:
            raise ValueError(f"probAdditionalCon must be in [0, 1], got {p['probAdditionalCon']}")
        if int(input_width) < 1:
            raise ValueError(f"input_width must be >= 1, got {input_width}")

        self.params = p
        self.input_width = int(input_width)
        self.cells_per_column = int(p["nCellPerCol"])
        self.n_in = int(p["nInConPerCol"])
        self.theta = _round_half_up(frac * self.n_in)
        self.strict = bool(p["strict"])
        self.k_min = int(p["nColsPerPattern"])
        self.k_max = None if p["kActiveColumn"] is None else int(p["kActiveColumn"])
        self.kmin_trigger = None if p["kMin"] is None else int(p["kMin"])
        self.creation = str(p["creation"])
        self.prob_additional = float(p["probAdditionalCon"])
        self.max_columns = int(p["max_columns"])
        self.rng = np.random.Generator(np.random.PCG64(p["seed"]))

        # Learned state. FF rows and out-degree entries beyond the column count are spare capacity.
        self._n_cols = 0
        # (capacity, nInConPerCol) in the platform index type: numpy converts any other index dtype to
        # intp on every gather, which costs more than the gather itself at tens of thousands of columns.
        self._ff = np.zeros((0, self.n_in), dtype=np.intp)
        self._out_count = np.zeros(0, dtype=np.int32)  # (capacity · nCellPerCol,) outgoing connections
        self._cell_targets: dict[int, list[int]] = {}  # cell -> its targets, in learning order
        # Per column: the targets of all its cells, with multiplicity (what a burst adds to P_next)
        # and as a set (the "already connected from this column" test, O(1) per pair).
        self._col_edges: dict[int, list[int]] = {}
        self._col_targets: dict[int, set[int]] = {}
        self._edge_keys: set[int] = set()  # pre << 32 | post: connections are a set, no duplicates

        # Sequence context: predicted counts and winners of the previous step.
        self._p_prev = np.zeros(0, dtype=np.int64)
        self._prev_winners = np.zeros(0, dtype=np.int64)

        self.stats = MCNStepStats()
        self.column_counts: list[int] = []

    # ------------------------------------------------------------------ introspection

    @property
    def n_columns(self) -> int:
        return self._n_cols

    @property
    def n_cells(self) -> int:
        return self._n_cols * self.cells_per_column

    @property
    def n_connections(self) -> int:
        return len(self._edge_keys)

    @property
    def ff(self) -> np.ndarray:
        """(n_columns, nInConPerCol) int64 copy of the input indices of every column."""
        return self._ff[: self._n_cols].astype(np.int64)

    def targets(self, cell: int) -> np.ndarray:
        """Sorted (m,) int64 targets of the outgoing prediction connections of `cell`."""
        return np.array(sorted(self._cell_targets.get(int(cell), ())), dtype=np.int64)

    def predictive_cells(self) -> np.ndarray:
        """Sorted cell ids predicted for the next step (P_next > 0 of the last step)."""
        return np.flatnonzero(self._p_prev).astype(np.int64)

    def reset(self) -> None:
        """Break the sequence: forget the previous predictions and winners, keep what was learned."""
        self._p_prev = np.zeros(0, dtype=np.int64)
        self._prev_winners = np.zeros(0, dtype=np.int64)

    # ------------------------------------------------------------------ one step

    def step(self, x: np.ndarray, learn: bool = True) -> np.ndarray:
        """One step of docs/design/science.md §4.

        Args:
            x: (w,) sorted int indices of the ones of the input SDR, all in [0, input_width).
            learn: create columns and connections ("learning"), or only infer (needs kActiveColumn).

        Returns:
            (n,) int32 sorted winner cell ids (cell = column · nCellPerCol + i).

        Raises:
            MCNCapacityError: the columns this step must create would exceed `max_columns`; the
                model is left unchanged.
            ValueError: bad input, or inference without kActiveColumn.
        """
        x = self._check_input(x)
        nc = self.cells_per_column
        n_prev_cols = self._n_cols
        active = self._active_columns(x, learn)
        n_new = self._n_cols - n_prev_cols

        # Predicted cells of every active column, read from P_prev. Columns created this step did not
        # exist at t−1 and P_prev does not cover them: they always burst.
        offs = np.arange(nc, dtype=np.int64)
        cells = active[:, None] * nc + offs[None, :]  # (|A|, nc)
        predicted = np.zeros(cells.shape, dtype=bool)
        old = active < n_prev_cols
        if self._p_prev.size and old.any():
            predicted[old] = self._p_prev[cells[old]] > 0
        n_pred_per_col = predicted.sum(axis=1)

        # Previous winners grouped by column: the learning winner choice penalises them (+nCellPerCol).
        prev_by_col: dict[int, list[int]] = {}
        if learn:
            for p in self._prev_winners.tolist():
                prev_by_col.setdefault(p // nc, []).append(p % nc)

        pending: list[int] = []  # targets that receive +1 in P_next, with multiplicity
        winners: list[int] = []
        bursting: list[int] = []
        for row, c in enumerate(active.tolist()):
            if n_pred_per_col[row] == 0:
                bursting.append(c)
                pending.extend(self._col_edges.get(c, ()))
                base = c * nc
                counts = self._out_count[base : base + nc]
                if learn:
                    penalty = counts.astype(np.int64)
                    for i in prev_by_col.get(c, ()):
                        penalty[i] += nc
                    candidates = np.flatnonzero(penalty == penalty.min())
                else:
                    candidates = np.flatnonzero(counts > 0)
                    if candidates.size == 0:
                        candidates = offs
                i = int(candidates[0]) if candidates.size == 1 else int(self.rng.choice(candidates))
                winners.append(base + i)
            else:
                for cell in cells[row, predicted[row]].tolist():
                    winners.append(cell)
                    pending.extend(self._cell_targets.get(cell, ()))

        if learn:
            self._learn(winners)
            # Connections just learned from bursting cells also predict (miniColumn.py "also predict
            # newly learned predictions"): every cell of a bursting column adds its targets again.
            for c in bursting:
                pending.extend(self._col_edges.get(c, ()))

        # Fresh array every step: the aliasing defect of miniColumn2.py (§4 defect 1) is impossible.
        p_next = np.bincount(np.asarray(pending, dtype=np.int64), minlength=self.n_cells)
        winners_arr = np.asarray(winners, dtype=np.int64)  # ascending: columns ascending, cells ascending

        self.stats = MCNStepStats(
            active_columns=int(active.size),
            predicted_columns=int(np.count_nonzero(n_pred_per_col)),
            bursting_columns=len(bursting),
            predicted_cells=int(n_pred_per_col.sum()),
            predictive_cells=int(np.count_nonzero(p_next)),
            winner_cells=len(winners),
            new_columns=n_new,
            n_columns=self._n_cols,
            n_connections=self.n_connections,
        )
        self.column_counts.append(self._n_cols)
        self._p_prev = p_next
        self._prev_winners = winners_arr
        return winners_arr.astype(sdr.INDEX_DTYPE)

    # ------------------------------------------------------------------ internals

    def _check_input(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x)
        if x.ndim != 1:
            raise ValueError(f"x must be a 1-D array of indices, got shape {x.shape}")
        if x.size and not np.issubdtype(x.dtype, np.integer):
            raise ValueError(f"x must hold integer indices, got dtype {x.dtype}")
        x = x.astype(np.int64, copy=False)
        if x.size and (x.min() < 0 or x.max() >= self.input_width):
            raise ValueError(f"x indices must lie in [0, {self.input_width}), got [{x.min()}, {x.max()}]")
        if x.size > 1 and not np.all(x[1:] > x[:-1]):
            x = np.unique(x)  # duplicates would bias the draws of a new column
        return x

    def _passes(self, activity: np.ndarray) -> np.ndarray:
        return activity > self.theta if self.strict else activity >= self.theta

    def _kth_largest(self, activity: np.ndarray) -> int:
        assert self.k_max is not None
        k = min(self.k_max, activity.size)
        return int(np.partition(activity, activity.size - k)[activity.size - k])

    def _active_columns(self, x: np.ndarray, learn: bool) -> np.ndarray:
        """Column activity and the active set A (ascending int64), creating columns when learning."""
        n = self._n_cols
        if n:
            dense = sdr.to_dense(x, self.input_width)
            # A repeated FF index counts as many times as it is repeated (docs/design/science.md §4).
            activity = np.take(dense, self._ff[:n]).sum(axis=1, dtype=np.int32)
        else:
            activity = np.zeros(0, dtype=np.int32)

        if not learn:
            if self.k_max is None:
                raise ValueError("inference (learn=False) needs kActiveColumn (k_max); the preset has None")
            if n == 0:
                return np.zeros(0, dtype=np.int64)
            # miniColumn2.py: the k most active columns plus ties, with no activity threshold.
            return np.flatnonzero(activity >= self._kth_largest(activity)).astype(np.int64)

        mask = self._passes(activity)
        if self.creation == "replace":
            active = np.flatnonzero(mask).astype(np.int64)
            if active.size < self.kmin_trigger:
                # The grid rule replaces the (too few) matching columns by k_min new ones.
                active = self._create_columns(x, self.k_min)
            return active
        if self.k_max is not None and n:
            mask &= activity >= self._kth_largest(activity)
        active = np.flatnonzero(mask).astype(np.int64)
        need = max(0, self.k_min - active.size)
        if need:
            active = np.concatenate([active, self._create_columns(x, need)])
        return active

    def _create_columns(self, x: np.ndarray, k: int) -> np.ndarray:
        """Append k columns, each with nInConPerCol indices drawn with replacement from the ones of x."""
        n = self._n_cols
        if n + k > self.max_columns:
            raise MCNCapacityError(
                f"MCN needs {n + k} columns, above max_columns={self.max_columns} (it holds {n}); "
                "raise max_columns or use less varied input"
            )
        if x.size == 0:
            raise ValueError("cannot create a minicolumn from an empty input SDR")
        self._reserve(n + k)
        self._ff[n : n + k] = self.rng.choice(x, size=(k, self.n_in), replace=True)
        self._n_cols = n + k
        return np.arange(n, n + k, dtype=np.int64)

    def _reserve(self, n_cols: int) -> None:
        cap = self._ff.shape[0]
        if n_cols <= cap:
            return
        new_cap = min(max(n_cols, 2 * cap, 64), self.max_columns)
        ff = np.zeros((new_cap, self.n_in), dtype=np.intp)
        ff[:cap] = self._ff
        self._ff = ff
        out = np.zeros(new_cap * self.cells_per_column, dtype=np.int32)
        out[: self._out_count.size] = self._out_count
        self._out_count = out

    def _learn(self, winners: list[int]) -> None:
        """Connect every previous winner p to every current winner w (docs/design/science.md §4).

        p→w is added when no cell of p's column already connects to w; otherwise only with
        probability probAdditionalCon. The check is sequential, as in miniColumn.py: a connection
        just added from p's column counts for the next previous winner of the same column.
        """
        nc = self.cells_per_column
        prob = self.prob_additional
        for p in self._prev_winners.tolist():
            cp = p // nc
            col_targets = self._col_targets.setdefault(cp, set())
            for w in winners:
                # The random draw is made only when the column is already connected, as in [SIM].
                if w in col_targets and not self.rng.random() < prob:
                    continue
                key = (p << 32) | w
                if key in self._edge_keys:
                    continue
                self._edge_keys.add(key)
                self._cell_targets.setdefault(p, []).append(w)
                self._col_edges.setdefault(cp, []).append(w)
                col_targets.add(w)
                self._out_count[p] += 1
