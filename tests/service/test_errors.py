"""One error shape everywhere: RFC 9457 problem+json with request ids (docs/design/service.md §2)."""

from __future__ import annotations

import logging
import os
import uuid

import pytest
from fastapi import Depends, Query
from fastapi.testclient import TestClient
from pydantic import BaseModel, ConfigDict

from models.frontend.images import ERROR_CODES, ImageError
from service.deps import ApiKeyDep, SettingsDep, require_api_key
from service.errors import PROBLEM_MEDIA_TYPE, TITLES, Problem, image_error_problem, problem_responses
from tests.service import helpers

CORE = {"type", "title", "status", "detail", "instance", "request_id"}


class Body(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str
    count: int = 1


def make_app(tmp_path, **overrides):
    app = helpers.make_app(tmp_path / "data", **overrides)

    @app.get("/test/items")
    def list_items(top_k: int = Query(5, ge=0, le=10), learn: bool = True) -> dict:
        return {"top_k": top_k, "learn": learn}

    @app.post("/test/items", dependencies=[ApiKeyDep])
    def create_item(body: Body) -> dict:
        return {"created": body.name}

    @app.delete("/test/items/{item_id}", dependencies=[Depends(require_api_key)])
    def delete_item(item_id: str, settings: SettingsDep) -> dict:
        return {"deleted": item_id}

    @app.get("/test/boom")
    def boom() -> dict:
        raise RuntimeError("secret internals: /etc/passwd password=hunter2")

    @app.get("/test/problem")
    def problem() -> dict:
        raise Problem(404, "map-not-found", "map 'lab' does not exist", map_id="lab")

    @app.get("/test/image")
    def image() -> dict:
        raise ImageError("too-many-pixels", "image has 100000x100000 pixels", width=100_000, height=100_000)

    @app.get("/test/overloaded")
    def overloaded() -> dict:
        raise Problem(503, "overloaded", "encoder queue is full", headers={"Retry-After": "1"}, retry_after=1)

    return app


@pytest.fixture(autouse=True)
def _no_installed_weights(monkeypatch, tmp_path):
    monkeypatch.setenv("CORTEXLOC_WEIGHTS_DIR", str(tmp_path / "no-weights"))
    for var in list(os.environ):
        if var.startswith("CORTEXLOC_") and var != "CORTEXLOC_WEIGHTS_DIR":
            monkeypatch.delenv(var)


@pytest.fixture
def client(tmp_path):
    with TestClient(make_app(tmp_path)) as c:
        yield c


def assert_problem(r, status: int, slug: str) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"] == PROBLEM_MEDIA_TYPE
    body = r.json()
    assert set(body) >= CORE, body
    assert body["type"] == f"urn:cortexloc:problem:{slug}"
    assert body["title"] == TITLES[slug]
    assert body["status"] == status
    assert isinstance(body["detail"], str) and body["detail"]
    assert body["instance"] == r.request.url.path
    assert body["request_id"] == r.headers["x-request-id"]
    return body


def test_unknown_route_is_404_not_found(client):
    body = assert_problem(client.get("/v1/nothing/here"), 404, "not-found")
    assert "/v1/nothing/here" in body["detail"]


def test_wrong_method_is_405_with_every_allowed_method(client):
    r = client.put("/test/items")
    body = assert_problem(r, 405, "method-not-allowed")
    assert body["allowed"] == ["GET", "HEAD", "POST"]  # from both routes, not only the first that matched
    assert r.headers["allow"] == "GET, HEAD, POST"
    body = assert_problem(client.post("/healthz"), 405, "method-not-allowed")
    assert body["allowed"] == ["GET", "HEAD"]


def test_bad_query_is_400_invalid_parameter(client):
    body = assert_problem(client.get("/test/items", params={"top_k": -1, "learn": "maybe"}), 400,
                          "invalid-parameter")
    errors = {(e["location"], e["name"]) for e in body["errors"]}
    assert errors == {("query", "top_k"), ("query", "learn")}
    assert all(set(e) == {"location", "name", "message"} and e["message"] for e in body["errors"])


def test_bad_json_body_is_400(client):
    body = assert_problem(client.post("/test/items", json={"name": "a", "colour": "red"}), 400,
                          "invalid-parameter")
    assert body["errors"] == [{"location": "body", "name": "colour",
                               "message": "Extra inputs are not permitted"}]
    body = assert_problem(client.post("/test/items", json={"count": "x"}), 400, "invalid-parameter")
    assert {e["name"] for e in body["errors"]} == {"name", "count"}
    body = assert_problem(client.post("/test/items", content=b"{not json",
                                      headers={"content-type": "application/json"}), 400, "invalid-parameter")
    assert body["errors"][0]["location"] == "body"


def test_unexpected_exception_is_500_without_internals(tmp_path, caplog):
    with TestClient(make_app(tmp_path), raise_server_exceptions=False) as c, \
            caplog.at_level(logging.ERROR, logger="cortexloc"):
        r = c.get("/test/boom")
    body = assert_problem(r, 500, "internal-error")
    assert set(body) == CORE
    for leak in ("secret", "hunter2", "Traceback", "RuntimeError", "passwd"):
        assert leak not in r.text
    logged = [rec for rec in caplog.records if rec.exc_info]
    assert logged and "hunter2" in str(logged[0].exc_info[1])  # the traceback goes to the log


def test_unexpected_exception_does_not_escape_even_in_tests(client):
    assert_problem(client.get("/test/boom"), 500, "internal-error")


def test_problem_raised_by_a_route_keeps_its_members_and_headers(client):
    body = assert_problem(client.get("/test/problem"), 404, "map-not-found")
    assert body["map_id"] == "lab"
    r = client.get("/test/overloaded")
    body = assert_problem(r, 503, "overloaded")
    assert body["retry_after"] == 1 and r.headers["retry-after"] == "1"


def test_image_error_raised_by_a_route_is_mapped(client):
    body = assert_problem(client.get("/test/image"), 413, "image-too-large")
    assert (body["width"], body["height"], body["max_pixels"]) == (100_000, 100_000, 25_000_000)


@pytest.mark.parametrize(("code", "status", "slug"), [
    ("too-large", 413, "payload-too-large"),
    ("too-many-pixels", 413, "image-too-large"),
    ("unsupported-format", 415, "unsupported-media-type"),
    ("empty", 422, "undecodable-image"),
    ("not-an-image", 422, "undecodable-image"),
    ("truncated", 422, "undecodable-image"),
    ("degenerate", 422, "degenerate-image"),
    ("size-mismatch", 422, "raw-frame-size-mismatch"),
    ("unsupported-encoding", 415, "unsupported-media-type"),
])
def test_image_error_mapping(code, status, slug):
    p = image_error_problem(ImageError(code, "message", width=3, height=4, received_bytes=9), max_pixels=10)
    assert (p.status, p.slug, p.detail) == (status, slug, "message")
    assert p.members["width"] == 3 and p.members["received_bytes"] == 9
    if slug == "image-too-large":
        assert p.members["max_pixels"] == 10
    if slug == "unsupported-media-type":
        assert p.members["allowed"] == ["image/jpeg", "image/png", "image/webp", "image/bmp",
                                        "application/octet-stream"]
        assert "detected" in p.members


def test_every_image_error_code_is_mapped():
    for code in ERROR_CODES:
        assert image_error_problem(ImageError(code, "m")).slug in TITLES


def test_problem_refuses_unknown_slugs_and_reserved_members():
    with pytest.raises(ValueError, match="slug"):
        Problem(400, "no-such-slug", "x")
    with pytest.raises(ValueError, match="members"):
        Problem(400, "invalid-parameter", "x", request_id="mine")


def test_registry_covers_the_spec_table():
    spec = {"invalid-parameter", "map-not-found", "snapshot-not-found", "not-found", "method-not-allowed",
            "map-exists", "map-limit", "map-full", "payload-too-large", "image-too-large",
            "unsupported-media-type", "undecodable-image", "degenerate-image", "map-too-large",
            "invalid-configuration", "not-ready", "map-unavailable", "overloaded", "insufficient-storage",
            "internal-error", "unauthorized"}
    spec |= {"decompression-bomb", "snapshot-invalid"}  # issue 11: beyond the spec table
    spec |= {"observation-not-found", "raw-frame-size-mismatch", "invalid-metadata",
             "idempotency-key-reused"}  # issue 15
    spec |= {"request-timeout"}  # issue 19: the body-read deadline
    spec |= {"memory-budget", "stream-limit", "snapshot-in-use"}  # issue 19 items 1, 8 and 10
    spec |= {"recent-answer-not-found"}  # issue 23: the viewer's query thumbnails
    spec |= {"map-read-only"}  # a map whose map.sqlite refuses writes (was a 500)
    spec |= {"method-not-implemented"}  # a method llhttp does not know (was a 400 "malformed request")
    spec |= {"transfer-coding-not-implemented"}  # `Transfer-Encoding: gzip, chunked` (was read as sent)
    spec |= {"map-restored"}  # a learning post a restore rolled back before its fsync (was a 200)
    assert set(TITLES) == spec


def test_request_id_is_echoed_when_valid(client):
    r = client.get("/healthz", headers={"X-Request-ID": "robot-7.frame:42"})
    assert r.headers["x-request-id"] == "robot-7.frame:42"
    r = client.get("/nowhere", headers={"X-Request-ID": "abc-123"})
    assert r.headers["x-request-id"] == "abc-123" and r.json()["request_id"] == "abc-123"


@pytest.mark.parametrize("bad", ["", "has space", "x" * 129, "new\tline", "évil"])
def test_request_id_is_generated_when_missing_or_invalid(client, bad):
    headers = {"X-Request-ID": bad} if bad else {}
    try:
        r = client.get("/healthz", headers=headers)
    except UnicodeEncodeError:  # httpx refuses non-ASCII header values
        return
    rid = r.headers["x-request-id"]
    assert rid != bad
    assert uuid.UUID(rid).version == 4


def test_generated_request_ids_differ(client):
    ids = {client.get("/healthz").headers["x-request-id"] for _ in range(5)}
    assert len(ids) == 5


def test_openapi_documents_400_problem_not_422(client):
    spec = client.get("/openapi.json").json()
    op = spec["paths"]["/test/items"]["get"]
    assert "422" not in op["responses"]
    assert PROBLEM_MEDIA_TYPE in op["responses"]["400"]["content"]
    assert "HTTPValidationError" not in spec.get("components", {}).get("schemas", {})
    assert PROBLEM_MEDIA_TYPE in spec["paths"]["/readyz"]["get"]["responses"]["503"]["content"]
    assert set(problem_responses(404, 409)) == {404, 409}


# ------------------------------------------------------------------------------------------ API key


def test_writes_need_no_key_when_none_is_configured(client):
    assert client.post("/test/items", json={"name": "a"}).json() == {"created": "a"}


def test_api_key_required_on_writes_when_set(tmp_path):
    with TestClient(make_app(tmp_path, api_key="k3y-s3cret")) as c:
        r = c.post("/test/items", json={"name": "a"})
        body = assert_problem(r, 401, "unauthorized")
        assert "k3y-s3cret" not in r.text
        assert r.headers["www-authenticate"].startswith("Bearer")
        assert_problem(c.post("/test/items", json={"name": "a"}, headers={"X-API-Key": "wrong"}), 401,
                       "unauthorized")
        assert_problem(c.delete("/test/items/1", headers={"Authorization": "Bearer wrong"}), 401,
                       "unauthorized")
        assert_problem(c.delete("/test/items/1", headers={"Authorization": "Basic k3y-s3cret"}), 401,
                       "unauthorized")
        ok = c.post("/test/items", json={"name": "a"}, headers={"X-API-Key": "k3y-s3cret"})
        assert ok.status_code == 200 and ok.json() == {"created": "a"}
        ok = c.delete("/test/items/1", headers={"Authorization": "Bearer k3y-s3cret"})
        assert ok.status_code == 200
        # reads stay open
        assert c.get("/test/items").status_code == 200
        assert c.get("/healthz").status_code == 200
        assert "detail" in body
