"""The scale-out's HTTP ingress: the same `/v1` API as `cortexloc serve`, over shards (docs/scaling.md;
docs/design/service.md §9).

The ingress holds no map. It keeps the single process's edge: the same pure-ASGI middleware
(security headers, request ids, metrics, upload limits and body deadlines), the same API-key guards
(`service.deps`) and the same problem+json table (`service.errors`). A request about one map
(`/v1/maps/{map_id}/...`) goes whole to the shard that owns the map, where the single-process app
answers it with its own routes (service.scaleout.shard); what spans maps is gathered here from every
shard: `GET /v1/maps`, `POST /v1/maps` (on the least loaded shard), `GET /v1/memory`, `/metrics` (each
sample labelled with its shard) and `/readyz` (ready when every shard is).
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from importlib import metadata
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Request, Response
from fastapi.responses import JSONResponse
from prometheus_client import CONTENT_TYPE_LATEST
from prometheus_client.core import Metric
from prometheus_client.exposition import generate_latest
from prometheus_client.parser import text_string_to_metric_families
from prometheus_client.registry import CollectorRegistry

from service.app import install_edge
from service.deps import ApiKeyDep, ReadKeyDep
from service.errors import Problem, problem_responses
from service.maps.errors import ShardUnavailable
from service.maps.ids import new_map_id
from service.metrics import Metrics
from service.request_ids import REQUEST_ID_HEADER, request_id_var
from service.routes import QueryRulesDep
from service.routes.health import UNNAMED_ERROR, readiness_reply
from service.scaleout.shards import ShardSet
from service.schemas import BudgetModel, Health, MapList, Readiness
from service.settings import Settings
from service.ui import mount_viewer

__all__ = ["create_ingress_app"]

log = logging.getLogger("cortexloc.scaleout")

#: Headers that describe one hop, not the request: the shard's transport sets its own.
_HOP = {"host", "content-length", "transfer-encoding", "connection", "keep-alive"}


#: The methods whose body the ingress reads and forwards (the API takes none with GET or DELETE).
_BODY_METHODS = frozenset({"POST", "PATCH", "PUT"})

def _out_headers(request: Request) -> list[tuple[str, str]]:
    headers = [(k, v) for k, v in request.headers.items() if k.lower() not in _HOP]
    rid = request_id_var.get()
    if rid:  # the shard's logs and reply carry the ingress's request id
        headers = [(k, v) for k, v in headers if k.lower() != REQUEST_ID_HEADER.lower()]
        headers.append((REQUEST_ID_HEADER, rid))
    return headers


def _reply(reply: tuple[int, list[tuple[str, str]], bytes]) -> Response:
    status, headers, body = reply
    out = Response(content=body, status_code=status)
    for k, v in headers:
        if k.lower() not in _HOP:
            out.headers.append(k, v)
    return out


def get_shards(request: Request) -> ShardSet:
    return request.app.state.shards


ShardsDep = Annotated[ShardSet, Depends(get_shards)]


def _ok_json(replies: dict[str, Any]) -> dict[str, Any]:
    """Each shard's JSON body where it answered 200; ShardUnavailable if any did not."""
    out = {}
    for shard, r in replies.items():
        if isinstance(r, ShardUnavailable):
            raise r
        if r[0] != 200:
            raise ShardUnavailable("*", shard, f"its shard {shard} answered HTTP {r[0]}")
        out[shard] = json.loads(r[2])
    return out


def _merge_metrics(texts: dict[str, str]) -> bytes:
    """Every shard's Prometheus text, each sample labelled `shard`, one family per name."""
    families: dict[str, Metric] = {}
    for shard, text in texts.items():
        for fam in text_string_to_metric_families(text):
            merged = families.setdefault(fam.name, Metric(fam.name, fam.documentation, fam.type, fam.unit))
            merged.samples += [s._replace(labels={**s.labels, "shard": shard}) for s in fam.samples]

    class Gathered:
        def collect(self) -> list[Metric]:
            return list(families.values())

    registry = CollectorRegistry(auto_describe=False)
    registry.register(Gathered())  # type: ignore[arg-type]
    return generate_latest(registry)


def _router() -> APIRouter:
    # The query rules of every route but the probes' (service.routes.check_request_parameters) on the
    # routes answered here; a route forwarded whole (`one_map`) declares nothing and leaves them to its
    # shard.
    router = APIRouter()

    @router.get("/healthz")
    async def healthz() -> Health:
        return Health(status="ok")

    @router.get("/readyz", response_model=Readiness, responses=problem_responses(503))
    async def readyz(request: Request, shards: ShardsDep) -> Readiness | JSONResponse:
        """Ready when every shard is: each shard's own /readyz checks, under its name."""
        replies = await shards.each("GET", "/readyz", "", _out_headers(request))
        checks: dict[str, dict[str, Any]] = {}
        warnings: list[str] = []
        for shard, r in replies.items():
            if isinstance(r, ShardUnavailable):  # its own words: which shard, and that it restarts
                checks[shard] = {"status": "fail", "error": str(r)}
                continue
            body = json.loads(r[2])
            ok = r[0] == 200
            checks[shard] = {"status": "pass" if ok else "fail", "checks": body.get("checks", {}),
                             **({} if ok else {"error": body.get("detail", f"HTTP {r[0]}")})}
            warnings += [f"{shard}: {w}" for w in body.get("warnings", [])]
        if not shards.reconciled:  # the map table does not know every shard's maps yet
            # the reconcile's reason is any exception's text (logged there), which may name files of the
            # host; the shards hide their own where reads need the key (service.routes.health)
            error = getattr(request.app.state, "shards_error", None)
            named = not request.app.state.settings.api_key_reads
            checks["routes"] = {"status": "fail", "error": "the shards' maps are being read" if error is None
                                else error if named else UNNAMED_ERROR}
        return readiness_reply(request, checks, warnings)

    @router.get("/metrics", response_class=Response, dependencies=[ReadKeyDep, QueryRulesDep],
                responses=problem_responses(401, 503))
    async def metrics(request: Request, shards: ShardsDep) -> Response:
        replies = await shards.each("GET", "/metrics", "", _out_headers(request))
        texts = {}
        for shard, r in replies.items():
            if isinstance(r, ShardUnavailable):
                raise r
            texts[shard] = r[2].decode()
        return Response(_merge_metrics(texts), media_type=CONTENT_TYPE_LATEST)

    v1 = APIRouter(prefix="/v1", dependencies=[ReadKeyDep], responses=problem_responses(401))

    @v1.get("/maps", responses=problem_responses(503), dependencies=[QueryRulesDep])
    async def list_maps(request: Request, shards: ShardsDep) -> MapList:
        """Every shard's maps, each listed by the shard that owns it."""
        shards.require_reconciled()
        bodies = _ok_json(await shards.each("GET", "/v1/maps", request.url.query, _out_headers(request)))
        owner = {r.map_id: r.shard for r in shards.table.all()}
        maps = [m for shard, b in bodies.items() for m in b["maps"] if owner.get(m["map_id"]) == shard]
        return MapList.model_validate({"maps": sorted(maps, key=lambda m: m["map_id"])})

    # (the body is read as it came and forwarded; declared, so the request rules let it through)
    @v1.post("/maps", dependencies=[QueryRulesDep, ApiKeyDep],
             responses=problem_responses(400, 401, 409, 422, 503),
             openapi_extra={"requestBody": {"content": {"application/json": {}}}})
    async def create_map(request: Request, shards: ShardsDep) -> Response:
        """Created on the shard with the fewest maps, then routed there."""
        body = await request.body()
        try:
            doc = json.loads(body or b"{}")
        except ValueError:
            doc = None
        if isinstance(doc, dict) and not doc.get("map_id"):  # the id is chosen here, as by the shard
            doc["map_id"] = new_map_id(request.headers.get("Idempotency-Key"))
            body = json.dumps(doc).encode()
        map_id = doc.get("map_id") if isinstance(doc, dict) else None
        if not isinstance(map_id, str):  # let a shard answer the malformed body with its 4xx
            return _reply(await shards.call(shards.shards[0], "request", "POST", "/v1/maps",
                                            request.url.query, _out_headers(request), body))
        return _reply(await shards.create(map_id, "/v1/maps", request.url.query, _out_headers(request), body))

    @v1.get("/memory", responses=problem_responses(503), dependencies=[QueryRulesDep])
    async def memory(request: Request, shards: ShardsDep) -> BudgetModel:
        """Every shard's budget summed; the maps' reservations of each (by the shard that owns them)."""
        shards.require_reconciled()
        bodies = _ok_json(await shards.each("GET", "/v1/memory", "", _out_headers(request)))
        owner = {r.map_id: r.shard for r in shards.table.all()}
        summed = {k: sum(b[k] for b in bodies.values()) for k in (
            "total_bytes", "used_bytes", "reserve_bytes", "free_bytes", "encoders_bytes",
            "process_rss_bytes")}
        maps = [m for shard, b in bodies.items() for m in b["maps"] if owner.get(m["map_id"]) == shard]
        first = next(iter(bodies.values()))
        return BudgetModel.model_validate({**summed, "source": first["source"], "maps": maps})

    async def one_map(request: Request, shards: ShardsDep, map_id: str, rest: str = "") -> Response:
        """A request about one map, answered by its shard, at the path as it came (still percent-encoded).

        Raises:
            Problem: 400 invalid-parameter for a "." or ".." segment sent as it is.
        """
        # Decoded, a stream or snapshot id ".." sent as "%2E%2E" (as the typed client sends it) would be a
        # dot segment the forward resolves: `…/snapshots/%2E%2E` was DELETE /v1/maps/m on the shard, and
        # the table kept routing to the deleted map. Sent bare, the segment is refused: nothing of ours
        # sends one, and `m0/a/../../m1` would reach map m1 on m0's shard, past the table.
        raw = request.scope.get("raw_path") or request.url.path.encode()
        path = raw.split(b"?", 1)[0].decode("latin-1")
        if any(segment in (".", "..") for segment in path.split("/")):
            raise Problem(400, "invalid-parameter",
                          "the path has a '.' or '..' segment: an id of '.' or '..' goes percent-encoded",
                          errors=[{"location": "path", "name": "path", "message": "dot segment"}])
        if request.method == "DELETE" and not rest:
            return _reply(await shards.delete(map_id, path, request.url.query, _out_headers(request)))
        # The map is looked up before a byte of the body is read, and only a method with a body reads
        # one: a body sent to an id no shard has, or with a GET, would otherwise hold its share of the
        # upload budget (docs/design/service.md §3) until its deadline, a share per made-up id.
        shards.owner(map_id)
        body = await request.body() if request.method in _BODY_METHODS else b""
        return _reply(await shards.forward(map_id, request.method, path, request.url.query,
                                           _out_headers(request), body))

    # Reads under the read guard (the router's); every write needs the key here, as on the shard.
    for path in ("/maps/{map_id}", "/maps/{map_id}/{rest:path}"):
        v1.add_api_route(path, one_map, methods=["GET"], include_in_schema=False)
        v1.add_api_route(path, one_map, methods=["POST", "PATCH", "PUT", "DELETE"], include_in_schema=False,
                         dependencies=[ApiKeyDep])
    router.include_router(v1)
    return router


def create_ingress_app(settings: Settings, make_shards: Callable[[], ShardSet]) -> FastAPI:
    """The ingress app; `make_shards` builds its `ShardSet` at startup (Ray handles exist then).

    Its OpenAPI document is the shards' (`/openapi.json` forwarded): the API is theirs."""
    metrics = Metrics()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        shards = make_shards()
        app.state.shards = shards
        app.state.shards_error = None

        async def reconcile() -> None:
            """Until it succeeds (a shard may still be starting); /readyz fails meanwhile."""
            while True:
                try:
                    await shards.reconcile()
                    app.state.shards_error = None
                    return
                except Exception as e:
                    log.warning("cannot read the shards' maps yet: %s", e)
                    app.state.shards_error = f"the shards' maps could not be read: {type(e).__name__}: {e}"
                    await asyncio.sleep(5)

        task = asyncio.get_running_loop().create_task(reconcile())
        yield
        task.cancel()
        shards.table.close()

    app = FastAPI(title="cortexloc (Ray Serve ingress)", version=metadata.version("cortexloc"),
                  lifespan=lifespan, openapi_url=None, docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.metrics = metrics
    install_edge(app, metrics)  # the single process's edge: the same limits, ids, metrics, headers
    app.include_router(_router())

    @app.get("/openapi.json", include_in_schema=False)
    async def openapi(request: Request, shards: ShardsDep) -> Response:
        return _reply(await shards.call(shards.shards[0], "request", "GET", "/openapi.json", "",
                                        _out_headers(request), b""))

    mount_viewer(app)
    return app
