"""The service configuration: one validated, immutable `Settings` object (docs/design/service.md §8).

Read once from the `CORTEXLOC_*` environment variables by `Settings.from_env()`, which the app
factory's lifespan calls at startup (never at import time), then injected through `deps.SettingsDep`.
Each field `name` is read from `CORTEXLOC_<NAME>` by pydantic-settings' environment source; an empty
(or blank) value counts as unset (the default applies). An invalid value raises `ConfigError`, whose
message names the variable, and stops startup. Unknown `CORTEXLOC_*` names are logged as warnings (with
a suggestion when one is close to a known name). `Settings(...)` itself takes only what it is given:
the environment is read by `from_env` alone, so settings built in code (tests, benchmarks) never pick
up a stray variable.

Example:
    >>> s = Settings.from_env({"CORTEXLOC_PORT": "9000"})
    >>> s.port, s.data_dir
    (9000, PosixPath('var'))
    >>> Settings.from_env({"CORTEXLOC_PORT": "http"})
    Traceback (most recent call last):
    ConfigError: invalid configuration: CORTEXLOC_PORT='http': Input should be a valid integer, ...
"""

from __future__ import annotations

import difflib
import logging
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, ValidationInfo, field_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, PydanticBaseSettingsSource, SettingsConfigDict
from pydantic_settings.sources.utils import parse_env_vars

from models.frontend import backbones, limits
from models.localisation.index import MAX_ROWS

__all__ = ["ENV_PREFIX", "KEY_WHITESPACE", "OTHER_KNOWN_VARIABLES", "ConfigError", "Settings", "env_name"]

log = logging.getLogger("cortexloc.settings")

ENV_PREFIX = "CORTEXLOC_"

#: `CORTEXLOC_*` variables read elsewhere (models, evaluation), so not reported as unknown here.
OTHER_KNOWN_VARIABLES = frozenset({
    "CORTEXLOC_WEIGHTS_DIR",  # models.frontend.weights.default_cache_dir
    "CORTEXLOC_CACHE_DIR",  # cortexloc eval images feature cache
    "CORTEXLOC_SHARED_DATA",  # models.evaluation.datasets
})

# Every number has an upper bound: an absurd value is refused at startup naming its variable, not met
# later as a crash or a host brought down (a thread per encoder worker, torch's C int of threads, int32
# index rows). The bounds are far above any real deployment and each is a value the service runs at.
_LOG_ROWS = 10**9  # rows kept in a map's logs, and the automatic snapshot period
_YEAR_S = 365 * 86_400.0

#: Fields whose value must never appear in a message or a repr.
_SECRET_FIELDS = frozenset({"api_key"})
#: What an API key is compared without at its ends, set and sent (RFC 9110 §5.5: a header field's value
#: has no whitespace there; the HTTP parser drops only the leading).
KEY_WHITESPACE = " \t"


class ConfigError(ValueError):
    """An invalid configuration value; the message names every offending variable.

    Attributes:
        errors: (variable, message) pairs, one per invalid value.
    """

    def __init__(self, errors: list[tuple[str, str]]) -> None:
        self.errors = errors
        super().__init__("invalid configuration: " + "; ".join(f"{var}{msg}" for var, msg in errors))

    @property
    def variables(self) -> list[str]:
        return [var for var, _ in self.errors]


def env_name(field: str) -> str:
    """`max_upload_bytes` -> `CORTEXLOC_MAX_UPLOAD_BYTES`."""
    return ENV_PREFIX + field.upper()


class _Environ(EnvSettingsSource):
    """The `CORTEXLOC_*` variables of a given mapping (not only `os.environ`), values stripped."""

    def __init__(self, settings_cls: type[BaseSettings], environ: Mapping[str, str]) -> None:
        self._environ = environ  # read by `_load_env_vars`, which the base class calls
        super().__init__(settings_cls)

    def _load_env_vars(self) -> Mapping[str, str | None]:
        stripped = {k: v.strip() for k, v in self._environ.items() if k.startswith(ENV_PREFIX)}
        return parse_env_vars(stripped, self.case_sensitive, self.env_ignore_empty, self.env_parse_none_str)


class Settings(BaseSettings):
    """Every knob of the service, with the defaults of docs/design/service.md §8 (plus `api_key`)."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, env_ignore_empty=True, frozen=True,
                                      extra="forbid")

    data_dir: Path = Field(Path("./var"), description="root of all state")
    host: str = Field("127.0.0.1", min_length=1, description="bind address")
    port: int = Field(8000, ge=0, le=65535, description="bind port")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = "INFO"
    log_format: Literal["json", "text"] = "json"
    weights_path: Path | None = Field(None, description="AlexNet weights file (full or trimmed)")
    backbone: str | None = Field(None, description="backbone of new maps (a name registered in "
                                 f"models.frontend.backbones); unset: {backbones.PAPER} when its real "
                                 f"weights are installed, else {backbones.PRETRAINED} (resolved at startup)")
    allow_random_weights: bool = Field(True, description="serve (with a warning) on random weights")
    random_weights_seed: int = Field(0, ge=0, le=2**32 - 1, description="seed of the random fallback weights")
    device: Literal["cpu", "cuda", "auto"] = Field(
        "auto", description="where the backbone runs: cuda (ONNX Runtime's CUDA provider, the `gpu` extra; "
        "refuses to start without it), cpu, or auto (CUDA where it runs, else the CPU with a log line)")
    runtime: Literal["onnxruntime", "torch"] = Field(
        "onnxruntime", description="the backbone's runtime: onnxruntime (its ONNX export, same codes, "
        "faster) or torch (the reference)")
    torch_threads: int = Field(1, ge=1, le=1024)
    encoder_workers: int = Field(1, ge=1, le=256, description="encoder executor size")
    encoder_queue: int = Field(
        32, ge=1, le=100_000, description="encoder queue length (full: 503 overloaded; shared between maps, "
        "docs/design/service.md §6)")
    encode_batch: int = Field(16, ge=1, le=256, description="images one backbone call of the encoder pool "
                              "takes at most: requests that arrive together share a call (the forward's "
                              "cost per image is flat from batch 1 to 16 on ONNX Runtime)")
    encode_wait_ms: float = Field(2.0, ge=0.0, le=1000.0, allow_inf_nan=False,
                                  description="how long an encoder worker with one image waits for more to "
                                  "batch: a few ms, small against a forward (tens of ms), gathers the posts "
                                  "of several streams (0: never wait)")
    encode_chunk: int = Field(limits.DEFAULT_CHUNK, ge=1, le=256, description="images per backbone call "
                              "while the next ones are decoded: small chunks start the backbone sooner")
    max_extractions: int = Field(
        4, ge=1, le=256, description="keyframe extractions running at once, all maps together, the maps in "
        "turn, and in flight per map (full: 503 overloaded); each running one holds ~300 MB at most (a 25 "
        "MP SIFT frame)")
    max_upload_bytes: int = Field(limits.DEFAULT_MAX_BYTES, ge=1, le=2**30, description="request body limit")
    body_timeout_s: float = Field(60.0, gt=0, le=3600, description="a request's whole body must arrive "
                                  "within this many seconds of its start, its head within as many of the "
                                  "connection's opening or previous reply (408 and the connection closed "
                                  "otherwise); 10 MiB at 2 Mbit/s takes 42 s. A streamed reply whose client "
                                  "takes none of its 64 KiB pieces within it is cut")
    max_connections: int = Field(1000, ge=1, le=1_000_000, description="open client connections at most; "
                                 "a further one is answered 503 overloaded and closed at once, so idle or "
                                 "stalled connections cannot use up the process's file descriptors "
                                 "(`cortexloc serve` raises the soft descriptor limit to fit, up to the hard "
                                 "one; below it the cap is lowered to what fits)")
    max_inflight_upload_bytes: int = Field(
        128 * 2**20, ge=1, le=2**36, description="bytes all requests being read or served may hold in "
        "bodies at once (each reserves its Content-Length; a chunked one its limit); past it 503 overloaded "
        "with Retry-After before the body is read")
    max_pixels: int = Field(limits.DEFAULT_MAX_PIXELS, ge=1, le=2**30,
                            description="decoded-image limit (width x height)")
    default_preset: str = Field("cortexloc-default", min_length=1)
    max_map_bytes: int = Field(
        100_000_000, ge=1, le=2**40, description="a map's preallocated bytes at most: its memory, every "
        "stream's localiser state and its projection (very sparse where the dense one would break the "
        "budget)")
    max_maps: int = Field(64, ge=1, le=4096)
    max_observations: int = Field(1_000_000, ge=1, le=MAX_ROWS)
    max_streams: int = Field(64, ge=1, le=65_536)
    stream_keep_seconds: float = Field(600.0, ge=0, le=_YEAR_S, allow_inf_nan=False,
                                       description="a stream that posted within this many seconds is never "
                                       "evicted for a new one; a new stream is refused (429) while every "
                                       "slot is that recent (0: least recently used evicted at once)")
    memory_budget_bytes: int | None = Field(
        None, ge=1, le=2**50, description="RAM all maps and encoders may hold together; unset: half the "
        "smaller of host memory and the cgroup limit (service/maps/runtime/budget.py)")
    max_top_k: int = Field(100, ge=0, le=10_000)
    idempotency_keys: int = Field(
        100_000, ge=1, le=_LOG_ROWS, description="Idempotency-Keys kept per map: those of the learned posts "
        "of the last N seqs and the consolidated posts of the last N visits, in map.sqlite")
    loop_closures: int = Field(
        100_000, ge=1, le=_LOG_ROWS, description="loop closures kept per map in its log (the revisits "
        "streams were told of, map.sqlite): the last N, oldest pruned")
    visits: int = Field(
        100_000, ge=1, le=_LOG_ROWS, description="consolidated frames kept per map in its visit log "
        "(map.sqlite): the last N once a snapshot covers them (docs/design/science.md §11.8)")
    idempotency_cache: int = Field(
        1024, ge=0, le=1_000_000, description="replies of localisation posts (learn=false) kept in memory "
        "per map for their Idempotency-Key")
    verify_neighbours: int = Field(2, ge=0, le=10, description="a revisit candidate is verified against "
                                   "its place's keyframe, then up to N route neighbours each side "
                                   "(docs/design/science.md §12.2); maps with the keyframes option only")
    snapshot_every: int = Field(1000, ge=0, le=_LOG_ROWS, description="automatic snapshot period (0 = off)")
    snapshot_keep: int = Field(
        3, ge=0, le=1000, description="automatic snapshots kept, and whatever their number the one recovery "
        "starts from (0: only that one)")
    snapshot_manual_keep: int = Field(
        10, ge=0, le=100_000, description="manual snapshots kept per map, oldest deleted first (0: no count "
        "limit); so many pre-restore ones too, counted apart")
    snapshot_manual_bytes: int = Field(
        2**31, ge=0, le=2**50, description="bytes of manual snapshots kept per map, oldest deleted first "
        "(0: no byte limit); so many of pre-restore ones too, counted apart")
    lock_wait_s: float = Field(
        30.0, ge=0, le=86_400, allow_inf_nan=False, description="seconds a starting server waits for "
        "another process to let its data directory go (a restart, a rolling update) before it gives up and "
        "exits (docs/design/service.md §4.1)")
    max_import_bytes: int = Field(
        2**33, ge=1, le=2**50, description="most bytes a snapshot tar may unpack to (`cortexloc import`); a "
        "map within max_map_bytes and a million ~3 KB rows fit in 8 GiB")
    api_key: str | None = Field(None, min_length=1, repr=False,
                                description="when set, every write needs it (X-API-Key or Bearer)")
    api_key_reads: bool = Field(False, description="every /v1 read and /metrics need the key too (/healthz "
                                                   "and /readyz stay open); requires CORTEXLOC_API_KEY")

    @field_validator("api_key", mode="before")
    @classmethod
    def _key_as_sent(cls, v: Any) -> Any:
        # The key as a client can send it: a header field's value has no whitespace at its ends (RFC 9110
        # §5.5), so a key set with a trailing space (an env file's) would match no request
        return v.strip(KEY_WHITESPACE) if isinstance(v, str) else v

    @field_validator("data_dir")
    @classmethod
    def _absolute(cls, v: Path) -> Path:
        # Read once at startup, so relative means relative to where the service was started; stored
        # paths are relative to this root, and a root that is itself relative would be applied twice.
        return v.expanduser().resolve()

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper_level(cls, v: Any) -> Any:
        return v.strip().upper() if isinstance(v, str) else v

    @field_validator("log_format", "device", "runtime", mode="before")
    @classmethod
    def _lower(cls, v: Any) -> Any:
        return v.strip().lower() if isinstance(v, str) else v

    @field_validator("max_inflight_upload_bytes")
    @classmethod
    def _room_for_one_upload(cls, v: int, info: ValidationInfo) -> int:
        largest = info.data.get("max_upload_bytes")
        if largest is not None and v < largest:
            raise ValueError(f"must be at least CORTEXLOC_MAX_UPLOAD_BYTES ({largest}): an upload of the "
                             "largest size would never be let in")
        return v

    @field_validator("api_key_reads")
    @classmethod
    def _reads_need_a_key(cls, v: bool, info: ValidationInfo) -> bool:
        if v and info.data.get("api_key") is None:
            raise ValueError("needs CORTEXLOC_API_KEY: there is no key to require")
        return v

    @classmethod
    def settings_customise_sources(cls, settings_cls: type[BaseSettings],
                                   init_settings: PydanticBaseSettingsSource,
                                   env_settings: PydanticBaseSettingsSource,
                                   dotenv_settings: PydanticBaseSettingsSource,
                                   file_secret_settings: PydanticBaseSettingsSource,
                                   ) -> tuple[PydanticBaseSettingsSource, ...]:
        # Only the arguments: `from_env` is the one place that reads the environment (once, at startup).
        return (init_settings,)

    @classmethod
    def variables(cls) -> dict[str, str]:
        """Environment variable name -> field name."""
        return {env_name(name): name for name in cls.model_fields}

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> Settings:
        """Read and validate the `CORTEXLOC_*` variables once.

        Args:
            environ: the variables to read; None: `os.environ`.

        Returns:
            The validated settings.

        Raises:
            ConfigError: one or more values are invalid; the message names each variable and why (the
                value itself is shown, except for secrets).
        """
        env = os.environ if environ is None else environ
        known = cls.variables()
        for var in env:
            if var.startswith(ENV_PREFIX) and var not in known and var not in OTHER_KNOWN_VARIABLES:
                suffixes = [k.removeprefix(ENV_PREFIX) for k in known]
                close = difflib.get_close_matches(var.removeprefix(ENV_PREFIX), suffixes, n=1, cutoff=0.75)
                hint = f"; did you mean {ENV_PREFIX}{close[0]}?" if close else ""
                log.warning("unknown configuration variable %s is ignored%s", var, hint)
        raw: dict[str, Any] = _Environ(cls, env)()  # field name -> text
        try:
            return cls(**raw)
        except ValidationError as e:
            errors = []
            for err in e.errors(include_url=False, include_input=False):
                field = str(err["loc"][0]) if err["loc"] else ""
                var = env_name(field) if field else ENV_PREFIX + "*"
                shown = "" if field in _SECRET_FIELDS or field not in raw else f"={raw[field]!r}"
                errors.append((var, f"{shown}: {err['msg']}"))
            raise ConfigError(errors) from None
