"""One map in memory (docs/design/service.md §1.2, §6): `MapRuntime` (runtime.py: the writer thread, the
order of observations, persistence, snapshots), Idempotency-Keys (idempotency.py), stored observations
read back (stored.py), the recent answers (recent.py) and the memory resource (sizes.py)."""

from service.maps.runtime.runtime import MapRuntime

__all__ = ["MapRuntime"]
