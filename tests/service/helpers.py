"""The one app factory of the service tests, and the frames and requests they share.

Every test app runs the real service with a small encoder (sLSBH k = 16, random weights) on its own
data directory.
"""

from __future__ import annotations

import hashlib
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.app import create_app
from service.frontend import build_embedder
from service.settings import Settings

__all__ = ["frame", "held_encoder", "make_app", "make_client", "post", "served", "state_of", "tiny_encoder"]


@contextmanager
def served(app: FastAPI, **config: Any) -> Iterator[str]:
    """`app` on a real uvicorn server on loopback (a free port, `config` for `uvicorn.Config`), in a
    thread; yields its base URL."""
    import uvicorn

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, lifespan="on",
                                           **{"log_level": "warning", **config}))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "the server did not start"
        time.sleep(0.05)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=30)


def tiny_encoder(settings: Settings):
    return build_embedder(settings, slsbh={"k": 16})


def make_app(data_dir: Path | None, **overrides) -> FastAPI:
    """The app on `data_dir` with `overrides` of the settings; None: settings read at startup."""
    # AlexNet unless a test says otherwise: without its weights the service default would be EfficientNet.
    overrides = {"backbone": "alexnet", **overrides}
    settings = None if data_dir is None else Settings(data_dir=data_dir, **overrides)
    return create_app(settings, encoder_factory=tiny_encoder)


def make_client(data_dir: Path, **overrides) -> TestClient:
    """A client of `make_app(data_dir)`; `with` it to run the lifespan (encoder, maps)."""
    return TestClient(make_app(data_dir, **overrides))


def frame(place: int, noise: float = 0.0, fmt: str = ".png") -> bytes:
    """A 'camera frame' of a place: a smooth random scene per place, optionally re-noised."""
    rng = np.random.default_rng(place)
    img = cv2.resize(rng.integers(0, 256, (12, 16, 3), dtype=np.uint8), (128, 96),
                     interpolation=cv2.INTER_CUBIC).astype(np.float32)
    if noise:
        img += np.random.default_rng(1000 + place).normal(0, noise, img.shape)
    ok, buf = cv2.imencode(fmt, np.clip(img, 0, 255).astype(np.uint8))
    assert ok
    return buf.tobytes()


def post(c: TestClient, body: bytes, map_id: str = "default", ctype: str = "image/png", **params):
    return c.post(f"/v1/maps/{map_id}/observations", content=body, headers={"Content-Type": ctype},
                  params=params)


def tm_digest(tm) -> str:
    """SHA-256 over the learned arrays and generator state, stream contexts left out ('nothing changed')."""
    h = hashlib.sha256()
    for k, v in sorted(tm.state_dict().items()):
        if not k.startswith("ctx."):
            h.update(k.encode())
            h.update(np.ascontiguousarray(v).tobytes())
    return h.hexdigest()


def state_of(c: TestClient, map_id: str = "default") -> tuple:
    """Everything a 4xx or a localisation must leave as it was: rows, last seq, learned arrays, index."""
    rt = c.app.state.registry.get(map_id)
    return rt.store.count(), rt.store.last_seq(), tm_digest(rt.tm), len(rt.index)


@contextmanager
def held_encoder(encoder: Any) -> Iterator[tuple[threading.Event, list[int]]]:
    """`encoder.embed_prepared` (the encoder pool's backbone call) records each call's batch size, then
    waits for the gate: (gate, sizes). The gate opens at the latest when the block ends."""
    gate, sizes, real = threading.Event(), [], encoder.embed_prepared

    def held(prepared, **kw):
        sizes.append(len(prepared))
        gate.wait(30)
        return real(prepared, **kw)

    encoder.embed_prepared = held
    try:
        yield gate, sizes
    finally:
        gate.set()
        encoder.embed_prepared = real
