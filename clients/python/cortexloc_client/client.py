"""The synchronous client: one method per route of the cortexloc HTTP API (the service's
docs/design/service.md §1), typed replies (`cortexloc_client.models`), refusals raised as
`CortexlocError` (§2), 503s and unsent requests retried (`RetryPolicy`).

Example:
    >>> with Client("http://127.0.0.1:8000") as c:
    ...     c.create_map("lab")
    ...     answer = c.observe("lab", open("frame.jpg", "rb").read(), stream="robot1")
    ...     answer.matches[0].seq if answer.matches else None
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from itertools import count
from pathlib import Path
from time import sleep
from typing import TYPE_CHECKING, Any, TypeVar, cast

import httpx

from cortexloc_client import _core, models
from cortexloc_client._core import Call, RetryPolicy, Settings
from cortexloc_client.errors import InvalidResponseError
from cortexloc_client.frames import ColourOrder

if TYPE_CHECKING:
    import numpy as np

__all__ = ["Client"]

T = TypeVar("T")


class Client:
    """A synchronous cortexloc client over one `httpx.Client` (connections are kept alive).

    Keywords as `Settings` (base URL, API key, timeout, retry policy, idempotency keys), plus `transport`:
    an httpx transport instead of the network (tests; `httpx.MockTransport`).
    """

    def __init__(self, base_url: str = Settings.base_url, *, api_key: str | None = None,
                 timeout: float = Settings.timeout, retry: RetryPolicy | None = None,
                 idempotency_keys: bool = True, transport: httpx.BaseTransport | None = None) -> None:
        self.settings = Settings(base_url.rstrip("/"), api_key, timeout, retry or RetryPolicy(),
                                 idempotency_keys)
        self._http = httpx.Client(base_url=self.settings.base_url, headers=self.settings.headers(),
                                  timeout=timeout, transport=transport)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    # ------------------------------------------------------------------------------- sending

    def _send(self, call: Call[T], *, stream: bool = False) -> T:
        """`call` sent, retried by the policy, its reply decoded (`stream`: the body left unread for
        `call.decode`, the download's, to stream)."""
        request = self._http.build_request(call.method, call.path, params=call.params, json=call.json,
                                           content=call.content, headers=call.headers)
        unsure = False  # an earlier try may have been done (`_core.may_have_done`)
        for attempt in count():
            try:
                response = self._http.send(request, stream=stream)
            except httpx.TransportError as e:
                sleep(self.settings.retry.wait(call, attempt, error=e))
                unsure = unsure or _core.may_have_done(error=e)
                continue
            if response.status_code < 400:
                try:
                    return call.decode(response)
                except InvalidResponseError as e:  # a proxy's page sent with 200: as a lost reply
                    response.close()
                    sleep(self.settings.retry.wait(call, attempt, error=e))
                    unsure = True
                    continue
            response.read()
            response.close()
            if _core.done_already(call, response, unsure):
                return cast(T, None)  # a delete's: Call[None]
            sleep(self.settings.retry.wait(call, attempt, response=response))
            unsure = unsure or _core.may_have_done(response=response)
        raise AssertionError("unreachable")

    # ---------------------------------------------------------------------------- operations

    def health(self) -> models.Health:
        """`GET /healthz`."""
        return self._send(_core.health())

    def ready(self) -> models.Readiness:
        """`GET /readyz`; not retried. Raises `ServiceUnavailableError` (checks in `extra`) when not ready."""
        return self._send(_core.ready())

    # ---------------------------------------------------------------------------------- maps

    def create_map(self, map_id: str | None = None, *, preset: str | None = None,
                   seed: int | None = None, tm: Mapping[str, Any] | None = None,
                   slsbh: Mapping[str, Any] | None = None,
                   backbone: str | None = None, memory: str | None = None,
                   revisit_threshold: float | None = None, localiser: Mapping[str, Any] | None = None,
                   thumbnails: bool | None = None, resize: str | None = None,
                   keyframes: Mapping[str, Any] | None = None,
                   verify_revisit: bool | None = None, idempotency_key: str | None = None) -> models.Map:
        """`POST /v1/maps`: a new map; unset fields take the server's preset (a generated id if no id).

        Args:
            preset: the parameter preset (the server's default preset if None).
            seed: the Temporal Memory's and the projection's seed.
            tm, slsbh: Temporal Memory and sLSBH overrides (NuPIC names), merged over the preset.
            backbone: `alexnet`, `efficientnet-lite0-s5` or `efficientnet-lite0` (the server's default).
            memory: `tm` (default) or `none` (the Temporal Memory left out: the ablation).
            revisit_threshold: confidence at which a place is a revisit, in [0, 1] (`update_map` changes it).
            localiser: the sequence localiser's options (the service's docs/design/science.md §11.3).
            thumbnails: keep a small JPEG of each learned frame.
            resize: `crop` (the middle of a wide frame, as the paper) or `squash` (the whole frame,
                distorted to a square; the server's default): how frames become the backbone's input.
            keyframes: `{"features": "orb" | "sift" | "akaze", "max": N}`: keep each learned frame's local
                features, so revisits are verified geometrically (`Place.verification`).
            verify_revisit: a revisit needs a verified keyframe (`update_map` changes it).
            idempotency_key: the creation's key; default a fresh UUID (unless `idempotency_keys=False`),
                so a retry after a lost reply answers the map its first try made (200), not a second map
                nor 409.

        All but `revisit_threshold` and `verify_revisit` are frozen with the map.
        """
        return self._send(_core.create_map(
            self.settings, map_id, idempotency_key=idempotency_key, preset=preset, seed=seed, tm=tm,
            slsbh=slsbh,
            backbone=backbone, memory=memory, revisit_threshold=revisit_threshold, localiser=localiser,
            thumbnails=thumbnails, resize=resize, keyframes=keyframes, verify_revisit=verify_revisit))

    def list_maps(self) -> list[models.Map]:
        return self._send(_core.list_maps())

    def get_map(self, map_id: str) -> models.Map:
        return self._send(_core.get_map(map_id))

    def update_map(self, map_id: str, *, revisit_threshold: float | None = None,
                   verify_revisit: bool | None = None) -> models.Map:
        """`PATCH /v1/maps/{map_id}`: change what may change after creation (the revisit threshold,
        whether a revisit needs a verified keyframe)."""
        return self._send(_core.update_map(map_id, revisit_threshold, verify_revisit))

    def delete_map(self, map_id: str) -> None:
        """`DELETE /v1/maps/{map_id}`, with its observations and snapshots."""
        self._send(_core.delete_map(map_id))

    def memory(self, map_id: str) -> models.Memory:
        return self._send(_core.memory(map_id))

    def memory_budget(self) -> models.Budget:
        """The process-wide memory budget: total, used, free, each map's share."""
        return self._send(_core.memory_budget())

    def reset_stream(self, map_id: str, stream: str) -> models.StreamReset:
        """Break the stream's sequence: its next frame starts a new one."""
        return self._send(_core.reset_stream(map_id, stream))

    # -------------------------------------------------------------------------- observations

    def observe(self, map_id: str, image: bytes | np.ndarray, *, learn: bool = True, top_k: int = 5,
                stream: str = "default", label: str | None = None,
                metadata: models.Metadata | Mapping[str, Any] | None = None, colour: ColourOrder = "rgb8",
                idempotency_key: str | None = None) -> models.Observation:
        """`POST /v1/maps/{map_id}/observations`: one frame in, ranked matches (and the place) out.

        Args:
            image: JPEG, PNG, WebP or BMP bytes, or a raw frame as an array: (H, W, 3) uint8 in `colour`
                order, (H, W, 4) uint8 in `colour` order with alpha last (dropped), (H, W) or (H, W, 1)
                uint8 (mono8), (H, W) or (H, W, 1) uint16 (mono16).
            learn: True maps (stored, learned); False localises (nothing stored changes).
            top_k: matches to return (0 skips ranking).
            stream: one per camera or robot; frames of a stream must be posted in order, one at a time.
            label: stored and returned with matches (<= 200 characters).
            metadata: `{"stamp": ..., "pose": {"x", "y", "yaw", "frame_id"}}` or any small JSON object.
            colour: channel order of an (H, W, 3) or (H, W, 4) array: `rgb8`, `bgr8` (OpenCV), `rgba8`
                or `bgra8` (ROS encoding names; `rgba8` orders the colours as `rgb8`).
            idempotency_key: this post's key; default a fresh UUID (unless `idempotency_keys=False`).
        """
        return self._send(_core.observe(self.settings, map_id, image, learn=learn, top_k=top_k,
                                        stream=stream, label=label, metadata=metadata, colour=colour,
                                        idempotency_key=idempotency_key))

    def get_observation(self, map_id: str, seq: int) -> models.StoredObservation:
        """`GET /v1/maps/{map_id}/observations/{seq}`: a learned observation."""
        return self._send(_core.get_observation(map_id, seq))

    def list_observations(self, map_id: str, *, after_seq: int = 0,
                          limit: int = 100) -> models.StoredObservationList:
        """`GET /v1/maps/{map_id}/observations`: learned observations with seq > `after_seq`, in seq
        order, at most `limit` (<= 500); continue with `after_seq=page.next_after_seq`."""
        return self._send(_core.list_observations(map_id, after_seq, limit))

    def loop_closures(self, map_id: str, *, after: int = 0, limit: int = 100) -> models.LoopClosureList:
        """`GET /v1/maps/{map_id}/loop-closures`: the revisits streams were told of, oldest first, after
        log id `after`, at most `limit` (<= 500); continue with `after=page.cursor(after)` (`next_after`
        is None when there is nothing more for now), and rebuild from the export when
        `page.missed(after)` (entries the log's cap pruned before they were read)."""
        return self._send(_core.loop_closures(map_id, after, limit))

    def repair(self, map_id: str, *, undo: bool = False) -> models.Repair:
        """`GET /v1/maps/{map_id}/repair` (undo False: what a repair would undo) or `POST` (undo True: undo
        it, durably): the merges a stream made from its own recent trail, and the loop closures that
        named them (retracted in the log). A POST whose answer was lost is sent again: the second finds
        nothing left to undo, so its lists are empty; the retractions are in `loop_closures`."""
        return self._send(_core.repair(map_id, undo=undo))

    def export_loop_closures(self, map_id: str, fmt: str = "csv") -> bytes:
        """`GET /v1/maps/{map_id}/loop-closures/export`: the whole log as candidate pairs (`csv` or
        `jsonl`): both stamps in seconds, both ids, the confidence, both poses where given, and the
        verified relative pose on maps with keyframes; or (`g2o`) the verified closures as
        `EDGE_SE3:QUAT` lines in body axes (x ahead, y left, z up), each id they name declared as a
        `VERTEX_SE3:QUAT` at its posted pose (docs/design/service.md §1.2)."""
        return self._send(_core.export_loop_closures(map_id, fmt))

    def recent(self, map_id: str, *, limit: int = 50, stream: str | None = None) -> models.RecentAnswers:
        """`GET /v1/maps/{map_id}/recent`: the map's last answers (at most `limit`, of one `stream` if
        given), oldest first; the service keeps them in memory only."""
        return self._send(_core.recent(map_id, limit, stream))

    def thumbnail(self, map_id: str, seq: int) -> bytes:
        """`GET /v1/maps/{map_id}/observations/{seq}/thumbnail`: the stored JPEG thumbnail."""
        return self._send(_core.thumbnail(map_id, seq))

    def recent_thumbnail(self, map_id: str, answer_id: int) -> bytes:
        """`GET /v1/maps/{map_id}/recent/{answer_id}/thumbnail`: the query frame's JPEG kept with a recent
        answer (`RecentAnswer.has_thumbnail`; in the service's memory only)."""
        return self._send(_core.recent_thumbnail(map_id, answer_id))

    # ----------------------------------------------------------------------------- snapshots

    def create_snapshot(self, map_id: str) -> models.Snapshot:
        return self._send(_core.create_snapshot(map_id))

    def list_snapshots(self, map_id: str) -> list[models.Snapshot]:
        """Newest first."""
        return self._send(_core.list_snapshots(map_id))

    def restore_snapshot(self, map_id: str, snapshot_id: str) -> models.RestoredMap:
        """Roll the map back (the present is kept in a `pre-restore` snapshot first)."""
        return self._send(_core.restore_snapshot(map_id, snapshot_id))

    def delete_snapshot(self, map_id: str, snapshot_id: str) -> None:
        """Delete one snapshot (not the one the map recovers from: 409 snapshot-in-use)."""
        self._send(_core.delete_snapshot(map_id, snapshot_id))

    def download_snapshot(self, map_id: str, snapshot_id: str, dest: str | os.PathLike[str]) -> Path:
        """Stream the snapshot's tar into `dest` (through `dest.part`, moved into place when complete).

        Returns:
            `dest` as a Path.
        """
        path, part = _core.part_path(dest)
        response = self._send(_core.download_snapshot(map_id, snapshot_id), stream=True)
        written = 0
        try:
            with part.open("wb") as f:
                for chunk in response.iter_bytes():
                    written += f.write(chunk)
        except BaseException:
            part.unlink(missing_ok=True)
            raise
        finally:
            response.close()
        return _core.finish_download(response, written, path, part)
