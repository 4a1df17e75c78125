"""The client's models against the running service's `/openapi.json` (the `CONTRACT` table in
tests/conftest.py): every typed reply, success and problem+json."""

from __future__ import annotations

import inspect
from typing import Any

import pytest
from pydantic import BaseModel

from cortexloc_client import AsyncClient, Client, models

#: Served routes the client has no reply model for: Prometheus text, the docs, a tar or JPEG stream.
NOT_MODELLED = {("/metrics", "get"), ("/v1/maps/{map_id}", "delete"),
                ("/v1/maps/{map_id}/snapshots/{snapshot_id}", "delete"),
                ("/v1/maps/{map_id}/snapshots/{snapshot_id}/download", "get"),
                ("/v1/maps/{map_id}/observations/{seq}/thumbnail", "get"),
                ("/v1/maps/{map_id}/recent/{answer_id}/thumbnail", "get"),
                ("/v1/maps/{map_id}/loop-closures/export", "get")}  # files, not JSON


def test_every_reply_matches_the_servers_schema(openapi: dict[str, Any], contract) -> None:
    assert contract(openapi) == []


def test_problem_replies_match_the_servers_schema(openapi: dict[str, Any], contract) -> None:
    assert contract(openapi, models.Problem) == []


def test_every_route_the_server_serves_has_a_client_model(openapi: dict[str, Any], contract_rows) -> None:
    served = {(path, method) for path, ops in openapi["paths"].items() for method in ops
              if method in ("get", "post", "put", "patch", "delete")}
    modelled = {(path, method) for _, path, method, _, _ in contract_rows}
    assert served - modelled - NOT_MODELLED == set()
    assert ("/v1/maps/{map_id}/observations/{seq}/thumbnail", "get") in served


@pytest.mark.parametrize("method", [Client.create_map, AsyncClient.create_map])
def test_create_map_takes_every_option_the_server_does(openapi: dict[str, Any], method) -> None:
    body = openapi["paths"]["/v1/maps"]["post"]["requestBody"]["content"]["application/json"]["schema"]
    options = openapi["components"]["schemas"][body["$ref"].rsplit("/", 1)[-1]]["properties"]
    headers = {p["name"] for p in openapi["paths"]["/v1/maps"]["post"]["parameters"] if p["in"] == "header"}
    assert headers == {"Idempotency-Key"}
    assert set(inspect.signature(method).parameters) - {"self"} == set(options) | {"idempotency_key"}


class Inner(BaseModel):
    a: int
    b: str | None = None


class Outer(BaseModel):
    x: int
    inner: Inner | None = None
    items: list[Inner]
    free: dict[str, Any]


def test_the_contract_check_names_each_disagreement(schema_diff) -> None:
    spec = {"components": {"schemas": {
        "Inner": {"type": "object", "properties": {"a": {"type": "integer"}, "c": {"type": "integer"}}},
        "Item": {"type": "object", "properties": {"b": {"type": "string"}}},
    }}}
    schema = {"type": "object", "properties": {
        "inner": {"anyOf": [{"$ref": "#/components/schemas/Inner"}, {"type": "null"}]},
        "items": {"type": "array", "items": {"$ref": "#/components/schemas/Item"}},
        "free": {"type": "object", "additionalProperties": True},
        "extra": {"type": "string"},
        "x": {"anyOf": [{"type": "integer"}, {"type": "null"}]},
    }}
    assert sorted(schema_diff(Outer, schema, spec, "R")) == [
        "R.extra: declared by the server, missing in Outer",
        "R.inner.c: declared by the server, missing in Inner",
        "R.items.a: required by Inner, not declared by the server",
        "R.x: may be null on the server, not in Outer",
    ]
    assert schema_diff(Outer, {"type": "object", "additionalProperties": True}, spec, "R") == [
        "R: the server declares no fields for Outer"]
