"""Loop closure while mapping: one learning stream that must know when it is back (docs/design/science.md
§11.6, docs/results.md §10).

A route is a run of frames driven as ONE stream; each frame has a place label (Nordland: its file
index; the grid world: its cell). Frame i is a true revisit when an earlier frame j shows its place
(|label_j − label_i| <= tolerance) and the run went somewhere else in between (a frame k, j < k < i,
more than `away` labels from it): standing still or creeping along is not a revisit, a lap of any
length is. `score` reads a method's online answers (answer frame, confidence; -1 = none) against that
truth; `openseqslam_online` is the standard online SeqSLAM loop-closure detector beside it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from models.evaluation import metrics, seqslam
from models.localisation.localiser import reaches

__all__ = ["AWAY", "RECENT", "openseqslam_online", "revisit_truth", "score"]

#: Labels (Nordland files, about 10 s of travel each) a frame between must be from a place for the run
#: to have left it: the localiser's rival window, `exclusion` (docs/design/science.md §11.3).
AWAY = 10
#: Frames before the query OpenSeqSLAM's online detector leaves out (its own recent trail): twice its
#: path length, so no path it scores overlaps the frames it is matching.
RECENT = 2 * seqslam.DS


def revisit_truth(labels: np.ndarray, tolerance: int, away: int = AWAY) -> np.ndarray:
    """(T,) bool: frame i is a true revisit (module docstring). O(T²) over a route of T frames.

    Args:
        labels: (T,) int place labels in driven order. tolerance: labels within it are one place.
        away: how far (in labels) a frame between must be for the run to have left the place.
    """
    lab = np.asarray(labels, np.int64)
    out = np.zeros(lab.size, bool)
    for i in range(1, lab.size):
        same = np.abs(lab[:i] - lab[i]) <= tolerance
        far = np.abs(lab[:i] - lab[i]) > away
        # the last frame far from place i; a frame of place i before it was left since
        last_far = np.flatnonzero(far)
        out[i] = bool(last_far.size and same[:last_far[-1]].any())
    return out


def localise_truth(labels: np.ndarray, laps: np.ndarray, tolerance: int) -> np.ndarray:
    """(T,) bool: frames of laps >= 1 whose place lap 0 stored. A localising stream is another robot on
    the learned map: every such frame is at a stored place, "left" or not (the turn of an excursion)."""
    lab, laps = np.asarray(labels, np.int64), np.asarray(laps, np.int64)
    first = lab[laps == 0]
    return (laps >= 1) & (np.abs(lab[:, None] - first[None, :]) <= tolerance).any(axis=1)


def score(best: np.ndarray, confidence: np.ndarray, labels: np.ndarray, threshold: float,
          tolerance: int, laps: np.ndarray | None = None, also_true: np.ndarray | None = None
          ) -> dict[str, Any]:
    """One method's revisit decisions on a route, per query.

    Args:
        best: (T,) the frame each answer names (-1: no answer); confidence: (T,) its confidence.
        labels: (T,) place labels; threshold: confidence at which an answer is a revisit.
        tolerance: labels within it are one place. laps: (T,) int lap of each frame (default all 0).
        also_true: (T,) bool frames where a right answer is no false revisit though the route's truth
            counts none (a localising stream's `localise_truth`); "recall" and "recall_at_1" stay over the
            route's truth, so methods are compared on the same frames; the PR curve (query AUC, R@100P)
            is over both.

    Returns:
        {"false_revisits" (revisits called on frames that are no true revisit, whatever the lap),
        "lap": {lap: {"frames", "revisits_true" (true revisits), "revisits_called", "precision",
        "recall" (right revisits / true revisits), "right_called" (right revisits / right answers),
        "recall_at_1" (right answers / true revisits), "query_auc", "recall_at_100p"}}}.
    """
    best, conf = np.asarray(best, np.int64), np.asarray(confidence, np.float64)
    lab = np.asarray(labels, np.int64)
    laps = np.zeros(lab.size, np.int64) if laps is None else np.asarray(laps, np.int64)
    truth = revisit_truth(lab, tolerance)
    named = (best >= 0) & (np.abs(lab[np.maximum(best, 0)] - lab) <= tolerance)
    right = truth & named
    either = truth | (np.zeros(lab.size, bool) if also_true is None else np.asarray(also_true, bool))
    fine = either & named
    called = (best >= 0) & reaches(conf, threshold)
    out: dict[str, Any] = {"false_revisits": int((called & ~fine).sum()), "lap": {}}
    for lap in np.unique(laps):
        m = laps == lap
        n_true, n_called, n_right = int(truth[m].sum()), int(called[m].sum()), int(right[m].sum())
        hit = int((called & right)[m].sum())
        ok = int((called & fine)[m].sum())
        entry = {"frames": int(m.sum()), "revisits_true": n_true, "revisits_called": n_called,
                 "false_revisits": n_called - ok,
                 "precision": ok / n_called if n_called else None,
                 "recall": hit / n_true if n_true else None,
                 "right_called": hit / n_right if n_right else None,
                 "recall_at_1": n_right / n_true if n_true else None}
        if n_true:
            P, R = metrics.query_pr_curve(np.where(best[m] >= 0, conf[m], 0.0), fine[m], either[m])
            entry.update(query_auc=metrics.auc(P, R), recall_at_100p=metrics.recall_at_100_precision(P, R))
        out["lap"][int(lap)] = entry
    return out


def openseqslam_online(D: np.ndarray, ds: int = seqslam.DS, recent: int = RECENT,
                       exclusion: int = seqslam.EXCLUSION_WINDOW) -> tuple[np.ndarray, np.ndarray]:
    """OpenSeqSLAM as an online loop-closure detector (the standard use): frame i against every earlier
    frame of the run but its `recent` last ones, on the path of its own last `ds` frames.

    The reference's contrast enhancement (along the earlier frames, per frame) and straight paths at its
    velocities, but ending at frame i (it cannot see the future); the match is the row the best path ends
    on, its score 1 − best / best outside `exclusion` rows around it (OpenSeqSLAM's ratio).

    Args:
        D: (T, T) differences of the run's frames (OpenSeqSLAM's patch-normalised mean absolute
            difference), lower = more similar; only D[j, i] with j < i − recent is read for frame i.

    Returns:
        (best, confidence), each (T,): the answered frame (-1 until a full path exists) and 1 − ratio.
    """
    Dn = seqslam.contrast_normalise(np.asarray(D, np.float64))
    T = Dn.shape[0]
    best, conf = np.full(T, -1, np.int64), np.zeros(T)
    steps = [np.floor(v * np.arange(ds) + 1e-9).astype(np.int64) for v in seqslam.velocities(ds)]
    for i in range(ds - 1, T):
        n = i - recent  # rows 0 .. n-1 are candidates
        sums = np.full(max(n, 0), np.inf)
        for off in steps:
            if n - 1 - off[-1] < 0:
                continue
            # path ending on row r at frame i: row r - off[k] at frame i - k
            ends = np.arange(off[-1], n)
            total = np.zeros(ends.size)
            for k, o in enumerate(off):
                total += Dn[ends - o, i - k]
            sums[ends] = np.minimum(sums[ends], total)
        if not np.isfinite(sums).any():
            continue
        sums = sums - min(Dn.min() * ds, sums[np.isfinite(sums)].min())  # >= 0, as the reference's
        b = int(np.argmin(sums))
        rows = np.arange(sums.size)
        outside = sums[np.abs(rows - b) > exclusion // 2]
        second = outside.min() if outside.size else np.inf
        best[i] = b
        conf[i] = 1.0 - (sums[b] / second if np.isfinite(second) and second > 0 else 0.0)
    return best, conf
