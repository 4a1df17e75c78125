"""The client against the real thing: one `cortexloc serve` subprocess for the session, on a free loopback
port with a temporary data directory and an API key; each test makes its own small map.

The server is the repository's (`python -m service.cli serve`, run from the repository root) under this
interpreter, or under `CLIENT_TESTS_SERVER_PYTHON` (the client tested on Python 3.10 against a service
on 3.11); outside the repository they skip.
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import time
import types
import uuid
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Union, get_args, get_origin

import httpx
import numpy as np
import pytest
from pydantic import BaseModel

from cortexloc_client import Client, models

REPO = Path(__file__).resolve().parents[3]
API_KEY = "client-tests-key"
JSON, PROBLEM = "application/json", "application/problem+json"
#: The interpreter that runs the server: this one, or another (the service's, when the client is tested
#: on an older Python than the service runs on).
SERVER_PYTHON = os.environ.get("CLIENT_TESTS_SERVER_PYTHON") or sys.executable
#: `cortexloc-default` shrunk like the service tests' `tiny_default_preset` (128 columns, k = 64): the real
#: code paths at a fraction of the memory and time.
TINY_MAP = {"tm": {"columnDimensions": 128, "maxSegmentsPerCell": 8, "maxSynapsesPerSegment": 16,
                   "maxNewSynapseCount": 8, "activationThreshold": 4, "minThreshold": 2},
            "slsbh": {"k": 64}}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The base URL of a running `cortexloc serve` (random weights, `CORTEXLOC_API_KEY` = `API_KEY`)."""
    if not (REPO / "service" / "cli").is_dir():
        pytest.skip("the cortexloc service is not next to the client (not a repository checkout)")
    tmp = tmp_path_factory.mktemp("serve")
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if not k.startswith("CORTEXLOC_")}
    env.update({"CORTEXLOC_WEIGHTS_DIR": str(tmp / "no-weights"), "CORTEXLOC_LOG_FORMAT": "text",
                "CORTEXLOC_API_KEY": API_KEY,
                "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH")) if p)})
    log_path = tmp / "server.log"
    with log_path.open("a") as log:
        proc = subprocess.Popen([SERVER_PYTHON, "-m", "service.cli", "serve", "--port", str(port),
                                 "--data-dir", str(tmp / "var")], env=env, stdout=log, stderr=log, cwd=REPO)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                pytest.fail(f"server exited: {log_path.read_text()[-2000:]}")
            try:
                if httpx.get(f"{base}/readyz", timeout=5).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"server not ready within 120 s: {log_path.read_text()[-2000:]}")
            time.sleep(0.3)
        yield base
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.fixture
def api_key() -> str:
    """The key the tests' server requires for writes."""
    return API_KEY


@pytest.fixture
def tiny_params() -> dict[str, Any]:
    """`create_map` keywords for a small map (`TINY_MAP`)."""
    return TINY_MAP


@pytest.fixture
def client(server: str) -> Iterator[Client]:
    with Client(server, api_key=API_KEY) as c:
        yield c


@pytest.fixture
def tiny_map(client: Client) -> Iterator[str]:
    """A fresh small map's id; deleted afterwards."""
    map_id = f"t-{uuid.uuid4().hex[:10]}"
    client.create_map(map_id, **TINY_MAP)
    yield map_id
    client.delete_map(map_id)


def picture(place: int) -> np.ndarray:
    """(240, 320, 3) uint8 RGB: a smooth random scene, the same for the same `place`."""
    rng = np.random.default_rng(place)
    small = rng.integers(0, 256, (6, 8, 3)).astype(np.float64)
    rows = np.linspace(0, 5, 240)
    cols = np.linspace(0, 7, 320)
    r0, c0 = np.floor(rows).astype(int).clip(0, 4), np.floor(cols).astype(int).clip(0, 6)
    fr, fc = (rows - r0)[:, None, None], (cols - c0)[None, :, None]
    img = ((1 - fr) * (1 - fc) * small[r0][:, c0] + (1 - fr) * fc * small[r0][:, c0 + 1]
           + fr * (1 - fc) * small[r0 + 1][:, c0] + fr * fc * small[r0 + 1][:, c0 + 1])
    return img.round().astype(np.uint8)


@pytest.fixture
def make_picture() -> Callable[[int], np.ndarray]:
    """`make_picture(place) -> (240, 320, 3) uint8 RGB array`."""
    return picture


def png(image: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 RGB array as PNG bytes (zlib only: the tests need no image library)."""
    height, width, _ = image.shape
    raw = b"".join(b"\x00" + image[row].tobytes() for row in range(height))  # filter 0 on every row

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB, no interlace
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


@pytest.fixture
def make_frame() -> Callable[[int], bytes]:
    """`make_frame(place) -> PNG bytes` of `make_picture(place)`."""
    return lambda place: png(picture(place))


# ------------------------------------------------------------------------------- the OpenAPI contract

#: Client model -> where the service answers with it: (path, method, status, media type). One row per
#: reply; update it here when a route moves or a model is renamed.
CONTRACT: list[tuple[type[BaseModel], str, str, int, str]] = [
    (models.Health, "/healthz", "get", 200, JSON),
    (models.Readiness, "/readyz", "get", 200, JSON),
    (models.Problem, "/readyz", "get", 503, PROBLEM),
    (models.Map, "/v1/maps", "post", 201, JSON),
    (models.MapList, "/v1/maps", "get", 200, JSON),
    (models.Map, "/v1/maps/{map_id}", "get", 200, JSON),
    (models.Problem, "/v1/maps/{map_id}", "get", 404, PROBLEM),
    (models.Memory, "/v1/maps/{map_id}/memory", "get", 200, JSON),
    (models.StreamReset, "/v1/maps/{map_id}/streams/{stream}/reset", "post", 200, JSON),
    (models.Observation, "/v1/maps/{map_id}/observations", "post", 200, JSON),
    (models.Problem, "/v1/maps/{map_id}/observations", "post", 415, PROBLEM),
    (models.StoredObservation, "/v1/maps/{map_id}/observations/{seq}", "get", 200, JSON),
    (models.StoredObservationList, "/v1/maps/{map_id}/observations", "get", 200, JSON),
    (models.LoopClosureList, "/v1/maps/{map_id}/loop-closures", "get", 200, JSON),
    (models.Repair, "/v1/maps/{map_id}/repair", "get", 200, JSON),
    (models.Repair, "/v1/maps/{map_id}/repair", "post", 200, JSON),
    (models.Problem, "/v1/maps/{map_id}/observations/{seq}", "get", 404, PROBLEM),
    (models.Snapshot, "/v1/maps/{map_id}/snapshots", "post", 201, JSON),
    (models.SnapshotList, "/v1/maps/{map_id}/snapshots", "get", 200, JSON),
    (models.RestoredMap, "/v1/maps/{map_id}/snapshots/{snapshot_id}/restore", "post", 200, JSON),
    (models.Map, "/v1/maps/{map_id}", "patch", 200, JSON),
    (models.RecentAnswers, "/v1/maps/{map_id}/recent", "get", 200, JSON),
    (models.Budget, "/v1/memory", "get", 200, JSON),
]



def _resolve(schema: dict[str, Any], spec: dict[str, Any]) -> dict[str, Any]:
    """Follow `$ref`s and drop the `null` branch of an optional (`anyOf: [X, {type: null}]`)."""
    while True:
        if "$ref" in schema:
            node: Any = spec
            for part in schema["$ref"].removeprefix("#/").split("/"):
                node = node[part]
            schema = node
        elif "anyOf" in schema or "oneOf" in schema:
            options = [s for s in schema.get("anyOf", schema.get("oneOf")) if s.get("type") != "null"]
            if len(options) != 1:
                return schema
            schema = options[0]
        elif "allOf" in schema and len(schema["allOf"]) == 1:
            schema = schema["allOf"][0]
        else:
            return schema


def _server_nullable(schema: dict[str, Any]) -> bool:
    """Whether a property's schema admits null (`anyOf: [X, {type: null}]`, a type list with "null")."""
    options = schema.get("anyOf", schema.get("oneOf", []))
    kinds = schema.get("type")
    return any(o.get("type") == "null" for o in options) or (isinstance(kinds, list) and "null" in kinds)


def _admits_none(annotation: Any) -> bool:
    return annotation is Any or annotation is None or type(None) in get_args(annotation)


def _nested(annotation: Any) -> tuple[str | None, type[BaseModel]] | None:
    """(where the model sits: None itself, "items" in a list, "additionalProperties" in a dict, model)."""
    args = [a for a in get_args(annotation) if a is not type(None)]
    if get_origin(annotation) in (Union, types.UnionType):
        return _nested(args[0]) if len(args) == 1 else None
    if get_origin(annotation) is list and args:
        inner = _nested(args[0])
        return ("items", inner[1]) if inner and inner[0] is None else None
    if get_origin(annotation) is dict and len(args) == 2:
        inner = _nested(args[1])
        return ("additionalProperties", inner[1]) if inner and inner[0] is None else None
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return None, annotation
    return None


def schema_mismatches(model: type[BaseModel], schema: dict[str, Any], spec: dict[str, Any],
                      where: str) -> list[str]:
    """How `model` and the server's `schema` disagree: a field the server declares that the model lacks,
    a field the model requires that the server does not declare, a field the server may send as null
    that the model does not take as None; nested models are compared where the
    server describes them (a free-form object there is not compared)."""
    model.model_rebuild(force=True)  # a field naming a model defined further down is a ForwardRef until then
    schema = _resolve(schema, spec)
    props = schema.get("properties")
    if props is None:
        return [f"{where}: the server declares no fields for {model.__name__}"]
    out = [f"{where}.{name}: declared by the server, missing in {model.__name__}"
           for name in props if name not in model.model_fields]
    out += [f"{where}.{name}: required by {model.__name__}, not declared by the server"
            for name, f in model.model_fields.items() if f.is_required() and name not in props]
    out += [f"{where}.{name}: may be null on the server, not in {model.__name__}"
            for name, f in model.model_fields.items()
            if name in props and _server_nullable(props[name]) and not _admits_none(f.annotation)]
    for name, f in model.model_fields.items():
        nested = _nested(f.annotation)
        if nested is None or name not in props:
            continue
        sub = _resolve(props[name], spec)
        if nested[0] is not None:
            sub = sub.get(nested[0])
            if not isinstance(sub, dict):
                continue
            sub = _resolve(sub, spec)
        if "properties" in sub:
            out += schema_mismatches(nested[1], sub, spec, f"{where}.{name}")
    return out


def contract_mismatches(spec: dict[str, Any], rows: list[tuple[type[BaseModel], str, str, int, str]]
                        ) -> list[str]:
    """`schema_mismatches` of each row against `spec` (a parsed `/openapi.json`)."""
    out = []
    for model, path, method, status, media in rows:
        where = f"{method.upper()} {path} {status}"
        try:
            schema = spec["paths"][path][method]["responses"][str(status)]["content"][media]["schema"]
        except KeyError:
            out.append(f"{where} {media}: not in the server's OpenAPI")
            continue
        out += schema_mismatches(model, schema, spec, where)
    return out


@pytest.fixture
def contract() -> Callable[[dict[str, Any], type[BaseModel] | None], list[str]]:
    """`contract(spec, model=None) -> mismatches` of the `CONTRACT` rows (those of `model`, or all)."""
    return lambda spec, model=None: contract_mismatches(
        spec, [row for row in CONTRACT if model is None or row[0] is model])


@pytest.fixture
def contract_rows() -> list[tuple[type[BaseModel], str, str, int, str]]:
    """The `CONTRACT` table."""
    return CONTRACT


@pytest.fixture
def schema_diff() -> Callable[..., list[str]]:
    """`schema_mismatches(model, schema, spec, where)`."""
    return schema_mismatches


@pytest.fixture(scope="session")
def openapi(server: str) -> dict[str, Any]:
    """The running service's `/openapi.json`."""
    return httpx.get(f"{server}/openapi.json", timeout=30).raise_for_status().json()
