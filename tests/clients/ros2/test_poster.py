"""The node's poster without ROS (cortexloc_ros.poster): what diagnostics say of the service while it is
slow, down and back, driven through a scripted client (no server)."""

from __future__ import annotations

import math
import threading
import time
from dataclasses import replace
from types import SimpleNamespace
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
from cortexloc_client.models import StreamReset

ANSWER = Observation.model_validate({
    "map_id": "m", "stream": "s", "learned": True, "seq": 1, "sequence": {
        "step": 1, "active_columns": 1, "predicted_columns": 0, "bursting_columns": 1, "winner_cells": 1},
    "matches": [], "timings_ms": {},
    "versions": {"api": "v1", "code": "x", "encoder": "e", "weights": "w", "projection": "p", "map_seq": 1}})
#: The map as `get_map` and `create_map` answer it, as far as the poster reads it.
MAP = SimpleNamespace(revisit_threshold=0.8)


class ScriptedClient:
    """Raises or answers from a list, one per post or probe; records what diagnostics said at each call."""

    def __init__(self, stats: Stats, *outcomes: Exception | Observation) -> None:
        self.stats, self.outcomes = stats, list(outcomes)
        self.seen: list[tuple[str, str]] = []
        self.metadata: list[dict[str, Any]] = []
        self.calls: list[tuple[str, ...]] = []  # the calls other than observe and ready

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

    def _call(self, name: str, *args: Any) -> Any:
        self.calls.append((name, *args))
        return self._next()

    def reset_stream(self, map_id: str, stream: str) -> Any:
        return self._call("reset_stream", map_id, stream)

    def get_map(self, map_id: str) -> Any:
        return self._call("get_map", map_id)

    def create_map(self, map_id: str) -> Any:
        return self._call("create_map", map_id)


class Log:
    def __init__(self) -> None:
        self.lines: list[str] = []
        self.errors: list[str] = []  # the lines said at ERROR (in `lines` too)

    def info(self, text: str) -> None:
        self.lines.append(text)

    warning = info

    def error(self, text: str) -> None:
        self.lines.append(text)
        self.errors.append(text)


def _poster(monkeypatch: pytest.MonkeyPatch, *outcomes: Any, odometry: OdometryBuffer | None = None,
            **params: Any) -> tuple[Poster, Stats, ScriptedClient]:
    """A poster of the default parameters (`params` over them; its stream is `cam`)."""
    monkeypatch.setattr(poster, "BACKOFF_S", 0.001)  # the retries' waits, not what is tested
    cfg = replace(read_config({**{name: default for name, (default, _) in PARAMETERS.items()}, **params}),
                  stream="cam")
    stats = Stats()
    client = ScriptedClient(stats, *outcomes)
    p = Poster(cfg, client, FrameQueue(2), stats, odometry, lambda: None,  # type: ignore[arg-type]
               lambda *a: None, Log())
    return p, stats, client


def _problem(status: int, slug: str) -> Exception:
    from cortexloc_client import CortexlocError
    from cortexloc_client.models import Problem

    return CortexlocError(status, Problem(type=f"urn:cortexloc:problem:{slug}", title=slug, status=status,
                                          detail=f"map 'default' {slug}"))


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


def test_a_start_resets_the_stream_before_the_first_frame_unless_it_resumes_a_run(monkeypatch):
    # A new start (no run_id) is a new drive: the service keeps a stream's context across the node's
    # restart, and without a reset a new drive's first frame continued the last one (an outside probe: a
    # row 30 frames away at confidence 0.96, published as a loop closure). The service down at start: the
    # reset is retried, and frames wait for it.
    # The map is read first: its revisit_threshold scales the markers' colours (node.py `_markers`).
    request = httpx.Request("GET", "http://cortexloc.test/v1/maps/default")
    p, stats, client = _poster(monkeypatch, httpx.ConnectError("refused", request=request), MAP,
                               StreamReset(stream="cam", had_context=True))
    p._first_contact()
    assert client.calls == [("get_map", "default")] * 2 + [("reset_stream", "default", "cam")]
    assert client.seen[1][0] == "down" and (stats.service, stats.retries) == ("up", 1)
    assert any("a new drive (the last drive's context dropped)" in line for line in p.log.lines)
    assert p.revisit_threshold == 0.8
    # the same run_id again resumes that drive: its context (and its frames' keys) kept, the map checked
    p, stats, client = _poster(monkeypatch, MAP, run_id="drive-a")
    p._first_contact()
    assert client.calls == [("get_map", "default")] and stats.service == "up" and p.revisit_threshold == 0.8
    # a learning node's missing map is created at first contact (a new map: nothing to reset)
    p, stats, client = _poster(monkeypatch, _problem(404, "map-not-found"), MAP)
    p._first_contact()
    assert client.calls == [("get_map", "default"), ("create_map", "default")] and p.revisit_threshold == 0.8


def test_a_map_deleted_while_the_node_learns_is_an_error_not_created_again(monkeypatch):
    # Created anew with the service's defaults, the map took the next frames under seqs 1, 2, 3 ... again:
    # a pose-graph back end got other frames under old seqs with no word. Now: ERROR, the frame waits.
    gone = _problem(404, "map-not-found")
    p, stats, client = _poster(monkeypatch, gone, gone, ANSWER)
    p._post(_frame())
    assert client.calls == []  # never created again
    assert client.seen[1] == ("error", "404 map-not-found: map 'default' map-not-found")
    assert Stats(service=client.seen[1][0], last_error=client.seen[1][1]).health(0)[0] == "ERROR"
    assert (stats.answered, stats.retries, stats.service, stats.last_error) == (1, 2, "up", "")
    assert sum("not created again" in line for line in p.log.lines) == 1  # said once, not per retry


def test_between_frames_the_poster_hands_on_the_streams_retractions_and_counts_them(monkeypatch):
    # A repair withdrew closure 2 while the node ran: the poster reads the log between frames (one page
    # each `retractions_poll`) and hands the retraction on for the topic; the frame is answered as ever.
    from cortexloc_client.models import LoopClosureList

    p, stats, client = _poster(monkeypatch, MAP, StreamReset(stream="cam", had_context=False), ANSWER,
                               retractions_poll=0.05)
    withdrawn = {"id": 6, "stream": "cam", "seq": 4,
                 "place": {"seq": 1, "observation_id": "o1", "stream": "cam"},
                 "confidence": 0.0, "support": 0, "created_at": "2026-11-29T00:00:00Z", "retracts": 2}
    pages = [LoopClosureList(loop_closures=[], newest=5, epoch="e"),
             LoopClosureList.model_validate({"loop_closures": [withdrawn], "newest": 6, "epoch": "e"})]
    reads: list[int] = []

    def loop_closures(map_id: str, *, after: int = 0, limit: int = 100) -> LoopClosureList:
        reads.append(after)
        return pages.pop(0) if pages else LoopClosureList(loop_closures=[], newest=6, epoch="e")

    client.loop_closures = loop_closures  # type: ignore[attr-defined]
    client.ready = lambda: None  # type: ignore[method-assign]  # the idle probe: up
    got: list = []
    p._on_retraction = got.append
    p.queue.put(_frame())
    p.start()
    deadline = time.monotonic() + 10
    while not got and time.monotonic() < deadline:
        time.sleep(0.01)
    p.stop()
    assert [e.retracts for e in got] == [2] and reads[:2] == [0, 5]
    with stats.lock:
        assert (stats.answered, stats.retractions) == (1, 1)


def _revisit(closure_id: int) -> Observation:
    return Observation.model_validate({
        **ANSWER.model_dump(), "loop_closure_id": closure_id,
        "place": {"seq": 3, "place_id": 3, "confidence": 0.95, "revisit": True, "support": 9}})


class StoreClient(ScriptedClient):
    """Answers each key once from the script and its repeats from a store, as the service does."""

    def __init__(self, stats: Stats, *outcomes: Any) -> None:
        super().__init__(stats, *outcomes)
        self.store: dict[str, Observation] = {}

    def observe(self, *args: Any, **kwargs: Any) -> Observation:
        key = kwargs["idempotency_key"]
        if key not in self.store:
            self.store[key] = super().observe(*args, **kwargs)
        return self.store[key]


def _published(p: Poster) -> list[tuple[int | None, bool]]:
    """What the node publishes for each answer: (its closure id, whether the closure is published). The
    closure flag of the version before (a memory of closure ids) is read when it is given."""
    out: list[tuple[int | None, bool]] = []
    p.on_answer = lambda frame, pose, answer, latency, *flag: out.append((answer.loop_closure_id, all(flag)))
    return out


def test_a_message_delivered_twice_publishes_its_closure_once_through_the_duplicate_check(monkeypatch):
    # A message delivered twice (a camera bridged twice) got the same key, and the service answered the second
    # from its store: its closure was published again under the same id. The duplicate check posts it once.
    from cortexloc_ros.core import FrameKeys

    p, stats, _ = _poster(monkeypatch)
    p.client = client = StoreClient(stats, _revisit(7), _revisit(8))
    published = _published(p)
    keys = FrameKeys("run1", "/cam")
    for ns, data in ((1, b"a"), (1, b"a"), (2, b"b"), (1, b"a")):
        got = keys.next(Stamp(ns), data)
        if not got.duplicate:
            p._post(replace(_frame(Stamp(ns)), key=got.key))
    assert published == [(7, True), (8, True)] and len(client.store) == 2
    assert (stats.answered, stats.revisits) == (2, 2)


def test_a_map_deleted_and_made_again_publishes_its_closure_1_again(monkeypatch):
    # A memory of the closure ids published, forgotten only when the retraction follower read a new epoch,
    # kept the closures of a map made again (numbered from 1 again) off the topic: with retractions_poll 0
    # for good, and until the next poll otherwise. Each answer's closure is published.
    p, stats, _ = _poster(monkeypatch, _revisit(1), _problem(404, "map-not-found"), _revisit(1),
                          retractions_poll=0.0)
    published = _published(p)
    p._post(_frame(Stamp(1)))
    p._post(_frame(Stamp(2)))  # 404: the map deleted; retried, and answered by the map made again
    assert not p.retractions.due()
    assert published == [(1, True), (1, True)]
    assert (stats.answered, stats.revisits) == (2, 2)


def test_a_stop_waits_for_a_post_under_way_and_says_when_it_may_have_been_posted(monkeypatch):
    # Before, a stop waited 5 s for the poster while a post may take request_timeout (10 s): "1 in flight not
    # posted" could be said of a frame the service then stored. Now it waits request_timeout + 1 s, and says
    # the service may yet store it when the post is still under way.
    release = threading.Event()

    class Slow(ScriptedClient):
        def observe(self, *args: Any, **kwargs: Any) -> Observation:
            release.wait(float(kwargs["metadata"]["stamp_ns"]) / 1e3)  # stamp_ns: how many ms it takes
            return ANSWER

    for ms, timeout, said in ((300, 0.2, ""), (30_000, 0.1, "may yet store it")):
        p, stats, _ = _poster(monkeypatch, request_timeout=timeout)
        p.client = Slow(stats, MAP, StreamReset(stream="cam", had_context=False))
        p.start()
        p.queue.put(_frame(Stamp(ms)))
        _wait_for(lambda p=p: p.unposted()[2], "the frame sent", 5)
        started = time.monotonic()
        try:
            line = p.stop()
        finally:
            release.set()
        waited = time.monotonic() - started
        if said:
            assert line == ("stopping: 0 frames queued not posted; 1 frame sent whose request had not ended "
                            "(the service may yet store it)") and 1.0 <= waited < 2.0
        else:  # the post ends within the wait: answered, nothing left
            assert line == "" and stats.answered == 1 and waited < 1.0
        release.clear()


class Stalling(ScriptedClient):
    """The service as a stop finds it: each post's outcome from `posts` (an exception raised after `after_s`,
    as a reply late past request_timeout is; the last repeats), and a map that takes `reset_s` to reset."""

    def __init__(self, stats: Stats, *posts: Exception, after_s: float = 0.0, reset_s: float = 0.0) -> None:
        super().__init__(stats)
        self.posts, self.after_s, self.reset_s = list(posts), after_s, reset_s
        self.tries = 0

    def observe(self, *args: Any, **kwargs: Any) -> Observation:
        self.tries += 1
        time.sleep(self.after_s)
        raise self.posts.pop(0) if len(self.posts) > 1 else self.posts[0]

    def get_map(self, map_id: str) -> Any:
        return MAP

    def reset_stream(self, map_id: str, stream: str) -> Any:
        time.sleep(self.reset_s)
        return StreamReset(stream=stream, had_context=False)

    def ready(self) -> None:
        pass


def test_a_stop_tells_frames_never_sent_from_one_sent_whose_outcome_is_unknown(monkeypatch):
    # An outside probe: SIGINT while a post's reply was late; the client's request_timeout (3 s) ended the
    # post within the stop's wait (4 s), the thread ended, and the line said "1 frame queued and 1 in flight
    # not posted" of a frame the service had stored. A frame whose request was sent is never "not posted":
    # its reply lost or late, the service may have stored it. One whose requests never connected (the
    # service down), or that waits for its new drive's reset, was never sent, and is said so.
    read = httpx.Request("POST", "http://cortexloc.test/v1/maps/default/observations")
    late = httpx.ReadTimeout("timed out", request=read)
    refused = httpx.ConnectError("refused", request=read)
    cases = [
        # the probe's: the reply late past request_timeout, the thread ended within the wait; a frame queued
        ((late,), 0.3, 1, "stopping: 1 frame queued not posted; 1 frame sent whose answer did not come (the "
                          "service may have stored it)"),
        # the service down: no request of the frame ever connected
        ((refused,), 0.0, 2, "stopping: 0 frames queued and 1 in flight not posted (never sent)"),
        # one reply lost, then the service down: the first may have been stored
        ((late, refused), 0.0, 2, "stopping: 0 frames queued not posted; 1 frame sent whose answer did not "
                                  "come (the service may have stored it)"),
    ]
    for posts, after_s, tries, said in cases:
        p, stats, _ = _poster(monkeypatch, request_timeout=1.0, retractions_poll=0.0)
        client = p.client = Stalling(stats, *posts, after_s=after_s)
        p.start()
        p.queue.put(_frame(Stamp(1)))
        _wait_for(lambda c=client, n=tries: c.tries >= n, f"{tries} tries of the frame")
        if "1 frame queued" in said:
            p.queue.put(_frame(Stamp(2)))
        line = p.stop()
        assert line == said, posts
        assert not p._thread.is_alive()
    # a new drive's frame, its stream's reset under way when the stop's wait ends: never sent, nor after
    # (resumed: no reset at start)
    p, stats, _ = _poster(monkeypatch, request_timeout=0.1, run_id="drive-a", retractions_poll=0.0)
    client = p.client = Stalling(stats, late, reset_s=3.0)
    p.start()
    _wait_for(lambda: stats.service == "up", "first contact")
    p.queue.put(replace(_frame(Stamp(1)), drive=1))
    _wait_for(lambda: p.in_flight is not None, "the frame taken")
    assert p.stop() == "stopping: 0 frames queued and 1 in flight not posted (never sent)"
    assert p._thread.is_alive()  # in the reset still
    p._thread.join(5)
    assert client.tries == 0 and not p._thread.is_alive()


def test_a_new_drive_resets_the_stream_before_its_first_frame(monkeypatch):
    # The camera's stamps went back (a bag played again): the executor marks the frames with the next drive;
    # the stream is reset on the service before the first of them, so the new pass does not continue the
    # last pass's sequence (retried like a post while the service is down).
    request = httpx.Request("POST", "http://cortexloc.test/v1/maps/default/streams/cam/reset")
    p, stats, client = _poster(monkeypatch, ANSWER, httpx.ConnectError("refused", request=request),
                               StreamReset(stream="cam", had_context=True), ANSWER, ANSWER)
    p._post(_frame(Stamp(5)))
    p._post(replace(_frame(Stamp(1)), drive=1))
    p._post(replace(_frame(Stamp(2)), drive=1))
    assert client.calls == [("reset_stream", "default", "cam")] * 2  # once the drive, after a retry
    assert stats.answered == 3 and stats.retries == 1
    assert sum("a new drive, the camera's stamps went back" in line for line in p.log.lines) == 1


def test_a_frame_whose_stamp_identifies_no_frame_is_posted_without_a_pose(monkeypatch):
    # A camera that stamps 0 (or the same stamp twice) with odometry: every frame took the pose of that
    # stamp, so distinct images got one pose and the service merged them as a robot standing still.
    odometry = OdometryBuffer(tolerance_ns=50_000_000)
    odometry.add(Stamp(0), Pose2D(1.0, 0.0, 0.0, "odom"))
    odometry.add(Stamp(10), Pose2D(2.0, 0.0, 0.0, "odom"))
    p, stats, client = _poster(monkeypatch, ANSWER, ANSWER, odometry=odometry)
    p._post(replace(_frame(Stamp(0)), stamped=False))
    p._post(_frame(Stamp(10)))
    assert "pose" not in client.metadata[0] and client.metadata[1]["pose"]["x"] == 2.0
    assert stats.no_pose == 1


def test_a_frame_takes_its_pose_from_the_odometry_segment_of_its_stamp_only(monkeypatch):
    # Before, the image's and the odometry's jumps back were independent: a frame of a new drive that came
    # before the new pass's odometry took the last pass's pose at its stamp, and the last pass's frames still
    # queued lost theirs once the odometry jumped first.
    S = 10**9
    odometry = OdometryBuffer(tolerance_ns=50_000_000)
    for i in range(200):  # the last pass, 20 s
        odometry.add(Stamp(S + i * S // 10), Pose2D(float(i), 0.0, 0.0, "odom"))
    p, stats, client = _poster(monkeypatch, ANSWER, ANSWER, ANSWER, odometry=odometry)
    p._post(replace(_frame(Stamp(S + 205 * S // 10)), arrived=time.monotonic() - 1))  # past the odometry
    for i in range(3):  # the new pass's odometry, a segment of its own
        odometry.add(Stamp(S + i * S // 10), Pose2D(100.0 + i, 0.0, 0.0, "odom"))
    p._post(_frame(Stamp(S + S // 5)))
    p._post(_frame(Stamp(S + 199 * S // 10)))  # a last-pass frame still queued
    assert "pose" not in client.metadata[0]  # its odometry never came within its wait
    assert client.metadata[1]["pose"]["x"] == 102.0 and client.metadata[2]["pose"]["x"] == 199.0
    assert stats.no_pose == 1


def _unreadable() -> Exception:
    """What the client raises for a proxy's HTML page sent with 200."""
    from cortexloc_client import InvalidResponseError

    return InvalidResponseError(200, content_type="text/html", excerpt="<html>502 upstream hiccup</html>",
                                reason="Invalid JSON: expected value at line 1 column 1")


def _wait_for(cond: Any, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_a_reply_that_cannot_be_read_is_retried_with_the_frames_key_and_said_at_error(monkeypatch):
    # An outside probe: one 200 text/html reply raised pydantic's ValidationError out of the client, which
    # ended the poster thread; diagnostics said "service up" for as long as the node ran. Now the client
    # raises InvalidResponseError, and the frame is retried with its key like a service down, ERROR meanwhile.
    p, stats, client = _poster(monkeypatch, _unreadable(), _unreadable(), ANSWER)
    keys: list[str] = []
    observe = client.observe
    client.observe = lambda *a, **kw: (keys.append(kw["idempotency_key"]), observe(*a, **kw))[1]  # type: ignore
    p._post(_frame())
    assert keys == ["run1:.cam:1:1"] * 3 and (stats.answered, stats.retries, stats.refused) == (1, 2, 0)
    service, error = client.seen[1]
    assert service == "error" and error.startswith("200 invalid response: a reply the client cannot read")
    assert Stats(service=service, last_error=error).health(0)[0] == "ERROR"
    assert len(p.log.errors) == 1 and "retried with the same key" in p.log.errors[0]  # once, not per retry
    assert (stats.service, stats.last_error) == ("up", "")


def test_no_exception_ends_the_poster_thread_and_a_frame_faulting_again_and_again_is_given_up(monkeypatch):
    # A fault no handler names (here a ValueError from the client, a camera callback that raises): said at
    # ERROR once a kind, diagnostics ERROR, the thread goes on; a frame that faults FAULT_TRIES times in a
    # row is given up (`failed`), and the next frame is answered.
    faults = [ValueError("boom")] * poster.FAULT_TRIES
    p, stats, client = _poster(monkeypatch, MAP, StreamReset(stream="cam", had_context=False), *faults,
                               ANSWER, ANSWER, retractions_poll=0.0)
    client.ready = lambda: None  # type: ignore[method-assign]  # the idle probe: up
    cameras: list[Exception] = []
    p.camera = lambda: (_ for _ in ()).throw(cameras.pop()) if cameras else None
    seen: list[tuple[str, str]] = []
    p.on_answer = lambda *a: seen.append((stats.service, stats.last_error))
    p.start()
    try:
        p.queue.put(_frame(Stamp(1)))
        _wait_for(lambda: stats.failed == 1, "the first frame given up")
        with stats.lock:
            assert stats.health(0) == ("ERROR", "service error: fault of the node's own: ValueError('boom')")
        cameras.append(RuntimeError("camera_info callback failed"))
        p.queue.put(_frame(Stamp(2)))  # its metadata's camera raises: outside the post, in the thread's loop
        _wait_for(lambda: stats.failed == 2, "the second frame given up")
        p.queue.put(_frame(Stamp(3)))
        _wait_for(lambda: stats.answered == 1, "the third frame answered")
        assert p._thread.is_alive()
    finally:
        p.stop()
    assert seen == [("up", "")] and client.metadata[-1]["stamp_ns"] == "3"
    assert [line.split(":")[0] for line in p.log.errors] == [
        "cortexloc poster fault, going on", "frame 1 given up after a fault of the node's own",
        "cortexloc poster fault, going on"]
    assert "RuntimeError('camera_info callback failed')" in p.log.errors[2]
    with stats.lock:
        assert stats.health(0) == ("WARN", "service up; in the last 60 s: lost 0, dropped 0, refused 0, "
                                           "failed 2, unsupported 0, malformed 0")


def test_a_pose_that_is_not_finite_is_not_posted(monkeypatch):
    # An outside probe: odometry with NaN or Inf (an EKF not yet converged) went into the metadata, the
    # service refused each such frame (422 "NaN is not JSON") and the node dropped it. The node takes no such
    # sample in (node.py); a pose that is not finite is left out here too: the frame is posted without one.
    odometry = OdometryBuffer(tolerance_ns=50_000_000)
    odometry.add(Stamp(10), Pose2D(math.nan, 0.0, 0.0, "odom"))
    odometry.add(Stamp(20), Pose2D(1.0, 2.0, math.inf, "odom"))
    odometry.add(Stamp(30), Pose2D(3.0, 0.0, 0.0, "odom"))
    p, stats, client = _poster(monkeypatch, ANSWER, ANSWER, ANSWER, odometry=odometry)
    for ns in (10, 20, 30):
        p._post(_frame(Stamp(ns)))
    assert ["pose" in m for m in client.metadata] == [False, False, True]
    assert (stats.no_pose, stats.answered, stats.refused) == (2, 3, 0)
    assert not Pose2D(1.0, math.nan, 0.0, "odom").is_postable()
    assert not Pose2D(1e12, 0.0, 0.0, "odom").is_postable() and Pose2D(1.0, 2.0, 3.0, "odom").is_postable()


def test_a_map_the_service_refuses_to_create_is_an_error_retried_not_created(monkeypatch):
    # Before, any 409 on creation read as "another node created it": the log said "created map" and every
    # frame then got 404 map-not-found. Only 409 map-exists is that; map-limit (or memory-budget, ...) is an
    # ERROR, and the creation is tried again until the service takes it.
    missing = _problem(404, "map-not-found")
    p, stats, client = _poster(monkeypatch, missing, _problem(409, "map-limit"), missing,
                               _problem(409, "map-limit"), missing, MAP)
    p._first_contact()
    assert client.calls == [("get_map", "default"), ("create_map", "default")] * 3
    service, error = client.seen[2]  # the second look, after the refusal
    assert (service, error) == ("error", "map 'default' cannot be created: 409 map-limit: map 'default' "
                                         "map-limit")
    assert Stats(service=service, last_error=error).health(0)[0] == "ERROR"
    assert len(p.log.errors) == 1 and "map 'default' cannot be created: 409 map-limit" in p.log.errors[0]
    assert [line for line in p.log.lines if "created map" in line] == ["created map 'default' (the service's "
                                                                       "defaults)"]  # once, when it was
    assert stats.service == "up"
    # made meanwhile by another node: used (read, for its threshold), and said so
    p, stats, client = _poster(monkeypatch, missing, _problem(409, "map-exists"), MAP)
    p._first_contact()
    assert stats.service == "up" and not p.log.errors and p.revisit_threshold == 0.8
    assert client.calls == [("get_map", "default"), ("create_map", "default"), ("get_map", "default")]
    assert any("exists: created meanwhile" in line for line in p.log.lines)
    assert not any("created map" in line for line in p.log.lines)


def test_refused_frames_are_logged_once_a_minute_a_kind_with_a_count(monkeypatch):
    # Before, one WARN line per refused frame: at camera rate, a flood on /rosout.
    from cortexloc_client import CortexlocError

    refusal = _problem(422, "invalid-metadata")
    big = CortexlocError(413, detail="too large")
    p, stats, _ = _poster(monkeypatch, refusal, refusal, big, refusal, big)
    for ns in range(1, 6):
        p._post(_frame(Stamp(ns)))
    assert stats.refused == 5
    assert [line.split(" refused: ")[0] for line in p.log.lines] == ["frame 1", "frame 3"]  # one of each kind
    clock = [0.0]
    p._said = poster.LogLimiter(clock=lambda: clock[0])
    p.client.outcomes = [refusal] * 3  # type: ignore[attr-defined]
    for ns, t in ((6, 0.0), (7, 30.0), (8, 61.0)):
        clock[0] = t
        p._post(_frame(Stamp(ns)))
    said = "422 invalid-metadata: map 'default' invalid-metadata"
    assert p.log.lines[-2:] == [f"frame 6 refused: {said}",
                                f"frame 8 refused: {said} (1 more like it since the last line)"]


def test_a_frame_lost_once_warns_for_a_minute_not_for_the_rest_of_the_run():
    """An outside probe: one frame dropped kept the diagnostics at WARN for good (the counters are
    cumulative). The level says how the node is now; the counters in the values stay cumulative."""
    stats = Stats(service="up")
    assert stats.health(0, now=100.0) == ("OK", "service up")
    stats.refused = 1
    assert stats.health(0, now=101.0)[0] == "WARN"
    assert stats.health(2, now=130.0) == ("WARN", "service up; in the last 60 s: lost 0, dropped 2, "
                                                  "refused 1, unsupported 0, malformed 0")
    assert stats.health(2, now=161.0) == ("WARN", "service up; in the last 60 s: lost 0, dropped 2, "
                                                  "refused 0, unsupported 0, malformed 0")
    assert stats.health(2, now=191.0) == ("OK", "service up")  # nothing new for a minute
    stats.lost = 3
    assert stats.health(2, now=192.0)[1].endswith("lost 3, dropped 0, refused 0, unsupported 0, malformed 0")
    assert stats.health(2, now=10_000.0) == ("OK", "service up")
    assert len(stats._marks) <= 3  # a mark a call, bounded by the window
    # counted before the first call (a node's diagnostics start after frames came): those warn too
    assert Stats(service="up", malformed=1).health(0, now=5.0)[0] == "WARN"
