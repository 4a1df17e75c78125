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


def test_query_thumbnails_fall_off_with_their_answers_and_stay_within_the_byte_budget():
    ring: RecentAnswers[int] = RecentAnswers(capacity=3, thumbnail_bytes=10)
    for i in range(3):
        ring.add("a", i, thumbnail=bytes([i]) * 4)
    ids = [e.answer_id for e in ring.last(10)]
    assert ids == [1, 2, 3]
    assert ring.with_thumbnails(ids) == {2, 3}  # 12 bytes would be over the 10: the oldest went first
    assert ring.thumbnail(3) == b"\x02" * 4 and ring.thumbnail(1) is None
    ring.add("a", 3, thumbnail=b"x" * 11)  # larger than the whole budget: not kept, nothing evicted for it
    ring.add("a", 4)  # answer 3 falls off the ring, with its thumbnail
    assert [e.answer_id for e in ring.last(10)] == [3, 4, 5] and ring.with_thumbnails([3, 4, 5]) == {3}
    assert ring.thumbnail(2) is None and ring._thumbs_size == 4
    ring.clear()
    ring.add("a", 5, thumbnail=b"y")
    assert [e.answer_id for e in ring.last(10)] == [6] and ring.thumbnail(6) == b"y"  # ids never reused
