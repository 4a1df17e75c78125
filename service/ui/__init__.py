"""The map viewer at `/ui` (docs/design/service.md §1.7): plain HTML, CSS and JavaScript modules under
`static/`, shipped as package data and served by the app itself (no CDN, no build step).

The page is public; what it shows comes from the API of the same service (`/v1/maps`, `.../memory`,
`.../recent`, `.../observations` and `.../thumbnail`), so the API's key rules apply to its fetches: it
sends the key the user types, kept in the browser's sessionStorage.
"""

from __future__ import annotations

from pathlib import Path

from starlette.staticfiles import StaticFiles

__all__ = ["STATIC_DIR", "UI_PATH", "static_files"]

UI_PATH = "/ui"
STATIC_DIR = Path(__file__).resolve().parent / "static"


def static_files() -> StaticFiles:
    """The viewer's files; `index.html` answers `/ui/` (`/ui` redirects there)."""
    return StaticFiles(directory=STATIC_DIR, html=True)
