"""Scoring many passes of one route (docs/results.md §11): a pass's revisit decisions against its
labels, and a short printed line per result."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.localisation.localiser import reaches

__all__ = ["Pass", "localise_score", "summary_row"]


@dataclass
class Pass:
    """One driven pass.

    Attributes:
        best: (T,) the label of the row each frame's `place` named (-1: no answer).
        confidence: (T,) its confidence. labels: (T,) the frames' own labels.
        rows: rows the pass made (learning). visits: frames consolidated into stored rows.
    """

    best: np.ndarray
    confidence: np.ndarray
    labels: np.ndarray
    rows: int
    visits: int = 0


def localise_score(p: Pass, threshold: float, tolerance: int) -> dict[str, Any]:
    """Revisits called (confidence >= threshold), right ones (the named row within `tolerance` labels),
    precision, recall over the pass's frames (every frame of a repeated route is a revisit), rows and
    visits of the pass."""
    answered = p.best >= 0
    right = answered & (np.abs(p.best - p.labels) <= tolerance)
    called = answered & reaches(p.confidence, threshold)
    hit = int((called & right).sum())
    n = int(called.sum())
    return {"frames": int(p.labels.size), "revisits": n, "right_revisits": hit,
            "precision": hit / n if n else None, "recall": hit / p.labels.size,
            "r_at_1": float(right.mean()), "pass_rows": p.rows, "pass_visits": p.visits,
            "rows_per_frame": p.rows / p.labels.size}


def summary_row(r: dict[str, Any]) -> str:
    return " ".join(f"{k}={round(v, 3) if isinstance(v, float) else v}" for k, v in r.items())
