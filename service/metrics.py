"""The service's Prometheus collectors and the middleware that feeds them (docs/design/service.md §1.6);
`service/routes/metrics.py` serves them as `GET /metrics`.

Each app owns a `Metrics` (its own `CollectorRegistry`, never the process-global one), so tests can build
several apps. What is here:

- `cortexloc_requests_total{method,route,status}` and `cortexloc_request_duration_seconds{...}`, by
  `MetricsMiddleware` (pure ASGI); `route` is the route template (`/v1/maps/{map_id}`), `<unmatched>`
  for paths no route knows, so label values stay bounded;
- `cortexloc_requests_in_flight`;
- `cortexloc_encoder_info{weights,encoder} 1`;
- `cortexloc_stage_duration_seconds{stage}`, fed by `Metrics.observe_stage` / `Metrics.time_stage`;
- `cortexloc_upload_inflight_bytes` and `cortexloc_upload_refusals_total{reason}`, fed by
  `service.limits.UploadLimitMiddleware`.

Other components register their own collectors on `metrics.registry` (e.g. per-map gauges).

Example:
    >>> with metrics.time_stage("encode"):
    ...     codes = encoder.encode([data])
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    generate_latest,
)
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.maps.recovery.snapshots import disk_use
from service.routing import iter_routes

__all__ = ["Metrics", "MetricsMiddleware"]

PREFIX = "cortexloc_"
UNMATCHED = "<unmatched>"
_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
STAGE_BUCKETS = (0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
REQUEST_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)


class Metrics:
    """The collectors of one app, in their own registry."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.requests = Counter(PREFIX + "requests", "HTTP requests by method, route template and status",
                                ["method", "route", "status"], registry=self.registry)
        self.request_duration = Histogram(PREFIX + "request_duration_seconds",
                                          "HTTP request latency by method, route template and status",
                                          ["method", "route", "status"], buckets=REQUEST_BUCKETS,
                                          registry=self.registry)
        self.in_flight = Gauge(PREFIX + "requests_in_flight", "HTTP requests being served",
                               registry=self.registry)
        self.stage_duration = Histogram(PREFIX + "stage_duration_seconds",
                                        "Duration of one request pipeline stage (decode, encode, tm, ...)",
                                        ["stage"], buckets=STAGE_BUCKETS, registry=self.registry)
        self.encoder_info = Gauge(PREFIX + "encoder_info", "The loaded encoder (value always 1)",
                                  ["weights", "encoder"], registry=self.registry)
        self.upload_inflight_bytes = Gauge(
            PREFIX + "upload_inflight_bytes",
            "Body bytes reserved by the requests being read or served (CORTEXLOC_MAX_INFLIGHT_UPLOAD_BYTES)",
            registry=self.registry)
        self.upload_refusals = Counter(
            PREFIX + "upload_refusals", "Requests refused for their body: too-large (413), timeout (408, the "
            "body-read deadline), budget (503, the in-flight bytes)", ["reason"], registry=self.registry)
        self.observations = Counter(PREFIX + "observations", "Observations answered, by map and mode",
                                    ["map", "learned"], registry=self.registry)
        self._counted: set[str] = set()  # maps with an `observations` series (`count_observation`)
        self.memory_budget = Gauge(PREFIX + "memory_budget_bytes", "CORTEXLOC_MEMORY_BUDGET_BYTES or its "
                                   "default", registry=self.registry)
        self.memory_used = Gauge(PREFIX + "memory_used_bytes", "Bytes of the memory budget the maps and "
                                 "encoders hold", registry=self.registry)
        labels = ["map"]
        self.map_gauges = {
            name: Gauge(PREFIX + "map_" + name, help_, labels, registry=self.registry)
            for name, help_ in (("segments", "Live TM segments"), ("synapses", "Live TM synapses"),
                                ("evictions", "TM segments evicted (least recently used) so far"),
                                ("overruns", "TM synapses destroyed by overrun so far"),
                                ("observations", "Rows held (in the index and their places)"),
                                ("places", "Places with a row held (docs/design/science.md §11.8)"),
                                ("appearances", "Rows held: the appearances of the places"),
                                ("visits", "Consolidated frames in the visit log (no row made)"),
                                ("forgotten", "Rows of places forgotten because the row cap bound, since "
                                              "start (docs/design/science.md §11.9)"),
                                ("memory_bytes", "Preallocated TM bytes"),
                                ("snapshots", "Snapshots of every kind on disk"),
                                ("snapshots_bytes", "Bytes of the snapshots on disk"),
                                ("stream_evictions", "Streams evicted (least recently used, idle "
                                                     "beyond CORTEXLOC_STREAM_KEEP_SECONDS) for a new one, "
                                                     "or over CORTEXLOC_MAX_STREAMS at a recovery, since "
                                                     "start"),
                                ("snapshot_failures", "Automatic snapshots that failed since start (the "
                                                      "rows stay durable; /readyz says why)"))}

    def count_observation(self, map_id: str, learned: bool) -> None:
        """One observation answered on `map_id` (`cortexloc_observations_total{map,learned}`)."""
        self.observations.labels(map=map_id, learned=str(learned).lower()).inc()
        self._counted.add(map_id)

    def update_maps(self, maps: dict) -> None:
        """Refresh the per-map gauges from the map runtimes (at scrape time: always current), and drop
        the observation counts of maps deleted since: a series per map ever made grew without bound (an
        outside probe), past `CORTEXLOC_MAX_MAPS`."""
        for g in self.map_gauges.values():
            g.clear()
        for gone in self._counted - maps.keys():
            for learned in ("true", "false"):
                with suppress(KeyError):  # a mode the map never saw
                    self.observations.remove(gone, learned)
        self._counted &= maps.keys()
        for map_id, rt in maps.items():
            catalog = getattr(rt, "catalog", None)
            if catalog is not None:  # failed maps too: their snapshots take the same disk
                use = disk_use(catalog, map_id)
                self.map_gauges["snapshots"].labels(map=map_id).set(use["snapshot_count"])
                self.map_gauges["snapshots_bytes"].labels(map=map_id).set(use["snapshots_bytes"])
            tm = getattr(rt, "tm", None)
            if tm is None:
                continue
            size = tm.size()
            values = {"segments": size["segments"], "synapses": size["synapses"],
                      "evictions": size["evictions"], "overruns": size["overrun_destroyed"],
                      "observations": len(rt.index), "memory_bytes": size["bytes"],
                      "snapshot_failures": getattr(rt, "snapshot_failures", 0),
                      "stream_evictions": getattr(rt, "stream_evictions", 0)}
            store, place_map = getattr(rt, "store", None), getattr(rt, "place_map", None)
            if store is not None and place_map is not None and not store.closed:
                values.update(places=place_map.places(), appearances=len(rt.index),
                              visits=store.visit_stats()[0], forgotten=getattr(rt, "forgotten", 0))
            for name, v in values.items():
                self.map_gauges[name].labels(map=map_id).set(v)

    def update_budget(self, total: int, used: int) -> None:
        """The process-wide memory budget and what the maps and encoders hold of it (§1.8)."""
        self.memory_budget.set(total)
        self.memory_used.set(used)

    def observe_stage(self, stage: str, seconds: float) -> None:
        """Record one duration of `stage` (seconds)."""
        self.stage_duration.labels(stage=stage).observe(seconds)

    @contextmanager
    def time_stage(self, stage: str) -> Iterator[None]:
        """Time the block as one observation of `stage` (also when it raises)."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.observe_stage(stage, time.perf_counter() - t0)

    def set_encoder(self, weights: str, encoder: str) -> None:
        """`cortexloc_encoder_info{weights,encoder} 1` for the loaded encoder (and only it)."""
        self.encoder_info.clear()
        self.encoder_info.labels(weights=weights, encoder=encoder).set(1)

    def render(self) -> bytes:
        return generate_latest(self.registry)


def _route_template(scope: Scope) -> str:
    route = scope.get("route")
    path = getattr(route, "path", None)
    if isinstance(path, str):
        return path
    app = scope.get("app")  # answered before routing (e.g. a 413): find the route the path would take
    for candidate in iter_routes(getattr(getattr(app, "router", None), "routes", ())):
        try:
            match, _ = candidate.matches(scope)
        except Exception:  # pragma: no cover - a route that cannot match this scope
            continue
        if match in (Match.FULL, Match.PARTIAL) and isinstance(getattr(candidate, "path", None), str):
            return candidate.path
    return UNMATCHED


class MetricsMiddleware:
    """Pure ASGI: counts and times every HTTP request by method, route template and final status."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500
        t0 = time.perf_counter()

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            await send(message)

        self.metrics.in_flight.inc()
        try:
            await self.app(scope, receive, send_status)
        except Exception:
            status = 500
            raise
        finally:
            self.metrics.in_flight.dec()
            method = scope.get("method", "")
            labels = {"method": method if method in _METHODS else "other", "route": _route_template(scope),
                      "status": str(status)}
            self.metrics.requests.labels(**labels).inc()
            self.metrics.request_duration.labels(**labels).observe(time.perf_counter() - t0)
