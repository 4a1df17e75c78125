"""Security headers on every response, and a Content-Security-Policy on every page (docs/design/service.md
§1.9).

`SecurityHeadersMiddleware` is pure ASGI (outermost, so the last-resort 500 has them too). Every response
gets `X-Content-Type-Options: nosniff`, `X-Frame-Options: DENY` and `Referrer-Policy: no-referrer`. An
HTML response (the viewer at `/ui/`, `/docs`, `/redoc`, `/docs/oauth2-redirect`) also gets `PAGE_CSP`:
everything from the service itself (`'self'`), nothing framed (`frame-ancestors 'none'`), no plugins, no
`<base>`. The docs pages carry small inline `<script>` and `<style>` blocks (FastAPI's page templates),
so the page is held (a few KiB; at most `MAX_PAGE_BYTES`) and each inline block is allowed by its
SHA-256 hash, never by `'unsafe-inline'`: an injected script has another hash. Images may also be
`data:` (Swagger's icons, the viewer's empty favicon) and `blob:` (the viewer's thumbnails, fetched with
the key and shown as object URLs); ReDoc runs its search in a worker made from a `blob:`.
"""

from __future__ import annotations

import base64
import hashlib
import re

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = ["INLINE_STYLE_PAGES", "MAX_PAGE_BYTES", "PAGE_CSP", "SECURITY_HEADERS",
           "SecurityHeadersMiddleware", "page_csp"]

#: Headers of every response.
SECURITY_HEADERS = {"X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY",
                    "Referrer-Policy": "no-referrer"}
#: The policy of every HTML page; `page_csp` adds the hashes of the page's own inline blocks.
PAGE_CSP = ("default-src 'self'; script-src 'self'{scripts}; style-src 'self'{styles}; "
            "img-src 'self' data: blob:; worker-src 'self' blob:; font-src 'self'; connect-src 'self'; "
            "object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")
#: Pages whose script writes `<style>` elements as it runs (ReDoc's styled-components): any inline style
#: is allowed there, scripts still only by hash. With hashes alone /redoc shows "Something went wrong".
INLINE_STYLE_PAGES = frozenset({"/redoc"})
#: A page larger than this is sent as it comes, its inline blocks not allowed (none of ours is near it).
MAX_PAGE_BYTES = 1 << 20

_INLINE = re.compile(rb"<(script|style)\b([^>]*)>(.*?)</\1\s*>", re.IGNORECASE | re.DOTALL)


def _sha256(block: bytes) -> str:
    return "'sha256-" + base64.b64encode(hashlib.sha256(block).digest()).decode() + "'"


def page_csp(html: bytes, *, any_inline_style: bool = False) -> str:
    """`PAGE_CSP` allowing exactly the page's inline `<script>` (not `src=`) and `<style>` blocks; with
    `any_inline_style`, every inline style (`'unsafe-inline'`, which a hash beside it would switch off)."""
    found: dict[bytes, list[str]] = {b"script": [], b"style": []}
    for tag, attrs, body in _INLINE.findall(html):
        if tag.lower() == b"script" and re.search(rb"\bsrc\s*=", attrs, re.IGNORECASE):
            continue
        found[tag.lower()].append(_sha256(body))
    def allowed(hashes: list[str]) -> str:
        return "".join(" " + h for h in dict.fromkeys(hashes))

    styles = " 'unsafe-inline'" if any_inline_style else allowed(found[b"style"])
    return PAGE_CSP.format(scripts=allowed(found[b"script"]), styles=styles)


class SecurityHeadersMiddleware:
    """Pure ASGI; see the module docstring."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start: Message | None = None
        held: list[bytes] = []
        size = 0

        async def release(csp: str) -> None:
            assert start is not None
            MutableHeaders(scope=start)["Content-Security-Policy"] = csp
            await send(start)
            if held:
                await send({"type": "http.response.body", "body": b"".join(held), "more_body": True})
                held.clear()

        async def send_with_headers(message: Message) -> None:
            nonlocal start, size
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in SECURITY_HEADERS.items():
                    headers.setdefault(name, value)
                if headers.get("content-type", "").split(";")[0].strip().lower() != "text/html":
                    await send(message)
                    return
                start = message  # held until the page is whole: its hashes go in a header
                return
            if start is None or message["type"] != "http.response.body":
                await send(message)
                return
            held.append(message.get("body", b""))
            size += len(held[-1])
            if size > MAX_PAGE_BYTES:  # too large to hold: strict policy, no inline block allowed
                await release(PAGE_CSP.format(scripts="", styles=""))
                start = None
                return
            if not message.get("more_body", False):
                page = b"".join(held)
                held.clear()
                csp = page_csp(page, any_inline_style=scope.get("path") in INLINE_STYLE_PAGES)
                await release(csp)
                start = None
                await send({"type": "http.response.body", "body": page, "more_body": False})

        await self.app(scope, receive, send_with_headers)
