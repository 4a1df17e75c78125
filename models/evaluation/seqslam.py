"""Sequence matching over a difference matrix: the SeqSLAM filter and the OpenSeqSLAM reference.

docs/design/science.md §10.1 (Milford & Wyeth, ICRA 2012, with the parameters of Sünderhauf's OpenSeqSLAM
release), written from that description:

- local contrast enhancement of each database row over a window of database rows, per query column;
- straight paths of `ds` query steps **centred on the query** at velocities of 0.8-1.2 database steps per
  query step; a path is the sum of the enhanced differences it crosses; the match for a query is the
  start row of its best path plus ds // 2;
- **only full paths compete**: a path that would start before the first or run past the last database
  row, or a query without `ds` query steps around it, gets no score (infinite difference). Scoring a
  shorter path by its mean favours rows near the ends of the database, where fewer and noisier terms are
  averaged (issue 12: 28.5 % of the queries of one window put their best row among the first 13 rows).

`seqslam` is this matcher on any single-image similarity (cosine, sLSBH or winner-cell Dice: the `-seq`
methods of models.evaluation.sequences); `openseqslam` adds the reference's own front end (grey 64x32
frames, 8x8 patch normalisation, mean absolute difference) and its match score, the best path over the
best path outside a window of rows around it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

DS = 10  # query steps in a path (OpenSeqSLAM's ds)
V_MIN, V_MAX = 0.8, 1.2  # database steps per query step
CONTRAST_WINDOW = 10  # database rows of the local contrast enhancement
EXCLUSION_WINDOW = 10  # rows around the best match left out of the second best (match score)
FRAME_SIZE = (64, 32)  # (width, height) of OpenSeqSLAM's grey frames
PATCH = 8  # side of the normalised patches


def velocities(ds: int = DS, v_min: float = V_MIN, v_max: float = V_MAX) -> np.ndarray:
    """Path slopes: every whole number of database steps from v_min·ds to v_max·ds, over ds query steps.

    ds = 10 gives 0.8, 0.9, 1.0, 1.1, 1.2; ds = 20 gives nine slopes 0.05 apart (OpenSeqSLAM's moves).
    """
    if ds < 1:
        raise ValueError(f"ds must be >= 1, got {ds}")
    if not 0 < v_min <= v_max:
        raise ValueError(f"need 0 < v_min <= v_max, got {v_min}, {v_max}")
    moves = np.arange(round(v_min * ds), round(v_max * ds) + 1)
    return moves / ds


def full_window(n_q: int, ds: int = DS) -> np.ndarray:
    """(n_q,) bool: queries with ds query steps centred on them (j - ds//2 .. j - ds//2 + ds - 1)."""
    j = np.arange(n_q)
    a = ds // 2
    return (j - a >= 0) & (j - a + ds <= n_q)


def contrast_normalise(D: np.ndarray, radius: int = CONTRAST_WINDOW // 2) -> np.ndarray:
    """Local contrast enhancement of a difference matrix along the database axis.

    Args:
        D: (n_db, n_q) differences, lower = more similar.
        radius: half-width of the database window (rows i - radius .. i + radius, clipped at the ends)
            used for the local mean and std; OpenSeqSLAM's window of 10 rows is radius 5.

    Returns:
        (n_db, n_q) float64: (D - local mean) / local std, per query column.
    """
    D = np.asarray(D, dtype=np.float64)
    n = D.shape[0]
    # Cumulative sums give every window's mean and variance in O(n_db * n_q).
    c1 = np.vstack([np.zeros((1, D.shape[1])), np.cumsum(D, axis=0)])
    c2 = np.vstack([np.zeros((1, D.shape[1])), np.cumsum(D * D, axis=0)])
    lo = np.clip(np.arange(n) - radius, 0, n)
    hi = np.clip(np.arange(n) + radius + 1, 0, n)
    count = (hi - lo)[:, None]
    mean = (c1[hi] - c1[lo]) / count
    var = np.maximum((c2[hi] - c2[lo]) / count - mean * mean, 0.0)
    return (D - mean) / (np.sqrt(var) + 1e-9)


def path_sums(D: np.ndarray, ds: int = DS, slopes: Sequence[float] | None = None,
              crossing: bool = False) -> np.ndarray:
    """Best straight-path sum of D for every (database row, query), full paths only.

    A path starts at database row s and query j - ds//2 and takes ds query steps; at slope v its k-th
    step is on row s + floor(v·k). OpenSeqSLAM scores it at row i = s + ds//2 (its match is "the start
    row plus ds/2"); with `crossing` at i = s + floor(v·ds//2), the row where the path crosses query j.
    The two differ by a row at slopes other than 1. The best over `slopes` is kept.

    Args:
        D: (n_db, n_q) differences, lower = more similar (finite).
        ds: query steps per path.
        slopes: database steps per query step (default `velocities(ds)`).
        crossing: score a path at the row where it crosses the query (default: OpenSeqSLAM's row).

    Returns:
        (n_db, n_q) float64 path sums; +inf where no full path exists: the query lacks a full window
        (`full_window`), or every slope's path would start before row 0 or run past the last row.
    """
    D = np.asarray(D, dtype=np.float64)
    if D.ndim != 2:
        raise ValueError(f"D must be 2-D, got shape {D.shape}")
    if not np.all(np.isfinite(D)):
        raise ValueError("D contains NaN or infinite values")
    n_db, n_q = D.shape
    slopes = velocities(ds) if slopes is None else np.asarray(slopes, dtype=np.float64)
    a = ds // 2
    out = np.full((n_db, n_q), np.inf)
    cols = np.flatnonzero(full_window(n_q, ds))
    if cols.size == 0:
        return out
    c0, nc = cols[0] - a, cols.size  # first query step of the first full window
    for v in slopes:
        # The tiny epsilon keeps floor(1.1 * 10) at 11 despite binary rounding.
        offsets = np.floor(v * np.arange(ds) + 1e-9).astype(np.int64)
        n_starts = n_db - int(offsets[-1])  # start rows whose path ends on a database row
        if n_starts <= 0:
            continue
        total = np.zeros((n_starts, nc))
        for k, o in enumerate(offsets):
            # Rows o .. o + n_starts - 1 of query step c0 + k ..: one slice per step, no gather.
            total += D[o:o + n_starts, c0 + k:c0 + k + nc]
        rows = np.arange(n_starts) + (offsets[a] if crossing else a)
        keep = rows < n_db
        target = out[rows[keep][:, None], cols[None, :]]
        out[rows[keep][:, None], cols[None, :]] = np.minimum(target, total[keep])
    return out


def seqslam(S: np.ndarray, ds: int = DS, slopes: Sequence[float] | None = None,
            radius: int = CONTRAST_WINDOW // 2, crossing: bool = False) -> np.ndarray:
    """Sequence-filtered similarity: the OpenSeqSLAM matcher on a single-image similarity.

    Args:
        S: (n_db, n_q) pairwise similarity, higher = more similar (cosine of features, Dice of codes).
        ds: query steps per path, centred on the query.
        slopes: database steps per query step (default `velocities(ds)`).
        radius: contrast-enhancement half-window (database rows).
        crossing: see `path_sums` (default: OpenSeqSLAM's row, so X-seq and openseqslam match alike).

    Returns:
        (n_db, n_q) similarity, higher = more similar: minus the mean contrast-enhanced difference along
        the best full path; -inf where no full path exists (see `path_sums`), so a shorter path never
        competes. Score only the columns of `full_window(n_q, ds)`.
    """
    Dn = contrast_normalise(-np.asarray(S, dtype=np.float64), radius)
    return -path_sums(Dn, ds, slopes, crossing) / ds


def with_ablations(methods: Sequence[str], table: Mapping[str, Sequence[str]]) -> list[str]:
    """`methods` with each method's ablations (`table[method]`) added before it, in order, once each.

    The memory's contribution is only visible beside the same matcher on the codes it is fed (and on the
    features): evaluations add these whether or not they were asked for (docs/design/science.md §10.1).
    """
    out: list[str] = []
    for m in methods:
        for extra in (*table.get(m, ()), m):
            if extra not in out:
                out.append(extra)
    return out


# ---------------------------------------------------------------------------------------------------
# OpenSeqSLAM's own front end and match score


def patch_normalise(frames: np.ndarray, patch: int = PATCH) -> np.ndarray:
    """Each patch x patch block of each frame to zero mean and unit std (flat blocks become 0), rounded.

    OpenSeqSLAM stores the result as an 8-bit image, 127 + round(value): the constant drops out of every
    difference and is left out, the rounding is kept. It matters: on nordland_tiny_64x32 files 1589-1788
    (ds 10) R@1 is 0.801 with it and 0.859 without, against 0.821 measured with the release (issue 12).

    Args:
        frames: (N, H, W) grey frames, H and W multiples of `patch`.

    Returns:
        (N, H * W) float32 whole numbers, the normalised frames flattened row-major.
    """
    f = np.asarray(frames, dtype=np.float64)
    n, h, w = f.shape
    if h % patch or w % patch:
        raise ValueError(f"frame size {w}x{h} is not a multiple of the {patch}-pixel patch")
    blocks = f.reshape(n, h // patch, patch, w // patch, patch)
    mean = blocks.mean(axis=(2, 4), keepdims=True)
    std = blocks.std(axis=(2, 4), keepdims=True)
    out = np.where(std > 0, (blocks - mean) / np.where(std > 0, std, 1.0), 0.0)
    return np.round(out).reshape(n, h * w).astype(np.float32)


def load_frames(paths: Sequence[Path], size: tuple[int, int] = FRAME_SIZE, patch: int = PATCH) -> np.ndarray:
    """(N, H * W) float32 patch-normalised grey frames of `paths`, resized to `size` = (W, H)."""
    import cv2  # only the pixel front end needs it

    out = []
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"cannot read image {p}")
        if (img.shape[1], img.shape[0]) != size:
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        out.append(img)
    return patch_normalise(np.stack(out), patch)


def mean_abs_difference(db: np.ndarray, q: np.ndarray, chunk: int = 16) -> np.ndarray:
    """(n_db, n_q) float64 mean absolute difference of flattened frames db (n_db, P) and q (n_q, P).

    Computed `chunk` queries at a time so that the broadcast stays near n_db * chunk * P floats.
    """
    db = np.asarray(db, dtype=np.float32)
    q = np.asarray(q, dtype=np.float32)
    out = np.empty((db.shape[0], q.shape[0]), dtype=np.float64)
    for j in range(0, q.shape[0], chunk):
        out[:, j:j + chunk] = np.abs(db[:, None, :] - q[None, j:j + chunk, :]).mean(axis=2)
    return out


class Matches(NamedTuple):
    """OpenSeqSLAM's answer for every query (n_q queries, n_db database rows).

    Attributes:
        S: (n_db, n_q) minus the best path sum at each row (higher = more similar; -inf: no full path).
        best: (n_q,) int64 matched database row (-1 where the query has no full window).
        ratio: (n_q,) float64 best path sum / best sum outside the exclusion window (lower = stronger;
            nan where the query has no full window).
        confidence: (n_q,) 1 - ratio, monotone in the match score, higher = more confident.
    """

    S: np.ndarray
    best: np.ndarray
    ratio: np.ndarray
    confidence: np.ndarray


def match(D: np.ndarray, ds: int = DS, slopes: Sequence[float] | None = None,
          radius: int = CONTRAST_WINDOW // 2, exclusion: int = EXCLUSION_WINDOW,
          crossing: bool = False) -> Matches:
    """OpenSeqSLAM's matching on a difference matrix D (n_db, n_q), lower = more similar.

    Contrast enhancement, then the global minimum is moved to 0 so that every path sum is >= 0 and the
    ratio of two sums is a score in [0, 1]; the minimum over paths is unchanged by it.
    """
    Dn = contrast_normalise(D, radius)
    sums = path_sums(Dn - Dn.min(), ds, slopes, crossing)
    n_db, n_q = sums.shape
    best = np.full(n_q, -1, dtype=np.int64)
    ratio = np.full(n_q, np.nan)
    cols = np.flatnonzero(np.isfinite(sums).any(axis=0))
    if cols.size:
        b = np.argmin(sums[:, cols], axis=0)  # ties: the lower row
        rows = np.arange(n_db)[:, None]
        outside = np.where(np.abs(rows - b[None, :]) > exclusion // 2, sums[:, cols], np.inf)
        first, second = sums[b, cols], outside.min(axis=0)
        # No second path at all (a database barely longer than a path): as strong as a match gets.
        r = np.where(np.isfinite(second) & (second > 0), first / np.where(second > 0, second, 1.0), 0.0)
        best[cols], ratio[cols] = b, r
    return Matches(S=-sums, best=best, ratio=ratio, confidence=1.0 - ratio)


def openseqslam(db_frames: np.ndarray, q_frames: np.ndarray, ds: int = DS,
                slopes: Sequence[float] | None = None, crossing: bool = False) -> Matches:
    """The reference on patch-normalised frames (`load_frames`): (n_db, P) database, (n_q, P) query."""
    return match(mean_abs_difference(db_frames, q_frames), ds, slopes, crossing=crossing)
