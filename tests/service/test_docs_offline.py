"""/docs and /redoc work on a network without the internet: every asset they load is served by the app."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings

_TYPES = {".js": "text/javascript", ".css": "text/css", ".png": "image/png"}


@pytest.fixture
def client(tmp_path):
    return TestClient(create_app(Settings(data_dir=tmp_path / "var")))  # no lifespan: docs need none


def _assets(html: str) -> list[str]:
    return re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", html)


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_the_docs_pages_load_every_asset_from_the_service(client, page):
    r = client.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    assets = _assets(r.text)
    assert any(a.endswith(".js") for a in assets), assets
    assert "http://" not in r.text and "https://" not in r.text  # no CDN, no web fonts
    for url in assets:
        assert url.startswith("/") and not url.startswith("//"), url
        got = client.get(url)
        assert got.status_code == 200, url
        suffix = url[url.rfind("."):]
        assert got.headers["content-type"].split(";")[0] == _TYPES[suffix], url
        assert len(got.content) > 1000, url


def test_the_swagger_ui_served_reads_the_openapi_version_the_app_writes(client):
    """Swagger UI 4.x shows "Unable to render this definition" for OpenAPI 3.1; the bundle must be 5.x."""
    assert client.get("/openapi.json").json()["openapi"].startswith("3.1")
    js_url = next(a for a in _assets(client.get("/docs").text) if a.endswith("swagger-ui-bundle.js"))
    assert b"isOAS31" in client.get(js_url).content
    assert "url: '/openapi.json'" in client.get("/docs").text
