"""The recent-answers ring (service/maps/runtime/recent.py): bounded, oldest first, filtered by stream."""

from __future__ import annotations

from service.maps.runtime.recent import RECENT_CAPACITY, RecentAnswers


def test_the_ring_keeps_the_newest_answers_oldest_first_up_to_its_capacity():
    ring: RecentAnswers[int] = RecentAnswers(capacity=4)
    for i in range(6):
        ring.add("a" if i % 2 else "b", i)
    assert len(ring) == 4
    assert [e.reply for e in ring.last(10)] == [2, 3, 4, 5]
    assert [e.reply for e in ring.last(2)] == [4, 5]
    assert [e.reply for e in ring.last(10, stream="a")] == [3, 5]
    assert [e.reply for e in ring.last(1, stream="b")] == [4]
    assert ring.last(10, stream="c") == [] and ring.last(0) == []
    assert all(e.received_at.endswith("+00:00") for e in ring.last(10))


def test_the_default_capacity_is_the_one_number():
    assert RecentAnswers().capacity == RECENT_CAPACITY
