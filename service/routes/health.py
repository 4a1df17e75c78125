"""`GET /healthz` (liveness) and `GET /readyz` (readiness with each check's result),
docs/design/service.md §1.6.

A check result is a dict with `status` = `pass` | `warn` | `fail` and its details. The service is ready
iff no check fails: 200 `{"status": "ready", "checks": ..., "warnings": [...]}`, else 503 problem+json
`not-ready` with `checks`. Built-in checks:

- `data_dir`: a probe file is written, fsynced and deleted in `CORTEXLOC_DATA_DIR`; a directory that
  has no room (a full disk, a used-up quota) is a warning, not a failure: the maps localise and serve
  reads, only what writes gets 507, and a readiness-gated balancer must not take that away;
- `encoder`: loaded, with its weights (`pretrained` + SHA-256, or `random` + seed: `warn`, or `fail`
  when `CORTEXLOC_ALLOW_RANDOM_WEIGHTS=false`), and the runtime and device its backbone runs on;
- `maps`: the state of each map in `app.state.maps` (objects with `state`, `state_reason`, `recovery`
  and `snapshot_error`): ready iff none is `recovering`; `failed` maps, `read-only` ones (their storage
  refuses writes), maps with no room to learn (`no_room`), maps `replaying` their tail
  (they localise, learning waits), recoveries that passed over snapshots or rows, and failed automatic
  snapshots are warnings. With `CORTEXLOC_API_KEY_READS` the
  probe stays open but names no map: it gives the counts by state (map ids are reads that need the key);
- `catalog`: once the map registry started, its catalog's own check (`Catalog.check`), and a warning
  for map directories it does not list (left as they are, not served); if the registry could not
  start, `app.state.registry_error` says why (a failure).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import JSONResponse

from service.errors import problem_response, problem_responses
from service.maps.runtime.room import probe_data_dir
from service.maps.states import serving
from service.schemas import Health, Readiness

__all__ = ["UNNAMED_ERROR", "Check", "check_catalog", "check_data_dir", "check_encoder", "check_maps",
           "failing", "readiness", "readiness_reply", "router"]

Check = dict[str, Any]

router = APIRouter(tags=["operations"])
log = logging.getLogger("cortexloc.service")


def check_data_dir(data_dir: Path) -> Check:
    """Write, fsync and delete a probe file in `data_dir`: a failure where it cannot be written (missing,
    a permission, a read-only mount), a warning where the OS says there is no room (module docstring)."""
    out: Check = {"status": "pass", "path": str(data_dir)}
    outcome, why = probe_data_dir(data_dir)
    if outcome == "no-room":
        out.update(status="warn", warning=f"no room to write in the data directory ({why}): maps localise "
                                          "and serve reads; learning, snapshots, resets and new maps get 507 "
                                          "insufficient-storage until room is made")
    elif outcome == "unwritable":
        out.update(status="fail", error=f"data directory is not writable: {why}")
    return out


def check_encoder(app: FastAPI) -> Check:
    """The encoder is loaded; its weights, with a warning (or a failure) for random ones."""
    encoder = getattr(app.state, "encoder", None)
    if encoder is None:
        return {"status": "fail", "error": "encoder not loaded"}
    info: dict[str, Any] = dict(getattr(app.state, "encoder_weights", None) or {})
    desc = encoder.describe()
    out: Check = {"status": "pass", "encoder": desc["encoder"], "weights": desc["weights"], **info,
                  "runtime": desc["runtime"], "device": desc["device"],
                  "backbone": app.state.settings.backbone}  # of new maps (service.frontend.resolve_backbone)
    registry = getattr(app.state, "registry", None)
    if registry is not None:  # one encoder per backbone in use
        out["backbones"] = {name: e.identity for name, e in registry.encoders.built().items()}
    if desc["weights"] == "random":
        settings = app.state.settings
        out["seed"] = settings.random_weights_seed
        if settings.allow_random_weights:
            out.update(status="warn",
                       warning="encoder runs on random weights: matches are not meaningful; set "
                               "CORTEXLOC_WEIGHTS_PATH or run `cortexloc weights download`")
        else:
            out.update(status="fail", error="random weights are not allowed (CORTEXLOC_ALLOW_RANDOM_WEIGHTS="
                                            "false): set CORTEXLOC_WEIGHTS_PATH or run `cortexloc weights "
                                            "download`")
    return out


def check_maps(maps: dict[str, Any], named: bool = True) -> Check:
    """Each map's state, how it recovered and whether its last automatic snapshot failed; fails while
    a map is still recovering, warns about failed maps and about recoveries or snapshots that went
    wrong (the map serves, but an operator should look). `named=False` (reads need the key): the same
    status from counts by state alone, no map id, reason or error text."""
    if not named:
        return _anonymous(check_maps(maps))
    states = {}
    notes = []
    for map_id, m in sorted(maps.items()):
        states[map_id] = {"state": str(m.state), "state_reason": m.state_reason,
                          "backbone": m.config.backbone}
        recovery, snap_error = getattr(m, "recovery", None), getattr(m, "snapshot_error", None)
        skipped = list((recovery or {}).get("skipped_snapshots") or [])
        if skipped:
            states[map_id]["skipped_snapshots"] = skipped
        if recovery and (skipped or recovery.get("mismatches") or recovery.get("complete") is False):
            states[map_id]["recovery"] = recovery  # only when it went wrong: the usual case stays short
            notes.append(f"map {map_id} recovered by {recovery.get('source')} after passing over "
                         f"{len(skipped)} snapshot(s) (a damaged snapshot, or one whose replay diverged), "
                         f"{recovery.get('mismatches', 0)} row(s) not reproduced")
        serves = serving(str(m.state))
        no_room = getattr(m, "no_room", None)
        if no_room and serves.learns:
            states[map_id]["no_room"] = no_room
            notes.append(f"map {map_id} has no room to write ({no_room}): localising frames are answered, "
                         "learning ones get 507 until room is made")
        if serves.read_only:
            notes.append(f"map {map_id}'s storage refuses writes (read-only): localising frames are "
                         "answered, learning ones get 503 map-read-only; make its map.sqlite writable and "
                         "restart")
        elif serves.reads and not serves.learns:  # replaying: localises, learning waits (service.md §4.4)
            states[map_id]["recovery"] = recovery  # `tail` steps, `replayed` so far
            notes.append(f"map {map_id} is replaying the rows after its snapshot: localising frames are "
                         "answered, learning ones get 503 until it is done")
        if snap_error:
            states[map_id]["snapshot_error"] = snap_error
            notes.append(f"map {map_id}: automatic snapshot failed at seq {snap_error.get('seq')}: "
                         f"{snap_error.get('error')}")
    blocking = [k for k, v in states.items() if serving(v["state"]).blocks_readiness]
    failed = [k for k, v in states.items() if serving(v["state"]).warns and not serving(v["state"]).reads]
    out: Check = {"status": "pass", "count": len(states), "maps": states}
    if failed:
        notes.insert(0, f"failed map(s), served as map-unavailable: {', '.join(failed)}")
    if notes:
        out.update(status="warn", warning="; ".join(notes))
    if blocking:
        out.update(status="fail", error=f"map(s) still recovering: {', '.join(blocking)}")
    return out


def _anonymous(check: Check) -> Check:
    """`check_maps`'s result without what names a map: its status and the number of maps per state."""
    by_state: dict[str, int] = {}
    for m in check["maps"].values():
        by_state[m["state"]] = by_state.get(m["state"], 0) + 1
    out: Check = {"status": check["status"], "count": check["count"],
                  "states": dict(sorted(by_state.items()))}
    if check["status"] == "warn":
        out["warning"] = "a map needs an operator's look (details with the read key: GET /v1/maps)"
    elif check["status"] == "fail":
        blocking = sum(n for state, n in by_state.items() if serving(state).blocks_readiness)
        out["error"] = f"{blocking} map(s) still recovering"
    return out


#: A failed check's reason where reads need the key (`named` False): its text names files of the host.
UNNAMED_ERROR = "see the server's log (the reason names files of the host; reads need the key)"


def check_catalog(app: FastAPI, named: bool = True) -> Check | None:
    """The map registry's catalog; None while no registry was started (an app without maps). Map
    directories it does not list (`MapRegistry.unlisted`: left as they are, not served) are a warning:
    their ids where `named`, else their count. A failure's reason names files (the catalog's path, the
    file a start could not open): where not `named` it is `UNNAMED_ERROR`, and logged."""
    error = getattr(app.state, "registry_error", None)  # logged at the start that failed
    if error is not None:
        return {"status": "fail", "error": error if named else UNNAMED_ERROR}
    registry = getattr(app.state, "registry", None)
    if registry is None:
        return None
    try:
        out = registry.catalog.check()
    except Exception as e:  # a check that crashes is a failed check, not a 500
        out = {"status": "fail", "error": f"{type(e).__name__}: {e}"}
    if out.get("status") == "fail":
        log.warning("readiness: the catalog check failed: %s", out.get("error"))
        if not named:
            out = {**out, "error": UNNAMED_ERROR}
    unlisted = list(getattr(registry, "unlisted", ()))
    if unlisted and out.get("status") == "pass":
        out.update(status="warn", unlisted=len(unlisted),
                   warning=f"{len(unlisted)} map director(y/ies) hold a map the catalog does not list: left "
                           "as they are, not served; restore catalog.sqlite or move them away")
        if named:
            out["unlisted_maps"] = unlisted
    return out


def failing(checks: dict[str, Check]) -> list[str]:
    """The one rule of readiness (docs/design/service.md §1.6): the names of the checks that fail; the
    service (a shard, or the ingress over its shards) is ready iff there is none. Warnings never count."""
    return [name for name, c in checks.items() if c.get("status") == "fail"]


def readiness_reply(request: Request, checks: dict[str, Check],
                    warnings: list[str]) -> Readiness | JSONResponse:
    """/readyz's reply: 200 `ready` with each check's result, or 503 problem+json `not-ready` naming the
    `failing` checks."""
    names = failing(checks)
    if not names:
        return Readiness(status="ready", checks=checks, warnings=warnings)
    return problem_response(request, 503, "not-ready", f"not ready: {', '.join(names)} failed",
                            checks=checks, warnings=warnings)


def readiness(app: FastAPI) -> tuple[bool, dict[str, Check]]:
    """Run every check: (ready, results by name)."""
    checks: dict[str, Check] = {}
    settings = getattr(app.state, "settings", None)
    if settings is None:
        return False, {"startup": {"status": "fail", "error": "startup has not finished"}}
    named = not settings.api_key_reads
    checks["data_dir"] = check_data_dir(settings.data_dir)
    checks["encoder"] = check_encoder(app)
    checks["maps"] = check_maps(getattr(app.state, "maps", None) or {}, named=named)
    catalog = check_catalog(app, named=named)
    if catalog is not None:
        checks["catalog"] = catalog
    if not named:  # the probe stays open: where reads need the key it shows no file path of the host
        checks = {name: {k: v for k, v in c.items() if k != "path"} for name, c in checks.items()}
    return not failing(checks), checks


@router.get("/healthz")
async def healthz() -> Health:
    """Liveness: the process answers. Touches nothing."""
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, responses=problem_responses(503))
def readyz(request: Request) -> Readiness | JSONResponse:
    """Readiness: 200 with each check's result, or 503 problem+json `not-ready` with `checks`."""
    _, checks = readiness(request.app)
    return readiness_reply(request, checks, [c["warning"] for c in checks.values() if c.get("warning")])
