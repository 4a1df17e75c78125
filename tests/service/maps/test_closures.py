"""The loop-closure exports' stamps (service/maps/closures.py, docs/design/service.md §1.2): seconds as
JSON can carry them, whatever a robot sent as `metadata.stamp`."""

from __future__ import annotations

import json
import math

import pytest

from service.maps.closures import stamp_seconds


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
