"""Scoring loop closure while mapping (models/evaluation/slam.py): what counts as a revisit, per lap, and
OpenSeqSLAM as an online detector."""

from __future__ import annotations

import numpy as np

from models.evaluation import slam


def test_a_revisit_needs_the_run_to_have_left_the_place():
    stop = np.r_[np.arange(20), np.full(30, 19)]
    assert not slam.revisit_truth(stop, 1).any()  # standing still, however long
    lap = np.r_[np.arange(30), np.arange(30)]
    truth = slam.revisit_truth(lap, 1)
    assert not truth[:30].any() and truth[30:].all()
    back = np.r_[np.arange(30), np.arange(29, -1, -1)]  # out and back: near the turn it has not left
    t = slam.revisit_truth(back, 0)
    assert not t[30:36].any() and t[50:].all()


def test_one_pass_has_no_true_revisit_at_any_frame_rate_and_a_loop_needs_the_run_to_go_away():
    """The truth is defined on the route (issue 35): a frame is a true revisit only after the route went
    more than `AWAY` labels away and came back, whatever the frame rate; a loop shorter than that is no
    revisit (the service's short-term memory, docs/design/science.md §11.6, does not close it)."""
    for rate in (1, 3, 10):
        one_pass = np.repeat(np.arange(200), rate)  # each place posted `rate` times
        assert not slam.revisit_truth(one_pass, 1).any()
        lap = np.repeat(np.arange(40), rate)
        assert slam.revisit_truth(np.r_[lap, lap], 1)[lap.size:].all()
    short = np.arange(slam.AWAY + 1)  # back at the start having gone AWAY labels away: not yet gone
    assert not slam.revisit_truth(np.r_[short, short], 1).any()


def test_score_counts_false_revisits_per_lap_and_recall_of_true_ones():
    n = 40  # long enough that every lap-2 frame was left (AWAY labels) before it comes back
    labels, laps = np.r_[np.arange(n), np.arange(n)], np.r_[np.zeros(n, int), np.ones(n, int)]
    best = np.r_[np.full(n, -1), np.arange(n)]
    best[3], best[n + 25] = 0, 7  # a lap-1 answer and a wrong lap-2 one
    conf = np.r_[np.zeros(n), np.full(n, 0.95)]
    conf[3] = 0.99
    s = slam.score(best, conf, labels, 0.9, 1, laps)
    assert s["false_revisits"] == 2 and s["lap"][0]["false_revisits"] == 1
    lap2 = s["lap"][1]
    assert lap2["revisits_true"] == n and lap2["revisits_called"] == n
    assert lap2["precision"] == lap2["recall"] == lap2["recall_at_1"] == (n - 1) / n
    assert lap2["right_called"] == 1.0


def test_a_localising_robot_at_a_stored_place_near_the_turn_is_no_false_revisit():
    """Out and back: the learning stream has not left the places near the turn, but a localising stream is
    another robot, and a right answer there is no false revisit; recall is still over the route's truth."""
    out, back = np.arange(30), np.arange(29, -1, -1)
    labels, laps = np.r_[out, back], np.r_[np.zeros(30, int), np.ones(30, int)]
    best = np.r_[np.full(30, -1), back]  # every lap-2 answer right
    conf = np.r_[np.zeros(30), np.full(30, 0.95)]
    extra = slam.localise_truth(labels, laps, 0)
    assert not extra[:30].any() and extra[30:].all()
    plain = slam.score(best, conf, labels, 0.9, 0, laps)
    local = slam.score(best, conf, labels, 0.9, 0, laps, extra)
    near_turn = int((~slam.revisit_truth(labels, 0))[30:].sum())
    assert near_turn > 0 and plain["lap"][1]["false_revisits"] == near_turn
    assert local["false_revisits"] == 0 and local["lap"][1]["precision"] == 1.0
    assert local["lap"][1]["recall"] == plain["lap"][1]["recall"] == 1.0
    assert local["lap"][1]["recall_at_100p"] == 1.0 > plain["lap"][1]["recall_at_100p"]


def test_openseqslam_online_is_causal_and_finds_a_repeated_lap():
    rng = np.random.default_rng(0)
    frames = rng.random((60, 32))
    run = np.r_[frames, frames + rng.normal(0, 0.01, frames.shape)]
    D = np.abs(run[:, None, :] - run[None, :, :]).mean(axis=2)
    best, _ = slam.openseqslam_online(D)
    assert np.all(best[:slam.RECENT] == -1)  # no full path over frames old enough yet
    assert np.mean(best[70:] == np.arange(70, 120) - 60) > 0.95
    later = D.copy()
    noise = rng.random((20, 120))
    later[100:, :] = noise
    later[:, 100:] = noise.T
    again, _ = slam.openseqslam_online(later)
    np.testing.assert_array_equal(again[:100], best[:100])  # frames after i change no answer before i
