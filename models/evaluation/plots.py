"""Figures written beside every evaluation result (docs/design/science.md §8.1, §8.6): PR curves and S images.

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


def similarity_caption(S: np.ndarray) -> str:
    """What a reader of the similarity image would misread, said under it: its white cells (no score:
    -inf or NaN) and its values below 0 (scores, not anticorrelations); "" when it has neither.

    Args:
        S: (n_db, n_query) similarities as drawn by `plot_similarity`.
    """
    s = np.asarray(S, dtype=np.float64)
    finite = np.isfinite(s)
    lines = []
    if not finite.all():
        lines.append(f"White: no score ({int((~finite).sum()):,} of {s.size:,} cells), not a similarity "
                     "of 0: the method never weighed that pair (a sequence method: no full path of ds "
                     "frames there, as at the route's ends; an online method or the service: no hypothesis "
                     "ended on that row).")
    if finite.any() and s[finite].min() < 0:
        lines.append("Below 0: scores, not anticorrelations. A sequence method gives minus a contrast-"
                     "normalised difference (0 = the local mean of its database window), an online method "
                     "a decayed path score less its move costs, cosine after mean subtraction (--adapt) "
                     "any sign; only the order down a query column decides the answer.")
    return "\n".join(lines)


def similarity_figure(S: np.ndarray, title: str) -> Figure:
    """A similarity matrix as an image (the paper's Fig. 4 style, §8.1), captioned by
    `similarity_caption`.

    Args:
        S: (n_db, n_query) similarities; database rows, query columns.
        title: figure title.
    """
    import textwrap

    from matplotlib.figure import Figure

    s = np.asarray(S, dtype=np.float64)
    if s.ndim != 2:
        raise ValueError(f"S must be 2-D, got shape {s.shape}")
    caption = [textwrap.fill(line, 95) for line in similarity_caption(s).splitlines()]
    lines = sum(c.count("\n") + 1 for c in caption)
    fig = Figure(figsize=(6.0, 5.0 + 0.12 * lines))
    ax = fig.add_subplot()
    image = ax.imshow(s, cmap="viridis", interpolation="nearest", aspect="auto", origin="upper")
    fig.colorbar(image, ax=ax, label="similarity")
    ax.set_xlabel("query")
    ax.set_ylabel("database")
    ax.set_title(title)
    if caption:
        fig.text(0.01, 0.01, "\n".join(caption), fontsize=6.5, va="bottom", ha="left")
        fig.tight_layout(rect=(0.0, (0.12 * lines + 0.05) / (5.0 + 0.12 * lines), 1.0, 1.0))
    else:
        fig.tight_layout()
    return fig


def plot_similarity(S: np.ndarray, path: str | Path, title: str) -> Path:
    """Draw a similarity matrix as an image with its caption (`similarity_figure`).

    Args:
        S: (n_db, n_query) similarities; database rows, query columns.
        path: PNG file to write (parent folders are created).
        title: figure title.

    Returns:
        The written path.
    """
    return _save(similarity_figure(S, title), path)


# Match gallery layout (pixels): every image is shown at TILE = (width, height); a pair is framed by
# BORDER pixels of its verdict's colour, with a caption strip under it.
TILE = (128, 64)
BORDER = 4
GAP = 4
CAPTION = 18
RIGHT_BGR = (0, 170, 0)
WRONG_BGR = (0, 0, 230)


def gallery_cell_size() -> tuple[int, int]:
    """(width, height) of one query/answer pair in the match gallery."""
    return 2 * TILE[0] + GAP + 2 * BORDER, TILE[1] + 2 * BORDER + CAPTION


def match_gallery(db_paths: Sequence[str | Path], q_paths: Sequence[str | Path], queries: Sequence[int],
                  best: Sequence[int], correct: Sequence[bool], confidence: Sequence[float],
                  path: str | Path, n: int = 12, cols: int = 3) -> Path:
    """A PNG of sampled queries beside their answers: green frame when right, red when wrong.

    Args:
        db_paths, q_paths: the database and query image files (index = row / column of S).
        queries: (m,) scored query indices; best, correct, confidence: (m,) each query's answer
            (database index), its verdict and its confidence, in the same order.
        path: PNG file to write (parent folders are created).
        n: queries shown, evenly spaced over the m (all if m <= n).
        cols: pairs per gallery row.

    Returns:
        The written path. The image is ceil(k / cols) x cols cells of `gallery_cell_size()`, k = min(n, m);
        each cell: query left, answer right, caption "q <query> -> <answer>  conf <c>".
    """
    import cv2

    m = len(queries)
    if m == 0 or n < 1 or cols < 1:
        raise ValueError(f"need at least one query, n >= 1 and cols >= 1 (got {m}, {n}, {cols})")
    pick = np.unique(np.linspace(0, m - 1, min(n, m)).round().astype(int))
    cw, ch = gallery_cell_size()
    rows = -(-len(pick) // cols)
    canvas = np.full((rows * ch, min(cols, len(pick)) * cw, 3), 255, dtype=np.uint8)

    def tile(p: str | Path) -> np.ndarray:
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        if img is None:
            raise ValueError(f"cannot read image {p}")
        return cv2.resize(img, TILE, interpolation=cv2.INTER_NEAREST)

    for slot, k in enumerate(pick):
        y, x = (slot // cols) * ch, (slot % cols) * cw
        colour = RIGHT_BGR if correct[k] else WRONG_BGR
        canvas[y:y + TILE[1] + 2 * BORDER, x:x + cw] = colour
        inner_y, inner_x = y + BORDER, x + BORDER
        canvas[inner_y:inner_y + TILE[1], inner_x:inner_x + TILE[0]] = tile(q_paths[queries[k]])
        ax = inner_x + TILE[0] + GAP
        canvas[inner_y:inner_y + TILE[1], ax:ax + TILE[0]] = tile(db_paths[best[k]])
        cv2.putText(canvas, f"q {queries[k]} -> {best[k]}  conf {confidence[k]:.3f}",
                    (x + 2, y + TILE[1] + 2 * BORDER + CAPTION - 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (0, 0, 0), 1, cv2.LINE_AA)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), canvas):
        raise OSError(f"cannot write {out}")
    return out
