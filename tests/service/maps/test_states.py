"""What each map state serves (service/maps/states.py, docs/design/service.md §1.6, §4.4): the one table
the request path, the map resource and /readyz read."""

from __future__ import annotations

from typing import get_args

import pytest

from service.maps.states import MapState, serving


@pytest.mark.parametrize(("state", "reads", "learns", "blocks", "warns", "read_only"), [
    ("ready", True, True, False, False, False),
    ("replaying", True, False, False, True, False),
    ("recovering", False, False, True, False, False),
    ("read-only", True, False, False, True, True),  # its storage refuses writes: it localises
    ("failed", False, False, False, True, False),
    ("no-such-state", False, False, True, False, False),
])
def test_each_state_serves_what_the_design_says(state: str, reads: bool, learns: bool, blocks: bool,
                                                warns: bool, read_only: bool) -> None:
    s = serving(state)
    assert (s.reads, s.learns, s.blocks_readiness, s.warns, s.read_only) == (reads, learns, blocks, warns,
                                                                            read_only)


def test_the_table_above_covers_every_state_the_api_names() -> None:
    """The map resource's `state` enum (`MapState`) is the list the test above pins, no more, no less."""
    assert set(get_args(MapState)) == {"ready", "replaying", "recovering", "read-only", "failed"}
