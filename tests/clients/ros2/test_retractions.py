"""The node's retraction follower (cortexloc_ros.retractions) and its documents, without ROS: a back end that
builds its pose graph from the node's loop-closure topic gets each retraction of the stream's closures,
with the id of the closure it withdraws, and can drop that edge (the service's repair, issue 35 item 3)."""

from __future__ import annotations

import json
from typing import Any

import httpx
import pytest

pytest.importorskip("cortexloc_ros.retractions", reason="the ROS 2 node is not installed (make install-ros)")

from cortexloc_ros.answers import loop_closure_json, retraction_json
from cortexloc_ros.core import Stamp
from cortexloc_ros.retractions import PAGE, RetractionFollower

from cortexloc_client import Observation
from cortexloc_client.models import LoopClosure, LoopClosureList


def entry(i: int, stream: str = "cam", retracts: int | None = None, seq: int | None = 7) -> dict[str, Any]:
    return {"id": i, "stream": stream, "seq": seq, "metadata": {"stamp": 10.5, "stamp_ns": "10500000000"},
            "place": {"seq": 3, "observation_id": "o3", "stream": stream, "metadata": {"stamp": 2.0}},
            "confidence": 0.0 if retracts else 0.95, "support": 0 if retracts else 9,
            "created_at": "2026-11-29T00:00:00Z", "retracts": retracts}


def page(entries: list[dict[str, Any]], newest: int | None, epoch: str = "e1", full: bool = False,
         oldest: int | None = 1) -> LoopClosureList:
    return LoopClosureList.model_validate({"loop_closures": entries, "oldest": oldest, "newest": newest,
                                           "epoch": epoch,
                                           "next_after": entries[-1]["id"] if full else None})


class Log:
    def __init__(self) -> None:
        self.lines: list[str] = []

    def warning(self, text: str) -> None:
        self.lines.append(text)

    info = warning


class Pages:
    """The map's log as the follower reads it: one scripted outcome per request, each request recorded."""

    def __init__(self, *outcomes: LoopClosureList | Exception) -> None:
        self.outcomes, self.requests = list(outcomes), []

    def loop_closures(self, map_id: str, *, after: int = 0, limit: int = 100) -> LoopClosureList:
        self.requests.append((map_id, after, limit))
        outcome = self.outcomes.pop(0)
        if isinstance(outcome, Exception):
            raise outcome
        return outcome


def follower(pages: Pages, every_s: float = 5.0) -> tuple[RetractionFollower, list[LoopClosure], list[float]]:
    now = [100.0]
    got: list[LoopClosure] = []
    f = RetractionFollower(pages, "m", "cam", every_s, got.append, Log(), clock=lambda: now[0],
                           on_epoch=lambda previous, epoch: f.log.lines.append(f"epoch {previous} {epoch}"))
    return f, got, now


def test_retractions_of_the_streams_closures_logged_after_the_start_are_handed_on_once():
    pages = Pages(page([], newest=40),  # the start: where the log stands (what came before is the export's)
                  page([entry(41), entry(42, retracts=12), entry(43, stream="other", retracts=13),
                        entry(44, retracts=41, seq=None)], newest=44),
                  page([], newest=44))
    f, got, now = follower(pages)
    assert f.due()
    f.poll()
    assert got == [] and not f.due()  # the next read a period later, not at once
    now[0] += 5.0
    f.poll()
    # closures are not retractions; another stream's retraction is its own node's to publish
    assert [(e.id, e.retracts) for e in got] == [(42, 12), (44, 41)]
    now[0] += 5.0
    f.poll()
    assert len(got) == 2 and f.published == 2
    assert pages.requests == [("m", 0, 1), ("m", 40, PAGE), ("m", 44, PAGE)]


def test_a_full_page_is_followed_by_the_next_at_once_not_a_period_later():
    pages = Pages(page([], newest=0),
                  page([entry(i, retracts=i - 100) for i in range(101, 101 + 3)], newest=900, full=True),
                  page([entry(104, retracts=4)], newest=900))
    f, got, now = follower(pages)
    f.poll()
    now[0] += 5.0
    f.poll()
    assert f.due()  # more to read: the next page at the poster's next turn
    f.poll()
    assert [e.retracts for e in got] == [1, 2, 3, 4] and not f.due()
    assert pages.requests[-1] == ("m", 103, PAGE)


def test_a_failed_read_is_said_once_and_tried_again_a_period_later():
    request = httpx.Request("GET", "http://cortexloc.test/v1/maps/m/loop-closures")
    down = httpx.ConnectError("refused", request=request)
    pages = Pages(down, down, page([], newest=5), page([entry(6, retracts=2)], newest=6))
    f, got, now = follower(pages)
    f.poll()
    assert not f.due()
    now[0] += 5.0
    f.poll()
    assert len(f.log.lines) == 1 and "tried again every 5 s" in f.log.lines[0]
    now[0] += 5.0
    f.poll()  # back: it starts from where the log stands now, and says so
    assert len(f.log.lines) == 2 and "again" in f.log.lines[1]
    now[0] += 5.0
    f.poll()
    assert [e.retracts for e in got] == [2]


def test_a_restore_or_a_pruned_gap_is_said_and_the_follower_goes_on_from_the_restored_log():
    pages = Pages(page([], newest=10, epoch="e1"),
                  page([entry(11, retracts=3)], newest=30, epoch="e2"),  # a restore meanwhile
                  page([entry(31, retracts=4)], newest=31, epoch="e2"),
                  page([entry(80, retracts=5)], newest=80, epoch="e2", oldest=70))  # the cap pruned 32-69
    f, got, now = follower(pages)
    for _ in range(4):
        f.poll()
        now[0] += 5.0
    # the restored log's entries up to its newest are not this run's to publish; 31 and 80 are
    assert [e.retracts for e in got] == [4, 5]
    assert f.log.lines[0] == "epoch e1 e2"  # handed on once (the node publishes it and clears its markers)
    assert "was restored" in f.log.lines[1] and "pruned" in f.log.lines[2] and len(f.log.lines) == 3


def test_an_older_server_or_a_zero_period_turns_the_follower_off():
    pages = Pages(page([], newest=None))
    f, got, _ = follower(pages)
    f.poll()
    assert not f.due() and "older server" in f.log.lines[0] and got == []
    f, _, _ = follower(Pages(), every_s=0.0)
    assert not f.due()


def test_the_topics_documents_name_the_closure_and_the_closure_a_retraction_withdraws():
    answer = Observation.model_validate({
        "map_id": "m", "stream": "cam", "learned": True, "seq": 9, "loop_closure_id": 42,
        "sequence": {"step": 1, "active_columns": 1, "predicted_columns": 0, "bursting_columns": 1,
                     "winner_cells": 1},
        "matches": [], "timings_ms": {},
        "versions": {"api": "v1", "code": "x", "encoder": "e", "weights": "w", "projection": "p",
                     "map_seq": 9},
        "place": {"seq": 3, "place_id": 3, "confidence": 0.95, "revisit": True, "support": 9}})
    closure = loop_closure_json(answer, Stamp.of(10, 500000000), "cam", None, "map")
    assert closure is not None and (closure["kind"], closure["id"]) == ("closure", 42)
    withdrawn = retraction_json(LoopClosure.model_validate(entry(50, retracts=42)), "m")
    assert (withdrawn["kind"], withdrawn["id"], withdrawn["retracts"]) == ("retraction", 50, 42)
    assert withdrawn["stamp"] == closure["stamp"] == {"sec": 10, "nanosec": 500000000}
    assert (withdrawn["place_seq"], withdrawn["place_stamp"]) == (3, {"sec": 2, "nanosec": 0})
    json.dumps(withdrawn)  # it is published as JSON


def test_the_node_publishes_a_retraction_and_takes_its_edge_off_the_markers():
    from collections import deque
    from types import SimpleNamespace

    node = pytest.importorskip("cortexloc_ros.node", reason="rclpy is not installed (make install-ros)")
    from cortexloc_ros.core import Pose2D

    closures: list = []
    markers: list = []
    fake = SimpleNamespace(cfg=SimpleNamespace(map_id="m"), poster=SimpleNamespace(revisit_threshold=0.91),
                           pub_closures=SimpleNamespace(publish=closures.append),
                           pub_markers=SimpleNamespace(publish=markers.append),
                           _edges=deque([(41, Pose2D(0, 0, 0, "odom"), Pose2D(5, 0, 0, "odom"), 0.9),
                                         (42, Pose2D(1, 0, 0, "odom"), Pose2D(6, 0, 0, "odom"), 0.95)],
                                        maxlen=node.MAX_EDGES))
    fake._markers = lambda: node.CortexlocNode._markers(fake)
    node.CortexlocNode._publish_retraction(fake, LoopClosure.model_validate(entry(50, retracts=42)))
    assert json.loads(closures[0].data)["retracts"] == 42
    (line,) = markers[-1].markers
    assert [(p.x, p.y) for p in line.points] == [(0.0, 0.0), (5.0, 0.0)]  # closure 41's edge is left
    node.CortexlocNode._publish_retraction(fake, LoopClosure.model_validate(entry(51, retracts=7)))
    assert len(closures) == 2 and len(markers) == 1  # an edge the node never drew: the markers stand
    node.CortexlocNode._publish_retraction(fake, LoopClosure.model_validate(entry(52, retracts=41)))
    assert markers[-1].markers[0].action == markers[-1].markers[0].DELETE  # none left: the list deleted
    # the log changed its epoch (a restore, a repair beyond the log): the topic says so, the markers clear
    fake._edges.append((60, Pose2D(0, 0, 0, "odom"), Pose2D(5, 0, 0, "odom"), 0.9))
    node.CortexlocNode._publish_epoch(fake, "t/0", "t/0/1")
    said = json.loads(closures[-1].data)
    assert said == {"kind": "epoch", "map_id": "m", "previous": "t/0", "epoch": "t/0/1"}
    assert not fake._edges and markers[-1].markers[0].action == markers[-1].markers[0].DELETE
