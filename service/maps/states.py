"""A map's states and what each one serves: the one home of per-map readiness (docs/design/service.md
§1.6, §4.4; issue 38 item 2).

A map is `ready` (it serves everything), `replaying` the rows after its snapshot at startup (it answers
localising frames and reads from the memory as far as it has replayed; what learns waits), `recovering`
(rebuilding its memory: nothing is served, and the service is not ready until it is done), `read-only`
(its `map.sqlite` refuses writes: an immutable or read-only file, a read-only mount; it answers
localising frames and reads, what would write gets 503 `map-read-only` until an operator makes the file
writable and restarts the service) or `failed`
(it answers `map-unavailable` while the other maps serve; an operator should look). The request path
(`MapRuntime.require_ready`, `FailedMap`), the map resource, the automatic snapshot and `/readyz` ask
`serving`; none of them compares a state name.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["MapState", "Serving", "serving"]

MapState = Literal["ready", "replaying", "recovering", "read-only", "failed"]


@dataclass(frozen=True)
class Serving:
    """What a map in one state serves.

    Attributes:
        reads: localising frames and reads are answered (from the memory as far as it goes).
        learns: learning frames and changes are taken.
        blocks_readiness: while a map is in this state the service is not ready (`/readyz` fails).
        warns: `/readyz` warns an operator about a map in this state (the map does not serve all).
        read_only: its storage refuses writes: what learns is refused as such (`MapReadOnly`), not as
            something to wait for.
    """

    reads: bool
    learns: bool
    blocks_readiness: bool = False
    warns: bool = False
    read_only: bool = False


def serving(state: str) -> Serving:
    """What a map in `state` serves (the module docstring); a state it does not know serves nothing and
    blocks readiness (no map should be in one)."""
    match state:
        case "ready":
            return Serving(reads=True, learns=True)
        case "replaying":
            return Serving(reads=True, learns=False, warns=True)
        case "recovering":
            return Serving(reads=False, learns=False, blocks_readiness=True)
        case "read-only":
            return Serving(reads=True, learns=False, warns=True, read_only=True)
        case "failed":
            return Serving(reads=False, learns=False, warns=True)
    return Serving(reads=False, learns=False, blocks_readiness=True)
