"""The id rules of maps and snapshots (docs/design/service.md §1.1, §1.5): storage's, because an id is
also a directory name, named here for the HTTP layer's path and body patterns."""

from __future__ import annotations

from storage.catalog import MAP_ID_RE, SNAPSHOT_ID_RE

__all__ = ["MAP_ID_RE", "SNAPSHOT_ID_RE"]
