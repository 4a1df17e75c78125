"""A map's per-frame pipeline, pure (docs/design/service.md §1.2, §6): the stream's state and the step
that the service's writer, the recovery's replay and the evaluation share."""

from models.pipeline.core import MapModel, Step, drop, observe, replay, revisit
from models.pipeline.state import (
    Stream,
    eviction_wait,
    load_memory_state,
    memory_name,
    memory_state,
    resume,
    resume_state,
    touch,
    was_reset,
)

__all__ = ["MapModel", "Step", "Stream", "drop", "eviction_wait", "load_memory_state", "memory_name",
           "memory_state", "observe", "replay", "resume", "resume_state", "revisit", "touch", "was_reset"]
