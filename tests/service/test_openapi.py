"""/openapi.json describes every successful reply: each 2xx of /v1 and of /healthz, /readyz has a
schema with properties, or a binary media type (downloads, thumbnails); a 204 has no body
(docs/design/service.md §1)."""

from __future__ import annotations

from typing import Any

from fastapi.testclient import TestClient

from tests.service.helpers import make_app

# Files a reply may be instead of a JSON document (a snapshot, a thumbnail, the loop-closure export).
BINARY = {"application/x-tar", "application/octet-stream", "image/jpeg", "text/csv", "application/jsonl"}


def _resolve(schema: dict[str, Any], spec: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in schema:
        name = schema["$ref"].rsplit("/", 1)[-1]
        schema = spec["components"]["schemas"][name]
    return schema


def undescribed(spec: dict[str, Any]) -> list[str]:
    """'METHOD path status' of every 2xx reply without a schema with properties or a binary type."""
    out = []
    for path, item in spec["paths"].items():
        if not (path.startswith("/v1/") or path in ("/healthz", "/readyz")):
            continue
        for method, op in item.items():
            for status, reply in op.get("responses", {}).items():
                if not status.startswith("2") or status == "204":
                    continue
                content = reply.get("content", {})
                json_schema = content.get("application/json", {}).get("schema")
                if json_schema is not None and _resolve(json_schema, spec).get("properties"):
                    continue
                if BINARY & set(content):
                    continue
                out.append(f"{method.upper()} {path} {status}")
    return out


def test_every_successful_reply_has_a_schema(tmp_path):
    spec = TestClient(make_app(tmp_path / "data")).get("/openapi.json").json()
    assert sum(len(v) for k, v in spec["paths"].items() if k.startswith("/v1/")) >= 10
    assert undescribed(spec) == []


def test_the_walk_finds_a_reply_without_a_schema(tmp_path):
    app = make_app(tmp_path / "data")

    @app.get("/v1/test/untyped")
    def untyped() -> dict:
        return {}

    spec = TestClient(app).get("/openapi.json").json()
    assert undescribed(spec) == ["GET /v1/test/untyped 200"]


def test_a_binary_reply_is_declared_as_what_it_sends_and_nothing_else(tmp_path):
    """The snapshot download is a tar: no `application/json` with an empty schema beside it."""
    spec = TestClient(make_app(tmp_path / "data")).get("/openapi.json").json()
    reply = spec["paths"]["/v1/maps/{map_id}/snapshots/{snapshot_id}/download"]["get"]["responses"]["200"]
    assert set(reply["content"]) == {"application/x-tar"}
    assert reply["content"]["application/x-tar"]["schema"] == {"type": "string", "format": "binary"}


def test_every_route_with_a_body_declares_its_415(tmp_path):
    """A body of another type (or with a content coding) is 415 on every route that reads one: the spec
    says so where a client generator reads it."""
    spec = TestClient(make_app(tmp_path / "data")).get("/openapi.json").json()
    with_body = [(m, p, op) for p, ops in spec["paths"].items() for m, op in ops.items()
                 if op.get("requestBody")]
    assert len(with_body) >= 3
    assert [f"{m} {p}" for m, p, op in with_body if "415" not in op["responses"]] == []
