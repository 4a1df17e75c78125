"""The poster: one thread that takes frames from the bounded queue and posts them, in order, through the
typed client; the ROS executor never waits on the service.

- Order: a stream's frames go one at a time, frame i+1 after frame i's answer (the map's memory depends
  on the order; docs/design/service.md §1.3).
- Retries: a frame is posted until the service answers it or refuses its bytes. The service down (no
  connection, a reply cut short, a timeout), a 503 or a 429: the same post again after `Retry-After` or
  a backoff of 0.5 s doubling to 5 s, with the **same Idempotency-Key** (made when the message
  arrived), so a post that was stored before its reply was lost is answered from the store, never
  learned twice. An
  answered frame is done: it is never posted again. Meanwhile the camera's frames queue, and the queue
  drops by its policy.
- First contact, before any frame is posted (retried like a post until the service answers): the map is
  read (its `revisit_threshold` scales the markers' colours), a missing map is created (service defaults)
  when learning, and the stream's sequence context is reset on the service, so a new start is a new
  drive (the service keeps a stream's context across a node's restart), unless `run_id` was given: a
  resumed drive keeps its context, and its frames' keys are the same. A map missing later (deleted while
  the node runs) is never created again, which would reuse its seqs for other frames: it is an error,
  its frame is retried like a service down until the map is back.
- A new drive (a frame whose `drive` is not the last one's: the camera's stamps went back, a bag played
  again): the stream is reset on the service before it is posted, as at a start, so the new pass does not
  continue the last one's sequence context.
- Answers are published as they come: a message delivered twice in a drive is posted once (the executor's
  duplicate check, `core.FrameKeys`), and a retry after a lost reply is answered once, so within one run
  of the node each such message's closure is published once. A map deleted and made again numbers its
  closures from 1 again: those are new closures, published as they come.
- A reply the client cannot read (`InvalidResponseError`: a proxy's page sent with 200, JSON cut short):
  the frame may have been stored, so it is retried like a service down, with its key; ERROR on
  diagnostics and in the log (once a minute, with a count) while it lasts.
- Refused: 400, 413, 415, 422 (the frame or its metadata) are counted and logged (each kind once a
  minute, with a count); the poster goes on. A pose that is not finite, or beyond the service's
  bounds (`POSE_MAX_ABS`), is never posted (the service refuses it): the frame goes without one (`no_pose`).
- No exception ends the thread: one no code expects (a fault of the node's own, or one of the client's
  no handler names) is logged at ERROR (each kind once a minute, with a count), diagnostics say ERROR
  until the service answers again, and the thread goes on after a backoff; a frame whose post raised
  such a fault `FAULT_TRIES` times in a row is given up (counted as `failed`), so that one fault that
  repeats cannot hold the queue for good.
- First contact creates a missing map; a map made meanwhile by another node (409 `map-exists`) is used,
  but any other refusal of its creation (409 `map-limit` or `memory-budget`, a 422, ...) is an ERROR,
  logged and on diagnostics, and the creation is retried: frames are not posted to a map that is not
  there.
- Idle, it checks the service's readiness every `PROBE_S`, so diagnostics say "down" without frames.
- Between frames, every `retractions_poll` seconds, it reads one page of the map's loop-closure log for
  the retractions of this stream's closures (`retractions.RetractionFollower`).
- The service's state for diagnostics: `up` (it answered), `slow` (connected, but no reply within
  `request_timeout`: it is busy, not gone), `down` (no connection, a reply cut short), `error` (it
  answered with an error). `last_error` is the current trouble's: cleared when the service answers
  again, so "service up" never shows an outage's error.
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np

from cortexloc_client import Client, CortexlocError, InvalidResponseError, Observation
from cortexloc_client.models import LoopClosure
from cortexloc_ros.core import FrameQueue, LogLimiter, OdometryBuffer, Pose2D, Stamp
from cortexloc_ros.params import Config
from cortexloc_ros.retractions import RetractionFollower

__all__ = ["Frame", "Poster", "Stats"]

#: Refusals of one frame (its bytes, size, metadata): counted, and the next frame is posted.
FRAME_REFUSALS = frozenset({400, 413, 415, 422})
BACKOFF_S, MAX_BACKOFF_S = 0.5, 5.0
PROBE_S = 1.0
#: Faults no code expects (module docstring) in a row after which a frame is given up.
FAULT_TRIES = 3
#: Latencies kept for the diagnostics' median.
LATENCY_WINDOW = 100
#: Seconds a frame lost, dropped, refused, failed, unsupported or malformed keeps the diagnostics at WARN
#: (`Stats.health`): the level says how the node is doing now, the counters in the values (cumulative)
#: what happened since it started. One dropped frame in the morning is no warning at night.
WARN_WINDOW_S = 60.0


#: Seconds past `odom_tolerance` that a frame waits, after it arrived, for the odometry of its instant:
#: the odometry at or after a frame's stamp is published after the frame's exposure, and its transport
#: may lag the image's by a few milliseconds.
ODOM_MARGIN_S = 0.05


@dataclass(frozen=True)
class Frame:
    """One camera frame on its way: the body (a raw-frame array or encoded bytes), its stamp and frame,
    the key of its post, and when it arrived (`time.monotonic()`: its wait for odometry counts from
    there); `stamped` False: its stamp does not identify it (zero, or the previous frame's), so it is
    posted without an odometry pose; `drive`: the drive it belongs to (`core.FrameKey.drive`)."""

    stamp: Stamp
    frame_id: str
    image: np.ndarray | bytes
    colour: str
    key: str
    arrived: float
    stamped: bool = True
    drive: int = 0


@dataclass
class Stats:
    """What the diagnostics report; written by the executor (received, skipped) and the poster."""

    received: int = 0
    lost: int = 0  # frames the middleware lost before they reached the node (best effort)
    skipped_rate: int = 0
    duplicates: int = 0  # messages received twice (the same stamp and bytes): not posted again
    unsupported: int = 0  # images of an encoding the service does not take
    malformed: int = 0  # images whose header their data does not fill (no pixels, a short step or data)
    answered: int = 0
    refused: int = 0
    failed: int = 0  # frames given up after faults of the node's own (FAULT_TRIES in a row)
    retries: int = 0
    revisits: int = 0
    retractions: int = 0  # retractions of the stream's closures published (`retractions`)
    no_pose: int = 0
    service: str = "unknown"  # up | slow | down | error | unknown (module docstring)
    last_error: str = ""  # the current trouble's; "" once the service is up again
    last_latency_ms: float | None = None
    latencies_ms: deque[float] = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))
    lock: threading.Lock = field(default_factory=threading.Lock)
    # (monotonic time, the troubles' totals) at each `health`, the first at or before WARN_WINDOW_S ago
    # kept as the window's base: a health call a second keeps about WARN_WINDOW_S of them
    _marks: deque[tuple[float, tuple[int, ...]]] = field(default_factory=deque, repr=False)

    def median_latency_ms(self) -> float | None:
        with self.lock:
            return statistics.median(self.latencies_ms) if self.latencies_ms else None

    def health(self, dropped: int, now: float | None = None) -> tuple[str, str]:
        """The diagnostics' level ("OK", "WARN" or "ERROR") and message; call with `lock` held. Slow is a
        warning: frames are still answered, later, and the queue drops by its policy meanwhile. Frames
        lost, dropped, refused, failed, unsupported or malformed warn for WARN_WINDOW_S after the last
        one (`now`: time.monotonic()); the message counts those of the window."""
        now = time.monotonic() if now is None else now
        totals = (self.lost, dropped, self.refused, self.failed, self.unsupported, self.malformed)
        if not self._marks:  # the node's start: nothing had happened
            self._marks.append((now, (0,) * len(totals)))
        self._marks.append((now, totals))
        while len(self._marks) > 1 and self._marks[1][0] <= now - WARN_WINDOW_S:
            self._marks.popleft()
        lost, dropped, refused, failed, unsupported, malformed = (
            a - b for a, b in zip(totals, self._marks[0][1], strict=True))
        if self.service in ("down", "error"):
            return "ERROR", f"service {self.service}: {self.last_error}"
        if self.service == "slow":
            return "WARN", f"service slow: {self.last_error}"
        if dropped or refused or failed or unsupported or malformed or lost:
            said = f", failed {failed}" if failed else ""
            return "WARN", (f"service {self.service}; in the last {WARN_WINDOW_S:g} s: lost {lost}, dropped "
                            f"{dropped}, refused {refused}{said}, unsupported {unsupported}, malformed "
                            f"{malformed}")
        return "OK", f"service {self.service}"


Answered = Callable[[Frame, Pose2D | None, Observation, float], None]


class Poster:
    """Posts queued frames through `client`, one at a time; `on_answer(frame, pose, answer, latency_ms)` runs
    on the poster's thread for each answered frame, `on_retraction(entry)` for each retraction of the
    stream's closures and `on_epoch(previous, epoch)` when the map's log changes its epoch (all
    publish)."""

    def __init__(self, cfg: Config, client: Client, queue: FrameQueue[Frame], stats: Stats,
                 odometry: OdometryBuffer | None, camera: Callable[[], dict[str, Any] | None],
                 on_answer: Answered, log: Any,
                 on_retraction: Callable[[LoopClosure], None] = lambda entry: None,
                 on_epoch: Callable[[str, str], None] = lambda previous, epoch: None) -> None:
        self.cfg, self.client, self.queue, self.stats = cfg, client, queue, stats
        self.odometry, self.camera, self.on_answer, self.log = odometry, camera, on_answer, log
        self.retractions = RetractionFollower(client, cfg.map_id, cfg.stream, cfg.retractions_poll,
                                              self._retracted, log, on_epoch=on_epoch)
        self._on_retraction = on_retraction
        self._drive = 0  # the drive of the frames posted (`Frame.drive`)
        self.in_flight: Frame | None = None  # the frame being posted
        # A request of `in_flight` may have reached the service, its outcome unknown until it is answered:
        # a stop then must not call it "not posted" (the service may have stored it, or may yet)
        self._sent = False
        #: The map's `revisit_threshold` as read at first contact (None: not read yet, or an older server).
        self.revisit_threshold: float | None = None
        self._stop = threading.Event()
        # Held while a post checks `_stop` and marks its frame sent: once `stop` has set `_stop` under it,
        # no request starts, so a frame not marked sent then is never sent
        self._sending = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="cortexloc-poster", daemon=True)
        self._last_probe = 0.0
        self._map_gone = False  # a 404 map-not-found after first contact, said in the log
        self._said = LogLimiter()  # refused frames, faults: one line a minute of each kind

    def start(self) -> None:
        self._thread.start()

    def stop(self, timeout: float | None = None) -> str:
        """Stops posting and waits for the thread, by default `request_timeout` + 1 s (a post under way
        ends within its timeout); what it leaves unposted, as a log line ("" for nothing).

        The line tells frames never sent (queued, or taken but not yet sent) from the frame whose request
        was sent and not answered: that one may be stored (its request still under way, or its reply lost
        or late past `request_timeout`), so it is never called "not posted". An outside probe: a post
        whose reply came later than `request_timeout` ended the thread within the wait, the line said
        "1 in flight not posted", and the service had stored the frame."""
        with self._sending:
            self._stop.set()
        self._thread.join(self.cfg.request_timeout + 1.0 if timeout is None else timeout)
        queued, unsent, sent = self.unposted()
        if not (queued or unsent or sent):
            return ""
        frames = f"{queued} frame{'s' * (queued != 1)} queued"
        line = (f"stopping: {frames} and 1 in flight not posted (never sent)" if unsent
                else f"stopping: {frames} not posted")
        if sent and self._thread.is_alive():
            line += "; 1 frame sent whose request had not ended (the service may yet store it)"
        elif sent:  # its reply lost, or late past request_timeout
            line += "; 1 frame sent whose answer did not come (the service may have stored it)"
        return line

    # -------------------------------------------------------------------------------------- thread

    def _run(self) -> None:
        """The thread. Nothing ends it but `stop` (module docstring): an exception that reaches here (a
        fault of the node's own) gives up the frame under way, is said at ERROR, and the loop goes on
        after a backoff. An outside probe: one reply that did not validate ended the thread, and the
        node ran on posting nothing while diagnostics said the service was up."""
        opened = False
        delay = BACKOFF_S
        while not self._stop.is_set():
            try:
                if not opened:
                    self._first_contact()  # until it is done, or the poster stops
                    opened = True
                    continue
                self._step()
            except Exception as e:
                frame, self.in_flight, self._sent = self.in_flight, None, False
                if frame is not None:
                    self._give_up(frame, e)
                delay = self._back_off(self._trouble(e, delay), delay)
            else:
                delay = BACKOFF_S

    def _step(self) -> None:
        """One frame posted, or the idle probe; then the retractions' poll when it is due."""
        frame = self.queue.get(timeout=0.2)
        if frame is not None:
            self._post(frame)
        elif time.monotonic() - self._last_probe >= PROBE_S:
            self._probe()
        if self.retractions.due() and not self._stop.is_set():
            try:
                self.retractions.poll()
            except Exception as e:  # a page it cannot read (a proxy's, a newer server's): posting goes on
                self._error("retractions", f"following the loop-closure log failed: {e!r}")

    def _error(self, kind: str, text: str) -> None:
        """An ERROR line, at most one a minute of `kind` (with how many more since)."""
        line = self._said.line(kind, text)
        if line is not None:
            self.log.error(line)

    def _give_up(self, frame: Frame, e: BaseException) -> None:
        with self.stats.lock:
            self.stats.failed += 1
        self._error("given-up", f"frame {frame.stamp.ns} given up after a fault of the node's own: {e!r} "
                                f"(not posted, or posted and its answer lost; counted as `failed`)")

    def unposted(self) -> tuple[int, int, int]:
        """What a stop leaves: (frames queued, the frame in flight if none of its requests was sent, the
        frame in flight if one was: its outcome unknown), the last two 0 or 1."""
        in_flight = self.in_flight is not None
        return len(self.queue), int(in_flight and not self._sent), int(in_flight and self._sent)

    def _retracted(self, entry: LoopClosure) -> None:
        with self.stats.lock:
            self.stats.retractions += 1
        try:
            self._on_retraction(entry)
        except Exception as e:  # e.g. publishing while SIGTERM shuts the context down
            if not self._stop.is_set():
                self.log.error(f"publishing the retraction of closure {entry.retracts} failed: {e!r}")

    def _probe(self) -> None:
        self._last_probe = time.monotonic()
        try:
            self.client.ready()
        except InvalidResponseError as e:
            self._trouble(e, PROBE_S)
        except CortexlocError as e:
            self._state("error", f"not ready: {e}")
        except httpx.HTTPError as e:
            self._transport_state(e)
        except Exception as e:  # a fault of the node's own: said, and the probe goes on
            self._trouble(e, PROBE_S)
        else:
            self._state("up", "")

    def _transport_state(self, e: httpx.HTTPError) -> None:
        """A request that got no answer: `slow` when connected but no reply came within the timeout (the
        service is busy: a request that could not connect in time is `down`), else `down`."""
        if isinstance(e, httpx.TimeoutException) and not isinstance(e, httpx.ConnectTimeout):
            self._state("slow", f"{e.__class__.__name__}: no reply within request_timeout "
                                f"({self.cfg.request_timeout:g} s)")
        else:
            self._state("down", f"{e.__class__.__name__}: {e}")

    def _state(self, service: str, error: str, said: bool = False) -> None:
        """Diagnostics' service state; a change logged (WARN, or INFO when it is up again) unless the caller
        `said` it already."""
        with self.stats.lock:
            if service != self.stats.service and service != "up" and not said:
                self.log.warning(f"cortexloc service {service}: {error}; retrying")
            elif service != self.stats.service:
                self.log.info(f"cortexloc service up at {self.cfg.service_url}")
                # recovered: the outage's error is history (the log has it); an operator reading
                # "service up" beside an old error would look for a fault that is gone
                self.stats.last_error = ""
            self.stats.service = service
            if error:
                self.stats.last_error = error

    def _metadata(self, frame: Frame, pose: Pose2D | None) -> dict[str, Any]:
        # `stamp` in seconds is what the service's export reads; `stamp_ns` (text: past 2^53) is exact.
        meta: dict[str, Any] = {"stamp": frame.stamp.seconds, "stamp_ns": str(frame.stamp.ns),
                                "frame_id": frame.frame_id}
        if self.cfg.trail:
            meta["trail"] = self.cfg.trail
        if pose is not None:
            meta["pose"] = pose.as_metadata()
        camera = self.camera()
        if camera is not None:
            meta["camera"] = camera
        return meta

    def _post(self, frame: Frame) -> None:
        # in flight until it is answered or refused: a stop meanwhile leaves it unposted, or, once one of
        # its requests was sent, of unknown outcome
        self._sent = False
        self.in_flight = frame
        if frame.drive != self._drive:
            self._new_drive(frame.drive)
        if self._post_frame(frame):
            self.in_flight = None

    def _post_frame(self, frame: Frame) -> bool:
        """Posts `frame` until it is answered or refused (True), or the poster stops (False)."""
        pose = None
        if self.odometry is not None and not frame.stamped:
            with self.stats.lock:  # a pose matched by a stamp that is not the frame's would be another's
                self.stats.no_pose += 1
        elif self.odometry is not None:
            # the nearest pose may be the one just after the stamp, not in yet: wait for it here (never
            # on the executor), at most odom_tolerance + ODOM_MARGIN_S after the frame arrived
            deadline = frame.arrived + self.cfg.odom_tolerance_ns / 1e9 + ODOM_MARGIN_S
            pose = self.odometry.wait_match(frame.stamp, deadline)
            if pose is None:
                with self.stats.lock:
                    self.stats.no_pose += 1
            elif not pose.is_postable():  # the node takes none in; the service would refuse it (422)
                pose = None
                with self.stats.lock:
                    self.stats.no_pose += 1
        meta = self._metadata(frame, pose)
        delay = BACKOFF_S
        faults = 0
        reached = False  # an earlier request of this frame may have reached the service
        while True:
            with self._sending:  # `stop` sets `_stop` under it: no request starts after a stop
                if self._stop.is_set():
                    break
                self._sent = True
            t0 = time.perf_counter()
            try:
                answer = self.client.observe(
                    self.cfg.map_id, frame.image, colour=frame.colour,  # type: ignore[arg-type]
                    stream=self.cfg.stream, learn=self.cfg.learn, top_k=self.cfg.top_k, metadata=meta,
                    idempotency_key=frame.key)
            except (httpx.ConnectError, httpx.ConnectTimeout) as e:
                # no connection: this request never left (the node's client tries once, so no earlier try
                # within it left either); the frame is as unsent as before it
                self._sent = reached
                wait = self._trouble(e, delay)
            except CortexlocError as e:
                reached = True
                if e.status in FRAME_REFUSALS:
                    with self.stats.lock:
                        self.stats.refused += 1
                        self.stats.last_error = str(e)
                    # at camera rate (NaN metadata, oversize frames): one line a minute of each kind
                    kind, text = f"refused:{e.status}:{e.slug}", f"frame {frame.stamp.ns} refused: {e}"
                    line = self._said.line(kind, text)
                    if line is not None:
                        self.log.warning(line)
                    return True
                if e.status == 404 and e.slug == "map-not-found" and not self._map_gone:
                    self._map_gone = True  # said once an outage: the log is no per-retry stream
                    self.log.error(f"map {self.cfg.map_id!r} not found (deleted while the node runs?): "
                                   f"frames wait until it is back (restore it, or restart the node); it is "
                                   f"not created again, which would reuse its seqs for other frames")
                wait = self._trouble(e, delay)
            except httpx.HTTPError as e:  # a reply lost or late: the frame may have been stored
                reached = True
                wait = self._trouble(e, delay)
            except Exception as e:  # a fault of the node's own: retried, then the frame given up
                reached = True  # raised before or after its request left: taken as sent
                wait = self._trouble(e, delay)
                faults += 1
                if faults >= FAULT_TRIES:
                    self._give_up(frame, e)
                    return True
            else:
                self._map_gone = False
                latency = (time.perf_counter() - t0) * 1e3
                revisit = bool(answer.place and answer.place.revisit)
                with self.stats.lock:
                    self.stats.answered += 1
                    self.stats.revisits += revisit
                    self.stats.last_latency_ms = latency
                    self.stats.latencies_ms.append(latency)
                    self.stats.last_error = ""  # a refused frame's too: the trouble is over
                self._state("up", "")
                try:
                    self.on_answer(frame, pose, answer, latency)
                except Exception as e:  # e.g. publishing while SIGTERM shuts the context down
                    if not self._stop.is_set():
                        self.log.error(f"publishing the answer of frame {frame.stamp.ns} failed: {e!r}")
                return True
            delay = self._back_off(wait, delay)
        return False

    def _trouble(self, e: Exception, delay: float) -> float:
        """Diagnostics' state after a request that failed; the seconds to wait before its retry. A reply the
        client cannot read and an exception no code expects are said at ERROR (once a minute a kind)."""
        if isinstance(e, InvalidResponseError):
            self._error("invalid-response", f"a reply from {self.cfg.service_url} that is not the service's "
                                            f"answer (a proxy's page?): {e}; retried with the same key")
            self._state("error", str(e), said=True)
            return delay
        if isinstance(e, CortexlocError):
            self._state("error", str(e))
            return e.retry_after if e.retry_after is not None else delay
        if isinstance(e, httpx.HTTPError):
            self._transport_state(e)
            return delay
        self._error(f"fault:{type(e).__name__}", f"cortexloc poster fault, going on: {e!r}")
        self._state("error", f"fault of the node's own: {e!r}", said=True)
        return delay

    def _back_off(self, wait: float, delay: float) -> float:
        """Counts a retry and waits `wait` (at most MAX_BACKOFF_S); the next backoff."""
        with self.stats.lock:
            self.stats.retries += 1
        self._stop.wait(min(wait, MAX_BACKOFF_S))
        return min(delay * 2, MAX_BACKOFF_S)

    def _new_drive(self, drive: int) -> None:
        """The stream reset on the service before the first frame of a new drive, retried like a post until
        the service answers (a map missing is an error, as for a post)."""
        delay = BACKOFF_S
        while not self._stop.is_set():
            try:
                had = self.client.reset_stream(self.cfg.map_id, self.cfg.stream).had_context
            except Exception as e:
                wait = self._trouble(e, delay)
            else:
                self._state("up", "")
                self._drive = drive
                dropped = " (the last drive's context dropped)" if had else ""
                self.log.info(f"stream {self.cfg.stream!r} reset on map {self.cfg.map_id!r}: a new drive, "
                              f"the camera's stamps went back{dropped}")
                return
            delay = self._back_off(wait, delay)

    def _first_contact(self) -> None:
        """The map made sure of and the stream reset (module docstring), retried until the service
        answers; frames wait in the queue meanwhile."""
        delay = BACKOFF_S
        while not self._stop.is_set():
            try:
                opened = self._open()
            except Exception as e:
                wait = self._trouble(e, delay)
            else:
                if opened:
                    self._state("up", "")
                    return
                wait = delay
            delay = self._back_off(wait, delay)

    def _open(self) -> bool:
        """The map made sure of (its `revisit_threshold` read, for the markers' colours) and the stream
        reset; False: the service refused to create the map (said at ERROR, and on diagnostics), to be
        tried again."""
        map_id, stream = self.cfg.map_id, self.cfg.stream
        try:
            found = self.client.get_map(map_id)
            if not self.cfg.resume:
                dropped = " (the last drive's context dropped)" if self.client.reset_stream(
                    map_id, stream).had_context else ""
                self.log.info(f"stream {stream!r} reset on map {map_id!r}: a new drive{dropped}")
        except CortexlocError as e:
            if not (e.status == 404 and e.slug == "map-not-found" and self.cfg.learn):
                raise
            try:  # a new map holds no stream context: nothing to reset
                found = self.client.create_map(map_id)
            except CortexlocError as e2:
                if e2.slug == "map-exists":  # another node created it meanwhile
                    self.log.info(f"map {map_id!r} exists: created meanwhile (by another node?)")
                    self.revisit_threshold = self.client.get_map(map_id).revisit_threshold
                    return True
                if e2.problem is None or e2.status == 503:
                    raise  # a proxy's page, a reply it cannot read, the service busy: retried as such
                # 409 map-limit or memory-budget, 422 invalid-configuration, ...: every frame would be 404.
                # Before, any 409 read as "created by another node", and the log said "created map".
                self._error(f"create:{e2.slug}", f"map {map_id!r} cannot be created: {e2}; frames wait in "
                                                 f"the queue and its creation is retried")
                self._state("error", f"map {map_id!r} cannot be created: {e2}", said=True)
                return False
            self.log.info(f"created map {map_id!r} (the service's defaults)")
        self.revisit_threshold = found.revisit_threshold
        return True
