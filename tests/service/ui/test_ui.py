"""The map viewer's files at /ui: served by the app, shipped as package data, no external URL."""

from __future__ import annotations

import fnmatch
import re
import tomllib
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service.ui import STATIC_DIR

ROOT = Path(__file__).resolve().parents[3]
_TYPES = {".html": "text/html", ".js": "text/javascript", ".css": "text/css"}


def _shipped() -> list[Path]:
    return sorted(p for p in STATIC_DIR.rglob("*") if p.is_file())


@pytest.fixture
def client(tmp_path):
    return TestClient(create_app(Settings(data_dir=tmp_path / "var")))  # static files need no lifespan


def test_the_viewer_names_no_external_url():
    assert _shipped()
    for path in _shipped():
        text = path.read_text()
        assert "http://" not in text and "https://" not in text, path  # no CDN, fonts or schema URLs
        assert not re.search(r"""(?:src|href|from|import)\s*\(?\s*["']//""", text), path


def test_every_file_the_page_loads_is_served_by_the_app(client):
    r = client.get("/ui", follow_redirects=False)
    assert r.status_code == 307 and r.headers["location"].endswith("/ui/")
    page = client.get("/ui/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    pending = re.findall(r"""(?:src|href)="([^"]+)\"""", page.text)
    seen: set[str] = {"index.html"}
    while pending:  # the page's assets, then every module they import
        rel = pending.pop()
        if rel.startswith("data:") or rel in seen:
            continue
        seen.add(rel)
        got = client.get(f"/ui/{rel}")
        assert got.status_code == 200, rel
        assert got.headers["content-type"].split(";")[0] == _TYPES[Path(rel).suffix], rel
        base = str(Path(rel).parent)
        for imported in re.findall(r"""from\s+["']\./([^"']+)["']""", got.text):
            pending.append(imported if base == "." else f"{base}/{imported}")
    assert {str(p.relative_to(STATIC_DIR)) for p in _shipped()} == seen  # nothing shipped unused


def test_the_wheel_ships_every_viewer_file():
    setuptools = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    globs = setuptools["package-data"]["service.ui"]
    for path in _shipped():
        rel = str(path.relative_to(STATIC_DIR.parent))
        assert any(fnmatch.fnmatch(rel, g) and rel.count("/") == g.count("/") for g in globs), rel
