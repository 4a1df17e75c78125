"""Security headers (issue 19 item 6; docs/design/service.md §1.9): every response is not to be sniffed,
framed or referred from; every page has a self-only Content-Security-Policy whose only inline code is
the page's own, by hash. `tests/e2e/test_viewer.py` loads the pages in Chromium under it."""

from __future__ import annotations

import base64
import hashlib
import re

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.headers import MAX_PAGE_BYTES, SecurityHeadersMiddleware, page_csp
from service.settings import Settings

PAGES = ["/ui/", "/docs", "/redoc", "/docs/oauth2-redirect"]


@pytest.fixture
def client(tmp_path):
    return TestClient(create_app(Settings(data_dir=tmp_path / "var")))  # pages and errors need no lifespan


def _policy(header: str) -> dict[str, list[str]]:
    return {d.split()[0]: d.split()[1:] for d in (p.strip() for p in header.split(";")) if d}


def _hash(block: str) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(block.encode()).digest()).decode() + "'"


def _common(r) -> None:
    assert r.headers["x-content-type-options"] == "nosniff"
    assert r.headers["x-frame-options"] == "DENY"
    assert r.headers["referrer-policy"] == "no-referrer"


@pytest.mark.parametrize("page", PAGES)
def test_every_page_has_a_self_only_policy_and_allows_only_its_own_inline_code(client, page):
    r = client.get(page)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    _common(r)
    csp = _policy(r.headers["content-security-policy"])
    assert csp["default-src"] == ["'self'"] and csp["frame-ancestors"] == ["'none'"]
    assert csp["object-src"] == ["'none'"] and csp["base-uri"] == ["'none'"]
    for sources in csp.values():
        assert not any(s.startswith(("http", "*")) or s == "'unsafe-eval'" for s in sources), sources
    scripts = [body for attrs, body in re.findall(r"<script\b([^>]*)>(.*?)</script>", r.text, re.S)
               if "src=" not in attrs]
    assert "'unsafe-inline'" not in csp["script-src"]
    assert sorted(csp["script-src"]) == sorted({"'self'", *map(_hash, scripts)})
    styles = re.findall(r"<style\b[^>]*>(.*?)</style>", r.text, re.S)
    if page == "/redoc":  # its styled-components writes <style> elements as it runs
        assert csp["style-src"] == ["'self'", "'unsafe-inline'"]
    else:
        assert sorted(csp["style-src"]) == sorted({"'self'", *map(_hash, styles)})


@pytest.mark.parametrize("path", ["/healthz", "/v1/maps", "/nope", "/ui/js/main.js", "/openapi.json"])
def test_every_other_response_has_the_headers_too(client, path):
    r = client.get(path)
    _common(r)
    assert "content-security-policy" not in r.headers  # a policy governs documents, not data or scripts


def test_an_injected_script_is_not_allowed_by_the_pages_hashes():
    page = b"<script>ok()</script><script src='/x.js'></script><style>p{}</style>"
    csp = page_csp(page)
    assert _hash("ok()") in csp and _hash("p{}") in csp and _hash("evil()") not in csp
    assert page_csp(page.replace(b"ok()", b"evil()")) != csp


async def _page(size: int) -> tuple[list[dict], bytes]:
    sent: list[dict] = []

    async def app(scope, receive, send):
        html = [(b"content-type", b"text/html")]
        await send({"type": "http.response.start", "status": 200, "headers": html})
        for _ in range(size // 65536):
            await send({"type": "http.response.body", "body": b"<p>" + b"x" * 65533, "more_body": True})
        await send({"type": "http.response.body", "body": b"<script>s()</script>", "more_body": False})

    async def send(message):
        sent.append(message)

    await SecurityHeadersMiddleware(app)({"type": "http", "path": "/big"}, None, send)
    return sent, b"".join(m.get("body", b"") for m in sent)


def test_a_page_too_large_to_hold_is_sent_whole_with_no_inline_code_allowed():
    import anyio

    sent, body = anyio.run(_page, 2 * MAX_PAGE_BYTES)
    assert body.endswith(b"<script>s()</script>") and len(body) == 2 * MAX_PAGE_BYTES // 65536 * 65536 + 20
    csp = dict(sent[0]["headers"])[b"content-security-policy"].decode()
    assert "sha256-" not in csp and "'unsafe-inline'" not in csp
    sent, body = anyio.run(_page, 0)
    assert _hash("s()") in dict(sent[0]["headers"])[b"content-security-policy"].decode()


@pytest.mark.parametrize("path", ["/v1/maps/", "/v1/maps/m/", "/healthz/", "/v1/maps/m/observations/"])
def test_a_slash_too_many_is_a_404_problem_not_a_redirect_to_the_clients_host(client, path):
    """An outside probe: `/v1/maps/` answered 307 with `Location: http://evil.example/v1/maps`, an absolute
    URL made from the request's Host header (a cache in front would keep and serve it)."""
    r = client.get(path, headers={"Host": "evil.example"}, follow_redirects=False)
    assert r.status_code == 404 and r.headers["content-type"] == "application/problem+json"
    assert "location" not in r.headers and "evil" not in r.text
    _common(r)


def test_the_viewers_redirect_is_relative(client):
    for method in ("GET", "HEAD"):
        r = client.request(method, "/ui", headers={"Host": "evil.example"}, follow_redirects=False)
        assert r.status_code == 307 and r.headers["location"] == "/ui/"
