"""One map in memory (docs/design/service.md §1.2, §6): `MapRuntime` (runtime.py, the facade over one
module per concern: writer.py and records.py, snapshots.py, recovering.py, admission.py, repairing.py,
resources.py; settings.py what it reads of the service's settings), Idempotency-Keys (idempotency.py),
the group commit (durability.py), the memory budget (budget.py), stored observations read back
(stored.py), the recent answers (recent.py) and the memory resource (sizes.py)."""

from service.maps.runtime.runtime import MapRuntime

__all__ = ["MapRuntime"]
