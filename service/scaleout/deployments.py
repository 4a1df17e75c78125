"""The Ray Serve application: an encoder deployment, one deployment per map shard, and the ingress
(docs/scaling.md; docs/design/service.md §9). Needs the `ray` extra (`pip install '.[ray]'`).

    cortexloc serve --ray --shards 2 --encoder-replicas 1      # service.cli.serve
    serve run service.scaleout.deployments:build shards=2 encoder_replicas=1 data_dir=/var/cortexloc

- `Encoder`: stateless; `@serve.batch` gathers single images from every shard into one backbone call;
  `encoder_replicas` replicas, or autoscaled on its queue (`autoscale=true`: 1..`encoder_replicas`,
  Ray Serve's target of ongoing requests per replica).
- `shard-<i>`: exactly one replica (a map has one owner and one writer); `data_dir/shard-<i>` is its
  data directory, where a restarted replica recovers its maps. Its health is checked every second,
  so that Ray replaces a dead replica within seconds.
- `Ingress`: the HTTP API at `/`; the map -> shard table is `data_dir/shards.sqlite`.

Every replica reads the same CORTEXLOC_* settings: those of the process that builds the application
(passed in its runtime environment), the data directory excepted.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from ray import serve
from ray.serve.handle import DeploymentHandle

from service.scaleout.embedding import EmbeddingService, EmbedReply, EmbedRequest
from service.scaleout.ingress import create_ingress_app
from service.scaleout.shard import ForwardedReply, ShardHost
from service.scaleout.shards import ShardSet
from service.settings import Settings

__all__ = ["APP_NAME", "Encoder", "Ingress", "Shard", "build", "build_app"]

#: The application's name in Ray Serve (`cortexloc shards move` finds the ingress by it).
APP_NAME = "cortexloc"


def _settings(env: dict[str, str], data_dir: Path) -> Settings:
    return Settings.from_env({**env, "CORTEXLOC_DATA_DIR": str(data_dir)})


class _Replica:
    def pid(self) -> int:
        """The replica's process id (the failure tests kill it: tests/e2e/test_scaleout.py)."""
        return os.getpid()


@serve.deployment(health_check_period_s=1, health_check_timeout_s=30)
class Encoder(_Replica):
    """Images -> features (1, D), batched across shards."""

    def __init__(self, env: dict[str, str], data_dir: str, max_batch: int) -> None:
        self.service = EmbeddingService(_settings(env, Path(data_dir)))
        self.embed.set_max_batch_size(max_batch)

    def info(self, backbone: str) -> dict[str, Any]:
        return self.service.info(backbone)

    @serve.batch(max_batch_size=16, batch_wait_timeout_s=0.005)
    async def embed(self, batch: list[EmbedRequest]) -> list[EmbedReply]:
        import anyio

        return await anyio.to_thread.run_sync(self.service.embed_batch, batch)


@serve.deployment(num_replicas=1, health_check_period_s=1, health_check_timeout_s=30,
                  max_ongoing_requests=64, graceful_shutdown_timeout_s=10)
class Shard(_Replica):
    """One shard: the single-process app on `data_dir` (service.scaleout.shard)."""

    async def __init__(self, env: dict[str, str], data_dir: str, encoder: DeploymentHandle) -> None:
        def info(backbone: str) -> dict[str, Any]:
            return encoder.info.remote(backbone).result()

        self.host = ShardHost(_settings(env, Path(data_dir)), info, encoder.embed.remote)
        await self.host.start()

    async def request(self, method: str, path: str, query: str, headers: list[tuple[str, str]],
                      body: bytes) -> ForwardedReply:
        return await self.host.request(method, path, query, headers, body)

    def map_ids(self) -> list[str]:
        return self.host.map_ids()

    async def import_tar(self, tar: bytes) -> str:
        return await self.host.import_tar(tar)

    async def __del__(self) -> None:
        await self.host.stop()


@serve.deployment(health_check_period_s=1, health_check_timeout_s=30, max_ongoing_requests=256)
@serve.ingress()
class Ingress(_Replica):
    """The HTTP API over the shards (service.scaleout.ingress); `move` is `cortexloc shards move`."""

    def __init__(self, env: dict[str, str], data_dir: str, shards: dict[str, DeploymentHandle]) -> None:
        self.settings = _settings(env, Path(data_dir))
        self.handles = shards
        self.table_path = Path(data_dir) / "shards.sqlite"
        self.shards: ShardSet | None = None

    def _make_shards(self) -> ShardSet:
        async def call(shard: str, method: str, *args: Any) -> Any:
            return await getattr(self.handles[shard], method).remote(*args)

        self.shards = ShardSet(list(self.handles), call, self.table_path)
        return self.shards

    def __serve_build_asgi_app__(self) -> Any:
        return create_ingress_app(self.settings, self._make_shards)

    async def move(self, map_id: str, target: str) -> dict[str, Any]:
        """Move a map between shards (`ShardSet.move`); internal requests carry the API key."""
        assert self.shards is not None
        key = self.settings.api_key
        return await self.shards.move(map_id, target, [("X-API-Key", key)] if key else [])

    async def routes(self) -> list[tuple[str, str, str]]:
        """The map -> shard table: (map_id, shard, state)."""
        assert self.shards is not None
        return [tuple(r) for r in self.shards.table.all()]


def build_app(data_dir: Path, *, shards: int = 2, encoder_replicas: int = 1, autoscale: bool = False,
              max_batch: int = 16, env: dict[str, str] | None = None) -> Any:
    """The bound application.

    Args:
        data_dir: the root: `shard-<i>/` per shard and `shards.sqlite` (each shard's directory must be
            on a volume that its replica's node mounts; docs/scaling.md).
        shards: shard deployments (fixed: a map's shard is in the table).
        encoder_replicas: encoder replicas (the maximum when `autoscale`).
        env: CORTEXLOC_* of every replica (default: this process's).
    """
    env = {k: v for k, v in (os.environ if env is None else env).items() if k.startswith("CORTEXLOC_")}
    root = Path(data_dir).resolve()
    runtime = {"runtime_env": {"env_vars": env}}
    scaling: dict[str, Any] = (
        {"autoscaling_config": {"min_replicas": 1, "max_replicas": encoder_replicas,
                                "target_ongoing_requests": 2 * max_batch}}
        if autoscale else {"num_replicas": encoder_replicas})
    encoder = Encoder.options(ray_actor_options=runtime, max_ongoing_requests=4 * max_batch,
                              **scaling).bind(env, str(root), max_batch)
    bound = {f"shard-{i}": Shard.options(name=f"shard-{i}", ray_actor_options=runtime)
             .bind(env, str(root / f"shard-{i}"), encoder) for i in range(shards)}
    return Ingress.options(ray_actor_options=runtime).bind(env, str(root), bound)


def build(args: dict[str, str]) -> Any:
    """`serve run service.scaleout.deployments:build shards=2 encoder_replicas=1 data_dir=DIR`."""
    return build_app(Path(args.get("data_dir", os.environ.get("CORTEXLOC_DATA_DIR", "var"))),
                     shards=int(args.get("shards", 2)), encoder_replicas=int(args.get("encoder_replicas", 1)),
                     autoscale=str(args.get("autoscale", "false")).lower() in ("1", "true", "yes"),
                     max_batch=int(args.get("max_batch", 16)))
