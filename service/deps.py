"""Typed dependencies: what routes receive from the app (one place, one spelling each).

    SettingsDep   the validated `Settings` (read once at startup)
    MetricsDep    the app's `Metrics` (per-app Prometheus registry)
    RegistryDep   the `MapRegistry` (503 not-ready until the maps are open)
    require_api_key / ApiKeyDep   guard for write routes when `CORTEXLOC_API_KEY` is set
    ReadKeyDep    the same guard for every /v1 read and /metrics, when `CORTEXLOC_API_KEY_READS`

Example:
    >>> @router.post("/v1/maps", dependencies=[ApiKeyDep])
    ... def create_map(settings: SettingsDep, registry: RegistryDep) -> ...
"""

from __future__ import annotations

import secrets
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.errors import Problem
from service.maps.registry import MapRegistry
from service.metrics import Metrics
from service.settings import KEY_WHITESPACE, Settings

__all__ = [
    "ApiKeyDep",
    "MetricsDep",
    "ReadKeyDep",
    "RegistryDep",
    "SettingsDep",
    "get_metrics",
    "get_registry",
    "get_settings",
    "require_api_key",
    "require_api_key_for_reads",
]


def get_settings(request: Request) -> Settings:
    settings = getattr(request.app.state, "settings", None)
    if settings is None:  # only before startup finished (e.g. a TestClient used without `with`)
        raise Problem(503, "not-ready", "the service has not finished starting")
    return settings


def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


SettingsDep = Annotated[Settings, Depends(get_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]


def get_registry(request: Request) -> MapRegistry:
    registry = getattr(request.app.state, "registry", None)
    if registry is None:
        # a start that could not open the maps stays so until the cause is fixed and the server restarted
        failed = getattr(request.app.state, "registry_error", None)
        raise Problem(503, "not-ready", f"{failed}; restart the server once fixed" if failed
                      else "the maps are not loaded yet")
    return registry


RegistryDep = Annotated[MapRegistry, Depends(get_registry)]

_api_key_header = APIKeyHeader(name="X-API-Key", scheme_name="ApiKey", auto_error=False,
                               description="the value of CORTEXLOC_API_KEY, when the server sets one")
_bearer = HTTPBearer(scheme_name="Bearer", auto_error=False,
                     description="`Authorization: Bearer <CORTEXLOC_API_KEY>`, when the server sets one")


def require_api_key(
    settings: SettingsDep,
    api_key: Annotated[str | None, Security(_api_key_header)] = None,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)] = None,
) -> None:
    """Let the request through if no key is configured, or if `X-API-Key` or a Bearer token matches it.

    Raises:
        Problem: 401 `unauthorized` (with `WWW-Authenticate: Bearer`) on a missing or wrong key.
    """
    expected = settings.api_key
    if expected is None:
        return
    given = api_key if api_key else (bearer.credentials if bearer is not None else None)
    given = None if given is None else given.strip(KEY_WHITESPACE)  # as the setting is read
    if given is not None and secrets.compare_digest(given.encode(), expected.encode()):
        return
    detail = ("this operation needs the API key: send it in X-API-Key or as Authorization: Bearer"
              if given is None else "the API key is not valid")
    raise Problem(401, "unauthorized", detail, headers={"WWW-Authenticate": 'Bearer realm="cortexloc"'})


#: `dependencies=[ApiKeyDep]` on a write route or router.
ApiKeyDep = Depends(require_api_key)


def require_api_key_for_reads(
    settings: SettingsDep,
    api_key: Annotated[str | None, Security(_api_key_header)] = None,
    bearer: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)] = None,
) -> None:
    """`require_api_key` for reads too, when `CORTEXLOC_API_KEY_READS` (docs/design/service.md §8)."""
    if settings.api_key_reads:
        require_api_key(settings, api_key, bearer)


#: `dependencies=[ReadKeyDep]` on a router whose reads are guarded: every `/v1` route and `/metrics`
#: (`service.routes`), which name maps, robots (stream names) and map contents; never /healthz or /readyz.
ReadKeyDep = Depends(require_api_key_for_reads)
