"""The online-X evaluation methods: the causal localiser on a method's similarity (science.md §11.4)."""

from __future__ import annotations

import numpy as np

from models.evaluation import metrics, online, sequences


def noisy_route(n: int = 80, d: int = 64, noise: float = 3.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    db = rng.normal(size=(n, d))
    q = db + rng.normal(0, noise, size=(n, d))  # single frames are weak
    return [(x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32) for x in (db, q)]


def test_online_methods_beat_single_frames_and_follow_a_reversed_route() -> None:
    db, q = noisy_route()
    for reverse in (False, True):
        res = sequences.image_experiment(db, q, methods=["cosine", "online-htm"], preset="cortexloc-grid",
                                         k=64, s=0.1, seeds=1, reverse_query=reverse)["methods"]
        assert set(res) == {"cosine", "online-cosine", "online-slsbh", "online-htm"}
        assert res["online-cosine"]["recall_at_1_mean"] > res["cosine"]["recall_at_1_mean"] + 0.2
        assert res["online-cosine"]["recall_at_1_mean"] > 0.8
    seq_rev = sequences.image_experiment(db, q, methods=["cosine-seq"], preset="cortexloc-grid", seeds=1,
                                         reverse_query=True)["methods"]["cosine-seq"]
    assert seq_rev["recall_at_1_mean"] < 0.2  # the straight-path matcher assumes the stored direction


def test_localise_answers_causally_with_warm_up() -> None:
    db, q = noisy_route(n=40, noise=0.5)
    S = db @ q.T
    found = online.localise(S, {"warmup": 3})
    assert found.best[:2].tolist() == [-1, -1] and np.all(found.best[2:] >= 0)
    assert found.S.shape == S.shape and np.isfinite(found.S[:, 5]).sum() <= 256
    cut = online.localise(S[:, :20], {"warmup": 3})
    np.testing.assert_array_equal(cut.best, found.best[:20])


def test_no_answer_counts_as_wrong() -> None:
    gt = np.eye(3, dtype=bool)
    q = metrics.query_metrics(np.eye(3), gt, confidence=np.array([0.0, 1.0, 1.0]), best=np.array([-1, 1, 2]))
    assert q["correct"].tolist() == [False, True, True] and q["recall_at_1"] == 2 / 3
