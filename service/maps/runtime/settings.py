"""What a map's runtime reads of the service's settings: one typed, frozen object (docs/design/service.md §8).

`RuntimeSettings.of` is the one place a `Settings` becomes what `MapRuntime` takes; the fields carry the
`Settings` names, so each value has one name, one default (`Settings`'s) and one check (its field's).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from service.settings import Settings

__all__ = ["RuntimeSettings"]


@dataclass(frozen=True)
class RuntimeSettings:
    """The `Settings` fields one map's runtime uses (each documented on its `Settings` field)."""

    max_streams: int  # localiser states held; the least recently used evicted (§1.3)
    max_observations: int  # rows the index holds; the hard cap of forgetting (science.md §11.9)
    stream_keep_seconds: float  # a stream that posted within it is never evicted for a new one (§1.3)
    snapshot_every: int  # rows and visits between automatic snapshots (0: none, §1.5)
    snapshot_keep: int  # automatic snapshots kept
    snapshot_manual_keep: int  # manual snapshots kept (0: no count limit)
    snapshot_manual_bytes: int  # bytes of manual snapshots kept (0: no byte limit)
    idempotency_keys: int  # keys of learned posts kept in the store (the last N seqs and visits)
    idempotency_cache: int  # replies of localisation posts kept in memory
    loop_closures: int  # loop closures kept in the store's log (the last N)
    visits: int  # visits kept once a snapshot covers them (science.md §11.8)
    verify_neighbours: int  # route neighbours a revisit's verification tries (science.md §12.2)

    @classmethod
    def of(cls, settings: Settings) -> RuntimeSettings:
        """The runtime's share of `settings`, read field by field under the same names."""
        return cls(**{f.name: getattr(settings, f.name) for f in dataclasses.fields(cls)})
