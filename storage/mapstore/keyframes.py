"""`map.sqlite`'s keyframes (docs/design/science.md §12.1): a learned row's local features and camera,
written with the row (`storage.mapstore.observations`), read back to verify a revisit.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from storage.mapschema import load_json

__all__ = ["Keyframes"]


class Keyframes:
    """`MapStore`'s keyframes (module docstring); no state of its own."""

    def keyframes(self, seqs: Iterable[int]) -> dict[int, tuple[bytes, dict[str, Any] | None]]:
        """The keyframes (packed features, camera or None) stored with those of `seqs` (at most 500)
        that have one (docs/design/science.md §12.1)."""
        wanted = sorted({int(s) for s in seqs})
        if not self.holds.keyframes or not wanted:
            return {}
        with self._lock:
            marks = ",".join("?" * len(wanted))
            found = self._db().execute(f"SELECT seq, features, camera FROM keyframes WHERE seq IN ({marks})",
                                       wanted).fetchall()
        return {int(r[0]): (bytes(r[1]), load_json(r[2])) for r in found}

    def keyframe_bytes(self) -> tuple[int, int]:
        """(keyframes stored, bytes of their features and cameras): what the option costs on disk."""
        if not self.holds.keyframes:
            return 0, 0
        with self._lock:
            n, b = self._db().execute("SELECT count(*), coalesce(sum(length(features) + "
                                      "coalesce(length(camera), 0)), 0) FROM keyframes").fetchone()
        return int(n), int(b)
