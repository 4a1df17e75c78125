"""What the sync and async clients share: each route as a `Call` (method, path, body, how to read the
reply), the retry policy, and the client's settings. No I/O here; `Client` and `AsyncClient` send.
"""

from __future__ import annotations

import json
import os
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, TypeVar
from urllib.parse import quote

import httpx
from pydantic import BaseModel, ValidationError

from cortexloc_client import models
from cortexloc_client.errors import InvalidResponseError, error_from_response, is_problem, retry_after_seconds
from cortexloc_client.frames import ColourOrder, frame_body

__all__ = ["Call", "RetryPolicy", "Settings"]

__version__ = "0.1.0"

T = TypeVar("T")
M = TypeVar("M", bound=BaseModel)

IDEMPOTENCY_HEADER = "Idempotency-Key"
#: Query parameter carrying an observation's metadata as compact JSON (the body is the image).
METADATA_PARAM = "metadata"


#: Statuses that, without the service's problem+json body, are a proxy's page in front of it: the request
#: may or may not have reached the service (RetryPolicy).
PROXY_STATUSES = frozenset({500, 502, 503, 504})


@dataclass(frozen=True)
class RetryPolicy:
    """When a request is sent again.

    - the service's 503 (problem+json `overloaded`, `not-ready`, `map-unavailable`, `map-read-only`): it
      refused before doing anything, so any request is retried, after `Retry-After` seconds when the
      reply has them, else after `backoff_s`, 2 x `backoff_s`, 4 x ...; never longer than `max_wait_s`.
      Except a map whose `state` is `failed`: it waits for its operator (the detail says what to do),
      not for time, so it is raised at once.
    - the service's 409 `map-restored`: a learning post whose row a restore rolled back before it was
      durable; the map holds nothing of it, so it is retried like a 503 (learned on the restored map).
    - a connection that could not be opened: the request was never sent; retried like a 503.
    - any other transport failure (reset, timeout while reading the reply): the service may have done
      the work, so only idempotent requests are retried (GET, DELETE, PATCH, a stream reset, and an
      observation or a map creation that carries an `Idempotency-Key`).
    - the scale-out's 503 `map-unavailable` with `outcome_unknown: true` (the ingress handed the request
      to its shard, which died with it or did not answer in time): it may have been done, so it is
      retried as a proxy's page below (idempotent requests only).
    - a 500, 502, 503 or 504 that is not problem+json: a proxy's page, not the service's answer (Ray
      Serve's proxy sends a plain-text 500 for a request whose ingress replica died with it; nginx and
      load balancers send HTML 502 Bad Gateway, 503 and 504 Gateway Timeout when the upstream failed or
      was slow), so whether the service did the work is unknown: a transport failure after the request
      left, retried for idempotent requests only, the same key, after `Retry-After` or the backoff
      above. A problem+json 500 is the service's own `internal-error` (a bug to report with its
      `request_id`): never retried.
    - a success reply whose body is not the route's answer (`InvalidResponseError`: a proxy's page
      sent with 200, JSON cut short or without the route's members): whether the service did the work is
      unknown, as for a 502 page, so it is a transport failure after the request left: retried for
      idempotent requests only (an observation post with the same `Idempotency-Key`: the service answers
      a repeat of a stored post from its store, so it is learned once), after the backoff. A reply that
      never validates (a server whose answer this client does not know) is raised once the attempts are
      spent.

    Args:
        attempts: tries in all, the first included (1: never retry).
        max_wait_s: cap on one wait, whatever `Retry-After` asks.
        backoff_s: the first wait when the reply gives none.
    """

    attempts: int = 4
    max_wait_s: float = 30.0
    backoff_s: float = 0.5

    def __post_init__(self) -> None:
        if self.attempts < 1 or self.max_wait_s < 0 or self.backoff_s < 0:
            raise ValueError(f"invalid retry policy {self}")

    def wait(self, call: Call[Any], attempt: int, *, response: httpx.Response | None = None,
             error: httpx.TransportError | InvalidResponseError | None = None) -> float:
        """Seconds to wait before try `attempt + 1` (0-based) after this failed try.

        Raises:
            CortexlocError: the reply's error, when it is not retried (its body must have been read).
            httpx.TransportError, InvalidResponseError: `error`, when it is not retried.
        """
        last = attempt + 1 >= self.attempts or not call.retry
        if error is not None:
            if last or (may_have_done(error=error) and not call.idempotent):
                raise error
            return min(self.backoff_s * 2**attempt, self.max_wait_s)
        assert response is not None
        unsure = may_have_done(response=response)  # a proxy's page, or the scale-out's "outcome unknown"
        refused = response.status_code == 503 and not unsure  # the service's own 503: nothing was done
        refused = refused or _rolled_back(response)  # nothing was kept
        if last or not (refused or (unsure and call.idempotent)) or (refused and _failed_map(response)):
            raise error_from_response(response)
        asked = retry_after_seconds(response.headers.get("Retry-After"))
        return min(self.backoff_s * 2**attempt if asked is None else asked, self.max_wait_s)


def may_have_done(*, response: httpx.Response | None = None,
                  error: httpx.TransportError | InvalidResponseError | None = None) -> bool:
    """Whether a failed try may have been done by the service (`RetryPolicy`'s cases): a transport
    failure after the request left, a reply spoilt on the way (`InvalidResponseError`), a proxy's page
    that is not the service's problem+json. Not a connection never opened, nor the service's own error."""
    if error is not None:
        return not isinstance(error, (httpx.ConnectError, httpx.ConnectTimeout))
    assert response is not None
    if response.status_code not in PROXY_STATUSES:
        return False
    return not is_problem(response) or _member(response, "outcome_unknown") is True


#: The 404s that say a delete's target is gone: the map, or (a snapshot's delete) its snapshot or map.
GONE = (":map-not-found", ":snapshot-not-found")


def done_already(call: Call[Any], response: httpx.Response, unsure: bool) -> bool:
    """A delete answered the service's 404 (its map or snapshot not found) after an earlier try that may
    have deleted (`unsure`, `may_have_done`): what it asked is so, and the try that did it lost its
    reply (a reset, a proxy's page, the scale-out's shard gone with it). A first try's 404 is the
    caller's error (`NotFoundError`): nothing of that name was there."""
    return (call.deletes and unsure and response.status_code == 404 and is_problem(response)
            and str(_member(response, "type") or "").endswith(GONE))


def _member(response: httpx.Response, name: str) -> Any:
    """A member of the reply's JSON object (its body read), None where there is none."""
    try:
        body = response.json()
    except ValueError:
        return None
    return body.get(name) if isinstance(body, dict) else None


def _rolled_back(response: httpx.Response) -> bool:
    """The service's 409 `map-restored`: a restore rolled the post back before it was durable."""
    if response.status_code != 409 or not is_problem(response):
        return False
    return str(_member(response, "type") or "").endswith(":map-restored")


def _failed_map(response: httpx.Response) -> bool:
    """A 503 about a map left `failed` (a corrupt or unopenable file, one that did not fit the memory
    budget at start): no retry helps until an operator acts."""
    return _member(response, "state") == "failed"


@dataclass(frozen=True)
class Settings:
    """A client's settings (`Client(...)` and `AsyncClient(...)` take the same keywords).

    Attributes:
        base_url: the service, e.g. `http://robot-server:8000`.
        api_key: the server's `CORTEXLOC_API_KEY`, sent as `X-API-Key` on every request.
        timeout: seconds for connecting, and between bytes of the reply.
        retry: when to send a request again (`RetryPolicy(attempts=1)`: never).
        idempotency_keys: give each observation post and map creation a fresh `Idempotency-Key` (kept
            across its retries), so that a retried post is not learned twice, nor a map made twice.
    """

    base_url: str = "http://127.0.0.1:8000"
    api_key: str | None = None
    timeout: float = 30.0
    retry: RetryPolicy = field(default_factory=RetryPolicy)
    idempotency_keys: bool = True

    def headers(self) -> dict[str, str]:
        out = {"User-Agent": f"cortexloc-client/{__version__}"}
        if self.api_key is not None:
            out["X-API-Key"] = self.api_key
        return out


@dataclass(frozen=True)
class Call(Generic[T]):
    """One request and how to read its successful reply."""

    method: str
    path: str
    decode: Callable[[httpx.Response], T]
    params: dict[str, str] | None = None
    json: Any = None
    content: bytes | None = None
    headers: dict[str, str] = field(default_factory=dict)
    #: Sending it twice leaves the service as sending it once (retried after any transport failure).
    idempotent: bool = False
    #: Retried at all (a readiness probe is not: its 503 is the answer).
    retry: bool = True
    #: A delete (a Call[None]): the service's 404 to a retry after a try that may have been done
    #: (`may_have_done`) is its success, the reply of the try that deleted lost on the way (`done_already`).
    deletes: bool = False


def _parse(cls: type[M], r: httpx.Response) -> M:
    """The reply's body as `cls`. Raises `InvalidResponseError` for one that is not (not JSON, cut
    short, without a member the route answers)."""
    try:
        return cls.model_validate_json(r.content)
    except ValidationError as e:
        raise InvalidResponseError.of(r, e) from None


def _model(cls: type[M]) -> Callable[[httpx.Response], M]:
    return lambda r: _parse(cls, r)


def _nothing(r: httpx.Response) -> None:
    """A delete's reply: the service's is 204 No Content. Raises `InvalidResponseError` for another
    success (a captive portal's page sent with 200: the delete may not have reached the service)."""
    if r.status_code != 204:
        raise InvalidResponseError.because(r, "a delete is answered 204 No Content")
    return None


def _typed(r: httpx.Response, media_type: str) -> httpx.Response:
    """`r`, a byte route's reply, when its `Content-Type` is the route's `media_type` (parameters such as
    `charset` aside). Raises `InvalidResponseError` for another (a captive portal's HTML page sent with
    200): retried as a reply lost on the way, as a JSON route's unreadable body is."""
    got = r.headers.get("Content-Type", "").split(";", 1)[0].strip().lower()
    if got != media_type:
        raise InvalidResponseError.because(r, f"Content-Type {got or 'none'!r}, not {media_type!r}")
    return r


def _bytes_of(media_type: str) -> Callable[[httpx.Response], bytes]:
    """The body of a reply of `media_type` (`_typed`)."""
    return lambda r: _typed(r, media_type).content


#: The media type of each byte route's reply (the service's `EXPORT_FORMATS`, `TAR_MEDIA_TYPE`).
EXPORT_MEDIA_TYPES = {"csv": "text/csv", "jsonl": "application/jsonl", "g2o": "text/plain"}
JPEG_MEDIA_TYPE = "image/jpeg"
TAR_MEDIA_TYPE = "application/x-tar"


def _seg(value: str) -> str:
    """One path segment. `quote` leaves '.' alone, and httpx resolves a "." or ".." segment (RFC 3986):
    `delete_snapshot(m, "..")` would be DELETE /v1/maps/m, so those two go as "%2E" (the server reads
    one segment, a stream named ".." among them). An empty one would name the collection instead."""
    if not value:
        raise ValueError("an id or stream name in a path cannot be empty")
    if value in (".", ".."):
        return "%2E" * len(value)
    return quote(value, safe="")


def _map(map_id: str) -> str:
    return f"/v1/maps/{_seg(map_id)}"


# ------------------------------------------------------------------------------------------ routes


def health() -> Call[models.Health]:
    return Call("GET", "/healthz", _model(models.Health), idempotent=True)


def ready() -> Call[models.Readiness]:
    return Call("GET", "/readyz", _model(models.Readiness), idempotent=True, retry=False)


def create_map(settings: Settings, map_id: str | None, *, idempotency_key: str | None,
               **fields: Any) -> Call[models.Map]:
    """Fields left None are not sent (the server's preset decides them). With a key (made here once, so
    every retry sends it) a retry whose first try made the map is answered that map, not a second one."""
    body = {"map_id": map_id, **fields}
    key = idempotency_key or (uuid.uuid4().hex if settings.idempotency_keys else None)
    return Call("POST", "/v1/maps", _model(models.Map), json={k: v for k, v in body.items() if v is not None},
                headers={} if key is None else {IDEMPOTENCY_HEADER: key}, idempotent=key is not None)


def list_maps() -> Call[list[models.Map]]:
    return Call("GET", "/v1/maps", lambda r: _parse(models.MapList, r).maps,
                idempotent=True)


def get_map(map_id: str) -> Call[models.Map]:
    return Call("GET", _map(map_id), _model(models.Map), idempotent=True)


def update_map(map_id: str, revisit_threshold: float | None,
               verify_revisit: bool | None = None) -> Call[models.Map]:
    body = {"revisit_threshold": revisit_threshold, "verify_revisit": verify_revisit}
    # Absolute values: a repeat sets the same thing again.
    return Call("PATCH", _map(map_id), _model(models.Map),
                json={k: v for k, v in body.items() if v is not None}, idempotent=True)


def delete_map(map_id: str) -> Call[None]:
    return Call("DELETE", _map(map_id), _nothing, idempotent=True, deletes=True)


def memory(map_id: str) -> Call[models.Memory]:
    return Call("GET", f"{_map(map_id)}/memory", _model(models.Memory), idempotent=True)


def memory_budget() -> Call[models.Budget]:
    return Call("GET", "/v1/memory", _model(models.Budget), idempotent=True)


def reset_stream(map_id: str, stream: str) -> Call[models.StreamReset]:
    return Call("POST", f"{_map(map_id)}/streams/{_seg(stream)}/reset", _model(models.StreamReset),
                idempotent=True)


def observe(settings: Settings, map_id: str, image: Any, *, learn: bool, top_k: int, stream: str,
            label: str | None, metadata: models.Metadata | Mapping[str, Any] | None, colour: ColourOrder,
            idempotency_key: str | None) -> Call[models.Observation]:
    frame = frame_body(image, colour)
    params = {"learn": "true" if learn else "false", "top_k": str(top_k), "stream": stream, **frame.params}
    if label is not None:
        params["label"] = label
    if metadata is not None:
        meta = metadata.model_dump(exclude_none=True) if isinstance(metadata, BaseModel) else dict(metadata)
        params[METADATA_PARAM] = json.dumps(meta, separators=(",", ":"))
    headers = {"Content-Type": frame.media_type}
    # One key per logical post, made here once: every retry of this Call sends the same key.
    key = idempotency_key or (uuid.uuid4().hex if settings.idempotency_keys else None)
    if key is not None:
        headers[IDEMPOTENCY_HEADER] = key
    return Call("POST", f"{_map(map_id)}/observations", _model(models.Observation), params=params,
                content=frame.content, headers=headers, idempotent=key is not None)


def get_observation(map_id: str, seq: int) -> Call[models.StoredObservation]:
    return Call("GET", f"{_map(map_id)}/observations/{int(seq)}", _model(models.StoredObservation),
                idempotent=True)


def list_observations(map_id: str, after_seq: int, limit: int) -> Call[models.StoredObservationList]:
    return Call("GET", f"{_map(map_id)}/observations", _model(models.StoredObservationList),
                params={"after_seq": str(int(after_seq)), "limit": str(int(limit))}, idempotent=True)


def loop_closures(map_id: str, after: int, limit: int) -> Call[models.LoopClosureList]:
    return Call("GET", f"{_map(map_id)}/loop-closures", _model(models.LoopClosureList),
                params={"after": str(int(after)), "limit": str(int(limit))}, idempotent=True)


def export_loop_closures(map_id: str, fmt: str) -> Call[bytes]:
    # an unknown format goes as asked: the service's 400 names the ones there are
    return Call("GET", f"{_map(map_id)}/loop-closures/export", _bytes_of(EXPORT_MEDIA_TYPES.get(fmt, "")),
                params={"format": fmt}, idempotent=True)


def repair(map_id: str, *, undo: bool) -> Call[models.Repair]:
    # a repair is idempotent: a second one finds nothing, so a retried POST is safe
    return Call("POST" if undo else "GET", f"{_map(map_id)}/repair", _model(models.Repair), idempotent=True)


def recent(map_id: str, limit: int, stream: str | None) -> Call[models.RecentAnswers]:
    params = {"limit": str(int(limit)), **({"stream": stream} if stream is not None else {})}
    return Call("GET", f"{_map(map_id)}/recent", _model(models.RecentAnswers), params=params, idempotent=True)


def thumbnail(map_id: str, seq: int) -> Call[bytes]:
    return Call("GET", f"{_map(map_id)}/observations/{int(seq)}/thumbnail", _bytes_of(JPEG_MEDIA_TYPE),
                idempotent=True)


def recent_thumbnail(map_id: str, answer_id: int) -> Call[bytes]:
    return Call("GET", f"{_map(map_id)}/recent/{int(answer_id)}/thumbnail", _bytes_of(JPEG_MEDIA_TYPE),
                idempotent=True)


def create_snapshot(map_id: str) -> Call[models.Snapshot]:
    return Call("POST", f"{_map(map_id)}/snapshots", _model(models.Snapshot))


def list_snapshots(map_id: str) -> Call[list[models.Snapshot]]:
    return Call("GET", f"{_map(map_id)}/snapshots",
                lambda r: _parse(models.SnapshotList, r).snapshots, idempotent=True)


def restore_snapshot(map_id: str, snapshot_id: str) -> Call[models.RestoredMap]:
    return Call("POST", f"{_map(map_id)}/snapshots/{_seg(snapshot_id)}/restore", _model(models.RestoredMap))


def delete_snapshot(map_id: str, snapshot_id: str) -> Call[None]:
    return Call("DELETE", f"{_map(map_id)}/snapshots/{_seg(snapshot_id)}", _nothing, idempotent=True,
                deletes=True)


def download_snapshot(map_id: str, snapshot_id: str) -> Call[httpx.Response]:
    """Streamed by the client (`Client.download_snapshot`): `decode` hands on the response unread, once
    its `Content-Type` is a tar's."""
    return Call("GET", f"{_map(map_id)}/snapshots/{_seg(snapshot_id)}/download",
                lambda r: _typed(r, TAR_MEDIA_TYPE), idempotent=True)


# -------------------------------------------------------------------------------------- downloads


def part_path(dest: str | os.PathLike[str]) -> tuple[Path, Path]:
    """(destination, its temporary `.part` sibling): a download lands whole or not at all."""
    path = Path(dest)
    return path, path.with_name(path.name + ".part")


def finish_download(response: httpx.Response, written: int, path: Path, part: Path) -> Path:
    """Move the finished `.part` into place after checking its length against `Content-Length`.

    Raises:
        httpx.ReadError: fewer (or more) bytes than announced; the part is removed.
    """
    expected = response.headers.get("Content-Length")
    if expected is not None and int(expected) != written:
        part.unlink(missing_ok=True)
        raise httpx.ReadError(f"snapshot download cut short: {written} of {expected} bytes",
                              request=response.request)
    os.replace(part, path)
    return path
