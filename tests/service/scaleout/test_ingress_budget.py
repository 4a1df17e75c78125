"""The ingress and the upload budget's per-map share (docs/design/service.md §3; from review): a body is
read only for a map that exists and a method that carries one, so made-up map ids cannot each take a
share of the budget and hold it until the body deadline."""

from __future__ import annotations

import asyncio
import json

from service.maps.errors import MapNotFound
from service.scaleout.ingress import create_ingress_app
from service.settings import Settings

LIMIT, BUDGET = 100_000, 250_000


class Shards:
    """A shard set with one map, `robot`: `forward` records the bodies it is given."""

    def __init__(self) -> None:
        self.forwarded: list[tuple[str, str, bytes]] = []

    def owner(self, map_id: str) -> str:
        if map_id != "robot":
            raise MapNotFound(map_id)
        return "shard-0"

    async def forward(self, map_id, method, path, query, headers, body):
        self.owner(map_id)
        self.forwarded.append((map_id, method, body))
        return 200, [("content-type", "application/json")], b"{}"


async def _request(app, map_id: str, method: str, stall: bool, length: int = LIMIT) -> dict:
    """One request declaring a `length`-byte body that sends 4 bytes, then (`stall`) nothing more."""
    path = f"/v1/maps/{map_id}/observations"
    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method,
             "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "client": ("127.0.0.1", 1), "server": ("t", 80),
             "headers": [(b"host", b"t"), (b"content-type", b"image/png"),
                         (b"content-length", str(length).encode()), (b"authorization", b"Bearer k")]}
    sent = False

    async def receive():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": b"\x89PNG", "more_body": True}
        if stall:
            await asyncio.sleep(3600)
        return {"type": "http.request", "body": b"\0" * (length - 4), "more_body": False}

    out: dict = {}

    async def send(message):
        if message["type"] == "http.response.start":
            out["status"] = message["status"]
        elif message.get("body"):
            out["body"] = json.loads(message["body"])

    await app(scope, receive, send)
    return out


def test_a_body_for_a_map_no_shard_has_or_with_a_get_is_never_read(tmp_path) -> None:
    shards = Shards()
    app = create_ingress_app(Settings(data_dir=str(tmp_path / "var"), max_upload_bytes=LIMIT,
                                      max_inflight_upload_bytes=BUDGET, body_timeout_s=30, api_key="k"),
                             lambda: shards)
    app.state.shards = shards

    async def main() -> None:
        # answered at once: read first, the stalled body would hold its share until the 30 s deadline
        out = await asyncio.wait_for(_request(app, "made-up-0", "POST", stall=True), 10)
        assert out["status"] == 404 and out["body"]["type"].endswith("map-not-found"), out
        out = await asyncio.wait_for(_request(app, "made-up-1", "GET", stall=False, length=1_000), 10)
        assert out["status"] == 404, out
        out = await asyncio.wait_for(_request(app, "robot", "GET", stall=False, length=1_000), 10)
        assert shards.forwarded == [("robot", "GET", b"")], out  # a GET's body is never forwarded
        out = await asyncio.wait_for(_request(app, "robot", "POST", stall=False), 10)
        assert out["status"] == 200
        assert shards.forwarded[-1] == ("robot", "POST", b"\x89PNG" + b"\0" * (LIMIT - 4))

    asyncio.run(main())
