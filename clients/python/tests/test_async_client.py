"""`AsyncClient` against a real `cortexloc serve` (tests/conftest.py): the same routes as `Client`."""

from __future__ import annotations

import asyncio
import tarfile
import uuid

import pytest

from cortexloc_client import AsyncClient, NotFoundError, UnauthorizedError, UnsupportedMediaTypeError

# One pytest-xdist worker runs both files that use the session's server (`make test`): it starts once,
# not once per worker (a start exports the backbone: tens of seconds on two cores).
pytestmark = pytest.mark.xdist_group("client-server")


def test_the_async_client_maps_localises_and_snapshots(server: str, api_key: str, tiny_params: dict,
                                                       make_frame, tmp_path) -> None:
    map_id = f"a-{uuid.uuid4().hex[:10]}"

    async def session() -> None:
        async with AsyncClient(server, api_key=api_key) as c:
            assert (await c.health()).status == "ok"
            assert (await c.ready()).status == "ready"
            created = await c.create_map(map_id, **tiny_params)
            assert created.map_id == map_id and created.observations == 0
            seqs = [(await c.observe(map_id, make_frame(place), top_k=2)).seq for place in range(4)]
            snap = await c.create_snapshot(map_id)
            assert snap.seq == seqs[-1]
            assert [s.snapshot_id for s in await c.list_snapshots(map_id)] == [snap.snapshot_id]
            assert (await c.reset_stream(map_id, "default")).had_context
            for place in range(3):
                answer = await c.observe(map_id, make_frame(place), learn=False, top_k=2)
            assert answer.matches[0].seq == seqs[2]
            assert (await c.memory(map_id)).index.observations == 4

            tar_path = await c.download_snapshot(map_id, snap.snapshot_id, tmp_path / "a.tar")
            with tarfile.open(tar_path) as tar:
                assert "manifest.json" in tar.getnames()
            assert (await c.restore_snapshot(map_id, snap.snapshot_id)).discarded_observations == 0
            assert map_id in [m.map_id for m in await c.list_maps()]

            with pytest.raises(UnsupportedMediaTypeError):
                await c.observe(map_id, b"GIF89a")
            async with AsyncClient(server) as anonymous:
                with pytest.raises(UnauthorizedError):
                    await anonymous.delete_map(map_id)
            await c.delete_map(map_id)
            with pytest.raises(NotFoundError) as e:
                await c.get_map(map_id)
            assert e.value.slug == "map-not-found"

    asyncio.run(session())


def test_concurrent_streams_each_get_their_answer(server: str, api_key: str, tiny_params: dict,
                                                  make_frame) -> None:
    """Two cameras posting at once through one client: each answer names its own stream."""
    map_id = f"a-{uuid.uuid4().hex[:10]}"

    async def camera(c: AsyncClient, stream: str, places: range) -> list[str]:
        return [(await c.observe(map_id, make_frame(p), stream=stream)).stream for p in places]

    async def session() -> tuple[list[str], list[str]]:
        async with AsyncClient(server, api_key=api_key) as c:
            await c.create_map(map_id, **tiny_params)
            try:
                return tuple(await asyncio.gather(camera(c, "left", range(3)),  # type: ignore[return-value]
                                                  camera(c, "right", range(10, 13))))
            finally:
                await c.delete_map(map_id)

    left, right = asyncio.run(session())
    assert left == ["left"] * 3 and right == ["right"] * 3
