"""The HTTP side of `cortexloc ingest`: one code path for a running service and for the app in this process.

`remote_client(url)` talks to a running service; `in_process_client(settings)` builds the app
(`service.app.create_app`), enters its lifespan (encoder, maps) and serves it through httpx's ASGI
transport, so both answer through the same routes, checks and map runtime. `ingest(client, source, opts)`
then posts the source's frames **one at a time, in source order**:

- order: the service hands frames to a map's memory in the order their requests pass its checks. Two
  requests in flight may pass them in either order, and a stream's sequence context (what the memory
  predicts next) depends on the order, so a stream is posted sequentially: frame i+1 leaves after frame
  i's answer. What runs alongside the post in flight is the reading and PNG conversion of the next
  `prefetch` frames (a reader thread and a bounded buffer).
- each post carries an `Idempotency-Key` (a fresh UUID per frame, the same on each of its retries), so
  that a retry of a post the service already learned is answered with its first reply, never learned
  twice (docs/design/service.md §1.2).
- retried at most `MAX_RETRIES` times, after `Retry-After` where the reply has one, else after 1, 2, 4 s
  (capped at `MAX_WAIT_S`): a 503 (overloaded, map recovering, starting); a 409 `map-restored` (a
  restore rolled the post back before it was durable: nothing kept); a 500 that is not
  problem+json, which is a proxy's, not the service's (Ray Serve's proxy answers so for a request whose
  ingress replica died with it, docs/scaling.md); and a connection lost mid-request. The service's own
  problem+json 500 is a bug, not retried; a post with no answer within `REMOTE_TIMEOUT_S` stops the
  ingest (the service is stuck, not restarting).
- a frame the service refuses for its bytes (413, 415, 422) is recorded as an error and the ingest goes
  on; any other refusal (401, 404, 409 map full, 5xx) stops it (`IngestError`, with the summary so far).
  A frame over the upload limit the source was opened with (`Frame.oversize`) is recorded as a 413 the
  same way without being posted (or, for a file, read); a bag message that cannot be made a frame
  (`Frame.unusable`: an encoding the service does not take, a payload shorter than its shape) as the
  415 or 422 the service would answer, not posted; a folder's file that cannot be read
  (`Frame.unreadable`) as status 0, not posted.
- a missing map is created with the server's default preset when learning (`Summary.created_map`); one
  made by someone else between the look and the creation (409 `map-exists`: two ingests started on one
  new map) is used as found. Localising against a missing map stops.
"""

from __future__ import annotations

import json
import math
import threading
import time
import uuid
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import anyio
import httpx
import numpy as np

from service.ingest.sources import Frame, Source
from service.maps.ids import MAP_ID_RE
from service.media_types import PROBLEM_MEDIA_TYPE

if TYPE_CHECKING:
    from service.settings import Settings

__all__ = ["MAX_RETRIES", "MAX_WAIT_S", "IngestError", "Options", "Record", "Summary",
           "in_process_client", "ingest", "remote_client"]

MAX_RETRIES = 5
MAX_WAIT_S = 30.0
#: Refusals of one frame's bytes: recorded, and the ingest goes on.
FRAME_ERRORS = frozenset({413, 415, 422})
REMOTE_TIMEOUT_S = 120.0
IDEMPOTENCY_HEADER = "Idempotency-Key"


class IngestError(RuntimeError):
    """The ingest stopped before the end of the source; `summary` holds what was done."""

    def __init__(self, message: str, summary: Summary) -> None:
        super().__init__(message)
        self.summary = summary


@dataclass(frozen=True)
class Options:
    """Where and how to post: map, stream, learn (mapping) or localise, stamp as label, API key."""

    map_id: str
    stream: str = "default"
    learn: bool = True
    label_stamp: bool = False
    api_key: str | None = None
    prefetch: int = 2


@dataclass(frozen=True)
class Record:
    """One frame's outcome: `answer` is the service's JSON (the observation, or a problem)."""

    frame: int
    name: str
    stamp_ns: int | None
    status: int
    latency_ms: float
    answer: dict[str, Any]

    def is_revisit(self) -> bool:
        """The service's own decision: the stream's `place` is a revisit (its confidence reached the
        map's `revisit_threshold`, docs/design/service.md §1.2)."""
        place = self.answer.get("place") if self.status == 200 else None
        return bool(place and place.get("revisit"))


@dataclass
class Summary:
    """Totals of an ingest; latencies are client round trips of a post (retries included), in ms."""

    source: str
    map_id: str
    stream: str
    learn: bool
    total: int
    created_map: bool = False
    frames: int = 0
    learned: int = 0
    revisits: int = 0
    errors: int = 0
    retries: int = 0
    elapsed_s: float = 0.0
    latencies_ms: list[float] = field(default_factory=list, repr=False)

    def add(self, rec: Record) -> None:
        if rec.status == 200:
            self.frames += 1
            self.learned += bool(rec.answer.get("learned"))
            self.revisits += rec.is_revisit()
            self.latencies_ms.append(rec.latency_ms)
        else:
            self.errors += 1

    def as_dict(self) -> dict[str, Any]:
        out = {k: v for k, v in asdict(self).items() if k != "latencies_ms"}
        lat = np.asarray(self.latencies_ms) if self.latencies_ms else None
        out["latency_ms_median"] = None if lat is None else round(float(np.median(lat)), 3)
        out["latency_ms_p95"] = None if lat is None else round(float(np.percentile(lat, 95)), 3)
        out["frames_per_s"] = round(self.frames / self.elapsed_s, 3) if self.elapsed_s > 0 else None
        return out

    def text(self) -> str:
        d = self.as_dict()
        lat = ("n/a" if d["latency_ms_median"] is None
               else f"median {d['latency_ms_median']:.1f} ms, p95 {d['latency_ms_p95']:.1f} ms")
        rate = "n/a" if d["frames_per_s"] is None else f"{d['frames_per_s']:.1f} frames/s"
        return (f"{self.source} -> map {self.map_id!r}, stream {self.stream!r} "
                f"({'learn' if self.learn else 'localise'}{', map created' if self.created_map else ''})\n"
                f"posted {self.frames}/{self.total} frames, learned {self.learned}, revisits {self.revisits} "
                f"(the stream's place, the map's threshold), errors {self.errors}, retries {self.retries}\n"
                f"latency {lat}; {rate} over {self.elapsed_s:.1f} s")


# ------------------------------------------------------------------------------------ transports


@asynccontextmanager
async def remote_client(url: str) -> AsyncIterator[httpx.AsyncClient]:
    """A client of the service at `url` (e.g. `http://robot:8000`)."""
    async with httpx.AsyncClient(base_url=url.rstrip("/"), timeout=REMOTE_TIMEOUT_S) as client:
        yield client


@asynccontextmanager
async def in_process_client(settings: Settings) -> AsyncIterator[httpx.AsyncClient]:
    """The app built from `settings`, started (its lifespan: encoder, maps) and served in this process."""
    from service.app import create_app

    app = create_app(settings)
    async with app.router.lifespan_context(app):
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://cortexloc.in-process",
                                     timeout=None) as client:
            yield client


# ------------------------------------------------------------------------------------------ ingest


Sleep = Callable[[float], Awaitable[None]]


async def ingest(client: httpx.AsyncClient, source: Source, opts: Options, *,
                 on_record: Callable[[Record], None] | None = None, sleep: Sleep = anyio.sleep) -> Summary:
    """Post every frame of `source` to `opts.map_id` in order; see the module docstring for the rules.

    Args:
        client: from `remote_client` or `in_process_client`.
        on_record: called with each frame's `Record` as its answer arrives (progress, --json).
        sleep: the wait between retries (tests pass a recorder).

    Returns:
        The summary (also when frames were refused: `errors`).

    Raises:
        IngestError: the service cannot be reached, refuses the map, or answers 503 past the retries.
    """
    summary = Summary(source=source.describe(), map_id=opts.map_id, stream=opts.stream, learn=opts.learn,
                      total=source.total)
    if not MAP_ID_RE.fullmatch(opts.map_id):
        # the id goes into the path as it is: "m/.." or "m/snapshots" would be another resource
        raise IngestError(f"map {opts.map_id!r} is not a map id ({MAP_ID_RE.pattern})", summary)
    headers = {"X-API-Key": opts.api_key} if opts.api_key else {}
    t0 = time.perf_counter()
    try:
        summary.created_map = await _ensure_map(client, opts, headers, summary)
        send, receive = anyio.create_memory_object_stream[Frame | Exception](max(opts.prefetch, 0))
        stop = threading.Event()
        failed: Exception | None = None  # raised after the task group, which would wrap it in a group
        async with anyio.create_task_group() as tg:
            tg.start_soon(anyio.to_thread.run_sync, _produce, source, send, stop)
            async with receive:
                try:
                    async for item in receive:
                        if isinstance(item, Exception):
                            raise item
                        assert isinstance(item, Frame)
                        rec = await _post_frame(client, item, opts, headers, summary, sleep)
                        summary.add(rec)
                        if on_record is not None:
                            on_record(rec)
                except Exception as e:
                    failed = e
                finally:
                    stop.set()
        if failed is not None:
            raise failed
    finally:
        summary.elapsed_s = time.perf_counter() - t0
    return summary


def _produce(source: Source, send: Any, stop: threading.Event) -> None:
    """Reader thread: frames (or the exception that ended the reading) into the bounded buffer."""
    with send:
        try:
            for frame in source.frames():
                if stop.is_set():
                    return
                anyio.from_thread.run(send.send, frame)
        except (anyio.BrokenResourceError, anyio.ClosedResourceError):
            return  # the consumer stopped
        except Exception as e:
            try:
                anyio.from_thread.run(send.send, e)
            except (anyio.BrokenResourceError, anyio.ClosedResourceError):
                return


async def _ensure_map(client: httpx.AsyncClient, opts: Options, headers: dict[str, str],
                      summary: Summary) -> bool:
    r = await _request(client, "GET", f"/v1/maps/{opts.map_id}", summary, headers=headers)
    if r.status_code == 200 and _is_map(r):
        return False
    if r.status_code == 404 and opts.learn:
        created = await _request(client, "POST", "/v1/maps", summary, headers=headers,
                                 json={"map_id": opts.map_id})
        if created.status_code == 201:
            return True
        # Made meanwhile (another ingest started on the same new map)? Then it is served now: use it. (A
        # map-exists for a directory the catalog does not list is not served: that 409 stops the ingest.)
        if created.status_code == 409 and str(json_body(created).get("type", "")).endswith(":map-exists"):
            again = await _request(client, "GET", f"/v1/maps/{opts.map_id}", summary, headers=headers)
            if again.status_code == 200 and _is_map(again):
                return False
        r = created
    raise IngestError(f"map {opts.map_id!r}: {_problem_text(r)}", summary)


async def _post_frame(client: httpx.AsyncClient, frame: Frame, opts: Options, headers: dict[str, str],
                      summary: Summary, sleep: Sleep) -> Record:
    if frame.oversize is not None:
        return Record(frame.index, frame.name, frame.stamp_ns, 413, 0.0, _not_sent(frame))
    if frame.unusable is not None:
        return _unusable(frame)
    if frame.unreadable is not None:  # status 0: never sent, nothing the service said
        return Record(frame.index, frame.name, frame.stamp_ns, 0, 0.0,
                      {"detail": f"the file could not be read ({frame.unreadable}); not sent", "sent": False})
    params: dict[str, str] = {"learn": "true" if opts.learn else "false", "stream": opts.stream,
                              **frame.params}
    if frame.stamp_ns is not None:  # where in time: the observation's `stamp` (seconds since the epoch),
        # and `stamp_ns` (text: exact past 2^53), the message's stamp to the nanosecond, as the ROS 2 node
        # posts it: seconds as a float keep about a quarter of a microsecond of a stamp today
        params["metadata"] = json.dumps({"stamp": frame.stamp_ns / 1e9, "stamp_ns": str(frame.stamp_ns)},
                                        separators=(",", ":"))
    if opts.label_stamp and frame.stamp_ns is not None:
        params["label"] = f"{frame.stamp_ns // 1_000_000_000}.{frame.stamp_ns % 1_000_000_000:09d}"
    # One key per frame, made once: each retry sends the same (a post learned already is replayed).
    headers = {**headers, "Content-Type": frame.media_type, IDEMPOTENCY_HEADER: uuid.uuid4().hex}
    t = time.perf_counter()
    for attempt in range(MAX_RETRIES + 1):
        last = attempt == MAX_RETRIES
        try:
            r: httpx.Response | None = await _request(
                client, "POST", f"/v1/maps/{opts.map_id}/observations", summary, params=params,
                content=frame.data, headers=headers)
        except IngestError as e:  # the connection broke mid-request: safe to resend with the key
            if last or not _connection_lost(e.__cause__):
                raise
            r = None
        if r is not None and (last or not _retried(r)):
            break
        summary.retries += 1
        await sleep(retry_after_s(None if r is None else r.headers.get("Retry-After"), attempt))
    assert r is not None
    latency_ms = (time.perf_counter() - t) * 1e3
    if _unanswered(r):  # a page in place of the answer to the last try: whether it was learned is unknown
        summary.errors += 1
        raise IngestError(f"frame {frame.name}: a 200 reply that is not the service's answer (a proxy's "
                          f"or captive portal's page?): {_problem_text(r)}", summary)
    rec = Record(frame.index, frame.name, frame.stamp_ns, r.status_code, round(latency_ms, 3), json_body(r))
    if r.status_code != 200 and r.status_code not in FRAME_ERRORS:
        summary.add(rec)
        raise IngestError(f"frame {frame.name}: {_problem_text(r)}", summary)
    return rec


#: Statuses that, without the service's problem+json body, are a proxy's page in front of it: the post may
#: or may not have reached the service, and every post here is keyed, so it is sent again. The typed
#: client's rule (`cortexloc_client._core.PROXY_STATUSES`; installed without the service, so a test keeps
#: the two equal).
PROXY_STATUSES = frozenset({500, 502, 503, 504})


#: Members every observation answer has (docs/design/service.md §1.2): a 200 without them is no answer.
ANSWER_MEMBERS = ("learned", "matches")


def _media_type(r: httpx.Response) -> str:
    return r.headers.get("Content-Type", "").split(";")[0].strip().lower()


def _is_map(r: httpx.Response) -> bool:
    """A map resource, not a captive portal's page sent with 200 (the ingest then stops, saying so)."""
    return _media_type(r) == "application/json" and "map_id" in json_body(r)


def _unanswered(r: httpx.Response) -> bool:
    """A 200 that is not the service's observation answer (a captive portal's or a proxy's page sent with
    200, JSON cut short): the post may not have reached the service, as for a proxy's 502."""
    if r.status_code != 200:
        return False
    if _media_type(r) != "application/json":
        return True
    body = json_body(r)
    return not all(k in body for k in ANSWER_MEMBERS)


def _retried(r: httpx.Response) -> bool:
    """The service's 503, its 409 `map-restored` (a restore rolled the post back: nothing kept), a
    proxy's page (`PROXY_STATUSES`, not problem+json), or a 200 that is no answer (`_unanswered`): the
    post is sent again (with its key: learned at most once)."""
    problem = _media_type(r) == PROBLEM_MEDIA_TYPE
    rolled_back = (problem and r.status_code == 409
                   and str(json_body(r).get("type", "")).endswith(":map-restored"))
    return (r.status_code == 503 or rolled_back or (r.status_code in PROXY_STATUSES and not problem)
            or _unanswered(r))


def _connection_lost(e: BaseException | None) -> bool:
    """A transport failure other than a timeout (a reset, a refused or dropped connection)."""
    return isinstance(e, httpx.TransportError) and not isinstance(e, httpx.TimeoutException)


def _not_sent(frame: Frame) -> dict[str, Any]:
    """The service's 413 problem for a frame over the limit, answered here: it is not worth sending."""
    return {"type": "urn:cortexloc:problem:payload-too-large", "title": "Payload too large", "status": 413,
            "detail": f"{frame.oversize} bytes, more than the upload limit; not sent",
            "received_bytes": frame.oversize, "sent": False}


def _unusable(frame: Frame) -> Record:
    """The service's refusal of a bag message that cannot be made a frame (`UnusableFrameError`, its status),
    answered here: it is not worth sending."""
    assert frame.unusable is not None
    status = frame.unusable.status
    slug, title = (("unsupported-media-type", "Unsupported media type") if status == 415 else
                   ("raw-frame-size-mismatch", "Raw frame size mismatch"))
    body = {"type": f"urn:cortexloc:problem:{slug}", "title": title, "status": status,
            "detail": f"{frame.unusable}; not sent", "sent": False}
    return Record(frame.index, frame.name, frame.stamp_ns, status, 0.0, body)


def retry_after_s(value: str | None, attempt: int) -> float:
    """Seconds to wait: the `Retry-After` delay in seconds, else 1, 2, 4, ... s; never above MAX_WAIT_S."""
    try:
        wait = float(value) if value is not None else 2.0**attempt
    except ValueError:  # an HTTP date: the service sends seconds; back off instead of parsing clocks
        wait = 2.0**attempt
    if not math.isfinite(wait) or wait < 0:  # `nan` reached asyncio.sleep (a proxy's header): back off
        wait = 2.0**attempt
    return min(wait, MAX_WAIT_S)


async def _request(client: httpx.AsyncClient, method: str, path: str, summary: Summary,
                   **kwargs: Any) -> httpx.Response:
    try:
        return await client.request(method, path, **kwargs)
    except httpx.TimeoutException as e:
        raise IngestError(f"{method} {path}: no answer within {REMOTE_TIMEOUT_S:.0f} s ({e!r}); a frame "
                            "being learned may or may not have been stored", summary) from e
    except httpx.TransportError as e:
        raise IngestError(f"{method} {path}: cannot reach the service at {client.base_url}: {e}",
                            summary) from e


def json_body(r: httpx.Response) -> dict[str, Any]:
    """The answer's JSON object; a body that is none (a proxy's page) as `status` and `detail`."""
    try:
        body = r.json()
    except ValueError:
        return {"status": r.status_code, "detail": r.text[:500]}
    return body if isinstance(body, dict) else {"body": body}


def _problem_text(r: httpx.Response) -> str:
    body = json_body(r)
    return f"{r.status_code} {body.get('title', '')}: {body.get('detail', '')}".strip()
