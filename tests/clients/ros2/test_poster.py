"""The node's poster without ROS (cortexloc_ros.poster): what diagnostics say of the service while it is
slow, down and back, driven through a scripted client (no server)."""

from __future__ import annotations

import threading
import time
from typing import Any

import httpx
import numpy as np
import pytest

pytest.importorskip("cortexloc_ros.poster", reason="the ROS 2 node is not installed (make install-ros)")

from cortexloc_ros import poster
from cortexloc_ros.core import FrameQueue, OdometryBuffer, Pose2D, Stamp
from cortexloc_ros.params import PARAMETERS, read_config
from cortexloc_ros.poster import Frame, Poster, Stats

from cortexloc_client import Observation

ANSWER = Observation.model_validate({
    "map_id": "m", "stream": "s", "learned": True, "seq": 1, "sequence": {
        "step": 1, "active_columns": 1, "predicted_columns": 0, "bursting_columns": 1, "winner_cells": 1},
    "matches": [], "timings_ms": {},
    "versions": {"api": "v1", "code": "x", "encoder": "e", "weights": "w", "projection": "p", "map_seq": 1}})


class ScriptedClient:
    """Raises or answers from a list, one per post or probe; records what diagnostics said at each call."""

    def __init__(self, stats: Stats, *outcomes: Exception | Observation) -> None:
        self.stats, self.outcomes = stats, list(outcomes)
        self.seen: list[tuple[str, str]] = []
        self.metadata: list[dict[str, Any]] = []

    def _next(self) -> Any:
        self.seen.append((self.stats.service, self.stats.last_error))
        outcome = self.outcomes.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    def observe(self, *args: Any, **kwargs: Any) -> Observation:
        self.metadata.append(kwargs["metadata"])
        return self._next()

    def ready(self) -> None:
        self._next()


class Log:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def info(self, text: str) -> None:
        self.lines.append(text)

    warning = error = info


def _poster(monkeypatch: pytest.MonkeyPatch, *outcomes: Exception | Observation,
            odometry: OdometryBuffer | None = None) -> tuple[Poster, Stats, ScriptedClient]:
    monkeypatch.setattr(poster, "BACKOFF_S", 0.001)  # the retries' waits, not what is tested
    cfg = read_config({name: default for name, (default, _) in PARAMETERS.items()})
    stats = Stats()
    client = ScriptedClient(stats, *outcomes)
    p = Poster(cfg, client, FrameQueue(2), stats, odometry, lambda: None,  # type: ignore[arg-type]
               lambda *a: None, Log())
    return p, stats, client


def _frame(stamp: Stamp | None = None) -> Frame:
    return Frame(stamp or Stamp(1), "cam", np.zeros((4, 4, 3), np.uint8), "rgb8", "run1:.cam:1:1",
                 time.monotonic())


def test_a_slow_service_is_slow_not_down_and_its_error_is_cleared_when_it_answers(monkeypatch):
    request = httpx.Request("POST", "http://cortexloc.test/v1/maps/m/observations")
    p, stats, client = _poster(monkeypatch, httpx.ReadTimeout("timed out", request=request),
                               httpx.ConnectError("refused", request=request), ANSWER)
    p._post(_frame())
    (before, slow, down) = client.seen
    assert before == ("unknown", "")
    assert slow[0] == "slow" and slow[1] == "ReadTimeout: no reply within request_timeout (10 s)"
    said = Stats(service=slow[0], last_error=slow[1])
    assert said.health(0) == ("WARN", "service slow: ReadTimeout: no reply within request_timeout (10 s)")
    assert down == ("down", "ConnectError: refused")
    # answered again: up, and no error left over from the outage beside it
    assert (stats.service, stats.last_error, stats.answered, stats.retries) == ("up", "", 1, 2)
    with stats.lock:
        assert stats.health(0) == ("OK", "service up")


def test_a_refused_frames_error_is_cleared_by_the_next_answer(monkeypatch):
    from cortexloc_client import CortexlocError

    p, stats, _ = _poster(monkeypatch, CortexlocError(422, detail="a degenerate image"), ANSWER)
    p._post(_frame())
    with stats.lock:
        assert (stats.refused, stats.last_error) == (1, "422 error: a degenerate image")
    p._post(_frame(Stamp(2)))
    with stats.lock:  # the service answers again: no refusal's text left beside "service up"
        assert (stats.answered, stats.last_error, stats.service) == (1, "", "up")


def test_the_idle_probe_reports_slow_down_and_recovery_alike(monkeypatch):
    request = httpx.Request("GET", "http://cortexloc.test/readyz")
    p, stats, _ = _poster(monkeypatch, httpx.ConnectError("refused", request=request),
                          httpx.ReadTimeout("timed out", request=request), None)  # type: ignore[arg-type]
    p._probe()
    with stats.lock:
        assert stats.health(0) == ("ERROR", "service down: ConnectError: refused")
    p._probe()
    assert (stats.service, stats.last_error.split(":")[0]) == ("slow", "ReadTimeout")
    p._probe()
    assert (stats.service, stats.last_error) == ("up", "")


def test_a_frame_waits_for_the_odometry_of_its_instant_and_takes_the_nearest(monkeypatch):
    # odometry 40 ms before the frame is in (within the 50 ms tolerance); the sample 10 ms after the
    # frame, the nearest, comes 30 ms after the frame did: the frame is posted with it
    odometry = OdometryBuffer(tolerance_ns=50_000_000)
    stamp = Stamp(10_000_000_000)
    odometry.add(Stamp(stamp.ns - 40_000_000), Pose2D(1.0, 0.0, 0.0, "odom"))
    p, stats, client = _poster(monkeypatch, ANSWER, ANSWER, odometry=odometry)
    threading.Timer(0.03, odometry.add, (Stamp(stamp.ns + 10_000_000), Pose2D(2.0, 0.0, 0.0, "odom"))).start()
    p._post(_frame(stamp))
    assert client.metadata[0]["pose"]["x"] == 2.0
    # no odometry after the stamp ever comes: the wait is bounded (odom_tolerance + the margin after the
    # frame arrived), then the nearest in is taken
    later = Stamp(stamp.ns + 45_000_000)
    t0 = time.monotonic()
    p._post(_frame(later))
    waited = time.monotonic() - t0
    assert client.metadata[1]["pose"]["x"] == 2.0 and stats.no_pose == 0
    assert waited < 5 * (0.05 + poster.ODOM_MARGIN_S)  # a bound on the wait, loose for a loaded machine
