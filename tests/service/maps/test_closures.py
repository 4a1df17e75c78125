"""The loop-closure exports (service/maps/closures.py, docs/design/service.md §1.2): stamps in seconds as
JSON can carry them, whatever a robot sent as `metadata.stamp`; a g2o edge weighed by its span."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from service.maps.closures import G2O_ROTATION_INFORMATION, g2o_lines, stamp_seconds
from storage.mapstore import LoopClosure


@pytest.mark.parametrize("stamp", ["NaN", "nan", "1e999", "-inf", "Infinity", float("nan"), float("inf")])
def test_a_stamp_that_is_no_finite_number_is_no_stamp(stamp):
    assert stamp_seconds({"stamp": stamp}) is None


def test_iso_text_without_an_offset_is_utc_whatever_the_servers_zone(monkeypatch):
    import time

    monkeypatch.setenv("TZ", "America/New_York")
    time.tzset()
    try:
        assert stamp_seconds({"stamp": "2026-11-26T12:00:00"}) == 1_795_694_400.0
        assert stamp_seconds({"stamp": "2026-11-26T12:00:00+01:00"}) == 1_795_690_800.0
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


def test_numbers_and_numeric_text_are_seconds_and_serialise_as_json():
    for stamp, want in ((12.5, 12.5), (7, 7.0), ("1700000000.25", 1_700_000_000.25)):
        got = stamp_seconds({"stamp": stamp})
        assert got == want and math.isfinite(json.loads(json.dumps(got)))
    assert stamp_seconds({"stamp": True}) is None and stamp_seconds({}) is None
    assert stamp_seconds({"stamp": "yesterday"}) is None


def test_a_g2o_edge_s_information_is_divided_by_its_span():
    # docs/design/science.md §11.11: an answer that could have been any of k places is a k times weaker
    # constraint; an entry logged before the span (schema 11) counts as 1.
    def closure(span):
        return LoopClosure(id=1, stream="a", seq=10, observation_id="o10", metadata=None, place_seq=3,
                           place_observation_id="o3", place_stream="a", place_label=None, place_metadata=None,
                           confidence=0.95, support=8, created_at="2026-11-28T00:00:00+00:00",
                           verification={"verified": True, "keyframe_seq": 3,
                                         "rotation": np.eye(3).tolist(), "translation": [1.0, 0.0, 0.0]},
                           span=span, span_seqs=None if span is None else tuple(range(3, 3 + span)))

    def rotation_information(span):
        values = (g2o_lines(closure(span)) or "").split()[3:]
        info = np.zeros((6, 6))
        info[np.triu_indices(6)] = [float(v) for v in values[7:]]
        return np.diag(info)[3:]

    assert np.all(rotation_information(None) == G2O_ROTATION_INFORMATION)
    assert np.all(rotation_information(1) == G2O_ROTATION_INFORMATION)
    assert np.allclose(rotation_information(3), G2O_ROTATION_INFORMATION / 3)
