"""`cortexloc import` and `cortexloc verify`: a data directory's maps, offline (the server stopped); and
`cortexloc repair`: a map's merges from a stream's own recent trail, listed or undone through the service
(`/v1/maps/{id}/repair`, a running one or the app run in this process)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from service.cli.common import check_map_id, progress
from service.cli.serve import command_settings, process_settings

if TYPE_CHECKING:
    from service.maps.repair import Found


def import_map(
    tar: Annotated[Path, typer.Argument(exists=True, dir_okay=False,
                                        help="A snapshot tar from /v1/maps/{map}/snapshots/{id}/download")],
    data_dir: Annotated[Path | None, typer.Option(help="Data directory (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Create a map from a snapshot tar, verifying every checksum (run while the server is stopped).

    Refused before anything is written: ids that the API would refuse, a map that exists, a tar that
    declares more than CORTEXLOC_MAX_IMPORT_BYTES or than the free space."""
    from types import SimpleNamespace

    from service.maps.encoding.embedders import Embedders
    from service.maps.errors import DataDirectoryInUse, MemoryBudgetExceeded, SnapshotInvalid
    from service.maps.registry import MapRegistry, remove_unused

    settings = command_settings(data_dir)
    root = settings.data_dir
    # Opening the registry makes a data directory (its catalog, lock and folders): one that this import
    # made and that ends up holding no map goes again, so a refused import leaves nothing behind.
    fresh = not root.exists()
    no_embedder = SimpleNamespace(identity="", feature_dim=0)  # an import embeds no image
    try:
        registry = MapRegistry(root, Embedders.one(no_embedder), settings=settings)
    except DataDirectoryInUse as e:  # the server is running on it
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    try:
        try:
            map_id = registry.import_snapshot(tar, settings.max_import_bytes)
        finally:
            registry.close()  # (no map is open: the catalog, and the directory's lock)
    except (SnapshotInvalid, MemoryBudgetExceeded, ValueError, OSError) as e:
        if fresh:
            remove_unused(root)
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    typer.echo(f"imported map {map_id!r} into {root}; it recovers from the snapshot when the server starts")


def verify(
    map_id: Annotated[str | None, typer.Option("--map", help="One map (default: every map).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Data directory (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Check maps offline, changing nothing: replay every row from the first and compare its stored
    winner cells, verify every snapshot's checksums and the projection. Exit 1 on any problem. Also list
    the merges made from a stream's own recent trail (`POST /v1/maps/{id}/repair` undoes them; they are
    no problem of the files)."""
    from service.maps.recovery import MapCheck, open_catalog, verify_map
    from service.maps.repair import listing

    root = process_settings(data_dir=data_dir).data_dir
    try:
        catalog = open_catalog(root)
        records = [r for r in catalog.list_maps() if map_id is None or r.map_id == map_id]
    except Exception as e:  # a missing or garbage catalog: say so, as a failed check
        typer.echo(f"error: cannot read the catalog in {root}: {e}", err=True)
        raise typer.Exit(1) from e
    if map_id is not None and not records:
        catalog.close()
        typer.echo(f"error: no map {map_id!r} in {root}", err=True)
        raise typer.Exit(2)
    bad = 0
    try:
        for record in records:
            try:
                with progress(f"verify {record.map_id}") as tick:
                    check = verify_map(catalog, record, progress=tick)
            except Exception as e:  # a fault no check names: this map's problem, and the others still run
                failed = f"the check itself failed: {type(e).__name__}: {e}"
                check = MapCheck(record.map_id, problems=[failed])
            bad += not check.ok
            rate = check.rows / check.seconds if check.seconds else 0.0
            typer.echo(f"map {record.map_id}: {'ok' if check.ok else 'PROBLEMS'}; {check.rows} rows "
                       f"replayed in {check.seconds:.2f} s ({rate:.0f} rows/s), "
                       f"{len(check.mismatches)} mismatched; snapshots {len(check.snapshots_ok)} ok, "
                       f"{len(check.snapshots_bad)} bad")
            if check.start is not None:
                typer.echo(f"  the visit log was pruned: replayed from snapshot {check.start}, the earliest "
                           "usable one that covers the pruned visits")
            if check.mismatches:
                seqs = ", ".join(map(str, check.mismatches))
                typer.echo(f"  stored winner cells differ from the replay at seq {seqs}")
            for sid, why in check.snapshots_bad.items():
                typer.echo(f"  snapshot {sid}: {why}")
            for problem in check.problems:
                typer.echo(f"  {problem}")
            if not check.problems:
                try:
                    _merges(listing(catalog, record))
                except Exception as e:  # as above: said, counted, and the next map checked
                    bad += check.ok
                    typer.echo(f"  its merges could not be listed: {type(e).__name__}: {e}")
    finally:
        catalog.close()
    typer.echo(f"{len(records)} map(s) checked, {bad} with problems")
    if bad:
        raise typer.Exit(1)


def _merges(found: Found) -> None:
    """The own-trail merges of one map, a line each."""
    if found.visits_pruned_through:
        typer.echo(f"  the visit log is pruned through visit {found.visits_pruned_through}: what was learned "
                   "before the oldest visit it keeps is not judged for merges")
    if not found:
        typer.echo(f"  no merges from a stream's own recent trail (its last {found.window} moves)")
        return
    typer.echo(f"  merges from a stream's own recent trail (its last {found.window} moves): "
               f"{len(found.visits)} visit(s), {len(found.joins)} place join(s), {len(found.closures)} loop "
               "closure(s); POST /v1/maps/{id}/repair undoes them")
    for v in found.visits:
        typer.echo(f"    visit {v.id}: stream {v.stream!r} consolidated into its own row {v.seq}")
    for seq, was, stream in found.joins:
        typer.echo(f"    row {seq}: stream {stream!r} joined the place of its own row {was}")
    for cid, stream, place in found.closures:
        typer.echo(f"    loop closure {cid}: stream {stream!r} named its own row {place}")


def repair(
    map_id: Annotated[str, typer.Option("--map", help="The map.")],
    dry_run: Annotated[bool, typer.Option("--dry-run", help="List the merges only (GET), change "
                                                           "nothing.")] = False,
    url: Annotated[str | None, typer.Option(help="A running service, e.g. http://127.0.0.1:8000 (default: "
                                                 "run the service in this process, the server stopped).")]
    = None,
    data_dir: Annotated[Path | None, typer.Option(help="In process: the data directory (default: "
                                                       "$CORTEXLOC_DATA_DIR or ./var).")] = None,
    api_key: Annotated[str | None, typer.Option(help="API key of the service (X-API-Key); in process "
                                                     "the configured CORTEXLOC_API_KEY is used.")] = None,
    json_out: Annotated[bool, typer.Option("--json", help="The answer's JSON on stdout.")] = False,
) -> None:
    """Undo a map's merges from a stream's own recent trail (docs/design/science.md §11.6): visits
    re-made as rows, rows given back their own place, loop closures retracted. Exit 1 on an error."""
    import anyio
    import httpx

    from service.cli.ingest import target
    from service.ingest import poster
    from service.maps.errors import DataDirectoryInUse

    check_map_id(map_id)
    settings, api_key = target(url, data_dir, api_key)
    headers = {"X-API-Key": api_key} if api_key else {}

    async def run() -> tuple[int, dict[str, Any]]:
        client = poster.remote_client(url) if settings is None else poster.in_process_client(settings)
        async with client as c:
            try:
                r = await c.request("GET" if dry_run else "POST", f"/v1/maps/{map_id}/repair",
                                    headers=headers)
            except httpx.TimeoutException as e:
                return 0, {"detail": f"no answer from {url} ({e!r}): the repair may or may not have run; "
                                     "--dry-run lists what is left"}
            except httpx.TransportError as e:
                return 0, {"detail": f"cannot reach the service at {url}: {e}"}
            return r.status_code, poster.json_body(r)

    try:
        status, body = anyio.run(run)
    except DataDirectoryInUse as e:  # in process, beside a server on the same data directory
        typer.echo(f"error: {e}; run it with --url against that server instead", err=True)
        raise typer.Exit(1) from e
    if status != 200:
        typer.echo(f"error: {status or 'no answer'}: {body.get('detail', body)}", err=True)
        raise typer.Exit(1)
    if json_out:
        typer.echo(json.dumps(body))
        return
    done, added = ("repaired", "added") if body["repaired"] else ("would repair", "to add")
    typer.echo(f"map {map_id}: {done} {len(body['splits'])} visit(s) as rows ({body['rows_added']} rows "
               f"{added}), {len(body['unjoins'])} place join(s), {len(body['retractions'])} loop closure(s) "
               f"retracted; a stream's recent trail: its last {body['window']} moves")
    if body.get("visits_pruned_through"):
        typer.echo(f"map {map_id}: the visit log is pruned through visit {body['visits_pruned_through']}: "
                   "what was learned before the oldest visit it keeps is not judged")
    if body.get("rewrite"):
        changes = "changed" if body["repaired"] else "would change"
        typer.echo(f"map {map_id}: the loop-closure log's cap pruned entries this repair may withdraw "
                   f"without a retraction: the log's epoch {changes}, so a back end following it rebuilds "
                   f"its edges from the export")
