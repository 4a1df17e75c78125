"""SeqSLAM-style filter: contrast normalisation and straight-line path scoring."""

from __future__ import annotations

import numpy as np

from models.evaluation import metrics
from models.evaluation.seqslam import contrast_normalise, seqslam


def test_contrast_normalisation_gives_zero_mean_unit_spread_locally():
    D = np.random.default_rng(0).normal(5.0, 3.0, (300, 4))
    Dn = contrast_normalise(D, radius=50)
    assert abs(Dn[100:200].mean()) < 0.2
    assert 0.8 < Dn[100:200].std() < 1.2


def test_sequence_filter_recovers_a_weak_diagonal():
    rng = np.random.default_rng(1)
    n = 150
    S = rng.normal(0, 1, (n, n))
    S[np.arange(n), np.arange(n)] += 1.0  # each single match is barely above the noise
    gt = np.eye(n, dtype=bool)
    single = metrics.auc(*metrics.pr_curve(S, gt))
    filtered = seqslam(S, window=10)
    assert filtered.shape == S.shape
    assert metrics.auc(*metrics.pr_curve(filtered, gt)) > 3 * single
    assert metrics.recall_at_k(filtered, gt, 1) > metrics.recall_at_k(S, gt, 1)


def test_paths_follow_other_velocities():
    n = 120
    S = np.zeros((n, n))
    j = np.arange(n)
    i = np.minimum((j * 1.25).astype(int), n - 1)  # the robot is 25 % faster in the database
    S[i, j] = 1.0
    F = seqslam(S, window=8, velocities=(1.0, 1.25))
    hits = (F.argmax(axis=0) == i)[20:100]
    assert hits.mean() > 0.9
