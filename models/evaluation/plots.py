"""Figures written beside every evaluation result (science.md §8.1, §8.6): PR curves and S images.

The figures are drawn on an explicit Agg canvas instead of through pyplot: no global backend switch, no
display needed, and safe to call from worker threads of the service or from tests.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from models.evaluation.metrics import auc

if TYPE_CHECKING:
    from matplotlib.figure import Figure

Curve = tuple[np.ndarray | Sequence[float], np.ndarray | Sequence[float]]


def _save(fig: Figure, path: str | Path) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    FigureCanvasAgg(fig)  # binds the figure to Agg, whatever pyplot's backend is
    fig.savefig(out, format="png", dpi=120)
    return out


def plot_pr_curves(curves: Mapping[str, Curve], path: str | Path, title: str) -> Path:
    """Draw all methods' PR curves in one figure, each labelled with its AUC (§8.2).

    Args:
        curves: method name -> (P, R), each a (n,) sequence as returned by `metrics.pr_curve`.
        path: PNG file to write (parent folders are created).
        title: figure title (state dataset, scoring and tolerance there, §8.6).

    Returns:
        The written path.
    """
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.0, 5.0))
    ax = fig.add_subplot()
    for name, (P, R) in curves.items():
        ax.plot(np.asarray(R, dtype=np.float64), np.asarray(P, dtype=np.float64),
                label=f"{name} (AUC {auc(P, R):.6f})")
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.05)
    ax.grid(True, alpha=0.3)
    ax.set_title(title)
    if curves:
        ax.legend(loc="lower left", fontsize="small")
    fig.tight_layout()
    return _save(fig, path)


def plot_similarity(S: np.ndarray, path: str | Path, title: str) -> Path:
    """Draw a similarity matrix as an image (the paper's Fig. 4 style, §8.1).

    Args:
        S: (n_db, n_query) similarities; database rows, query columns.
        path: PNG file to write (parent folders are created).
        title: figure title.

    Returns:
        The written path.
    """
    from matplotlib.figure import Figure

    s = np.asarray(S, dtype=np.float64)
    if s.ndim != 2:
        raise ValueError(f"S must be 2-D, got shape {s.shape}")
    fig = Figure(figsize=(6.0, 5.0))
    ax = fig.add_subplot()
    image = ax.imshow(s, cmap="viridis", interpolation="nearest", aspect="auto", origin="upper")
    fig.colorbar(image, ax=ax, label="similarity")
    ax.set_xlabel("query")
    ax.set_ylabel("database")
    ax.set_title(title)
    fig.tight_layout()
    return _save(fig, path)
