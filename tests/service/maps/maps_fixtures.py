"""A map registry on a temporary data directory with a features-only encoder: the domain's own code
(runtime, registry, recovery, idempotency) driven directly, not over HTTP."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from service.maps.encoding.embedders import Embedders
from service.maps.registry import MapRegistry
from service.maps.runtime import MapRuntime
from service.settings import Settings

D = 96  # feature dimension of the stand-in encoder
ENCODER = SimpleNamespace(identity="alexnet-conv3/test-features:crop", feature_dim=D,
                          identity_for=lambda resize: f"alexnet-conv3/test-features:{resize}")


@contextmanager
def registry(data_dir: Path, **settings: object) -> Iterator[MapRegistry]:
    conf = {"data_dir": data_dir, "snapshot_every": 0, **settings}
    reg = MapRegistry(data_dir, Embedders.one(ENCODER), Settings(**conf))
    reg.start()
    try:
        yield reg
    finally:
        reg.close()


def route(n: int, seed: int = 0) -> np.ndarray:
    """(n, D) features of n distinct places."""
    return np.random.default_rng(seed).normal(size=(n, D)).astype(np.float32)


def step(rt: MapRuntime, features: np.ndarray, *, learn: bool = True, stream: str = "s", top_k: int = 3,
         **kw: object):
    """One frame through the map's writer, as `observe` queues it once the pool has projected it."""
    assert rt.hasher is not None
    y = rt.hasher.project(features[None, :])[0]
    return rt.submit(lambda: rt.apply(y, "0" * 64, learn=learn, stream=stream, top_k=top_k, label=None,
                                      **kw)).result()
