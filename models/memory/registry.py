"""Memories: a registry of what turns a frame's sLSBH code into its winner cells, beside the backbones'
(`models.frontend.backbones`); a map names one in its `memory` option (docs/design/service.md §1.2).

    tm     the Temporal Memory's step on the stream's context (docs/design/science.md §3)
    none   the code itself: the ablation, the same pipeline without the Temporal Memory

The pipeline (`models.pipeline.core`) looks the map's option up here and never names a memory itself.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from models.memory.temporal_memory import StreamContext, TemporalMemory

__all__ = ["Memory", "get", "names", "register"]

#: (tm, code (2n,), learn, the stream's context) -> (w,) int64 sorted winner cells.
Step = Callable[[TemporalMemory, np.ndarray, bool, StreamContext], np.ndarray]


@dataclass(frozen=True)
class Memory:
    """A registered memory.

    Attributes:
        name: the map option's value.
        winners: the frame's winner cells (`Step`).
        sequential: it keeps a sequence in the stream's context (an empty context starts a new
            sequence); without one only the stream's step count runs on.
    """

    name: str
    winners: Step
    sequential: bool


_REGISTRY: dict[str, Memory] = {}


def register(name: str, *, sequential: bool) -> Callable[[Step], Step]:
    def add(fn: Step) -> Step:
        if name in _REGISTRY:
            raise ValueError(f"memory {name!r} is registered twice")
        _REGISTRY[name] = Memory(name, fn, sequential)
        return fn
    return add


def get(name: str) -> Memory:
    """Raises ValueError for an unknown name, listing the known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown memory {name!r}; known: {', '.join(names())}") from None


def names() -> list[str]:
    return list(_REGISTRY)


@register("tm", sequential=True)
def _temporal_memory(tm: TemporalMemory, code: np.ndarray, learn: bool, context: StreamContext) -> np.ndarray:
    return tm.compute(code, learn=learn, context=context)


@register("none", sequential=False)
def _code_itself(tm: TemporalMemory, code: np.ndarray, learn: bool, context: StreamContext) -> np.ndarray:
    return np.asarray(code, dtype=np.int64)
