"""The map viewer at `/ui` (docs/design/service.md §1.7): plain HTML, CSS and JavaScript modules under
`static/`, shipped as package data and served by the app itself (no CDN, no build step).

The page is public; what it shows comes from the API of the same service (`/v1/maps`, `.../memory`,
`.../recent`, `.../observations` and `.../thumbnail`), so the API's key rules apply to its fetches: it
sends the key the user types, kept in the browser's sessionStorage.
"""

from __future__ import annotations

from pathlib import Path

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import RedirectResponse
from starlette.staticfiles import StaticFiles

__all__ = ["STATIC_DIR", "UI_PATH", "mount_viewer", "static_files"]

UI_PATH = "/ui"
STATIC_DIR = Path(__file__).resolve().parent / "static"


def static_files() -> StaticFiles:
    """The viewer's files; `index.html` answers `/ui/` (`/ui` redirects there, `mount_viewer`)."""
    return StaticFiles(directory=STATIC_DIR, html=True)


async def _to_index(request: Request) -> RedirectResponse:
    return RedirectResponse(UI_PATH + "/", status_code=307)


def mount_viewer(app: Starlette) -> None:
    """The viewer under `/ui/` on `app`, and `/ui` sent there by a relative redirect: the apps redirect no
    path by themselves (`redirect_slashes` off), since such a redirect's `Location` is an absolute URL
    made from the request's `Host` header, whatever a client put there (docs/design/service.md §1.9)."""
    app.add_route(UI_PATH, _to_index, methods=["GET"], include_in_schema=False)
    app.mount(UI_PATH, static_files(), name="ui")
