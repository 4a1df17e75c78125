"""`cortexloc import` and `cortexloc verify`: a data directory's maps, offline (the server stopped)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from service.cli.common import progress
from service.cli.serve import process_settings


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

    from service.maps.encoding.encoders import Encoders
    from service.maps.errors import MemoryBudgetExceeded, SnapshotInvalid
    from service.maps.registry import MapRegistry

    settings = process_settings(data_dir=data_dir)
    root = settings.data_dir
    registry = MapRegistry(root, Encoders.one(SimpleNamespace(identity="", feature_dim=0)), settings=settings)
    try:
        map_id = registry.import_snapshot(tar, settings.max_import_bytes)
    except (SnapshotInvalid, MemoryBudgetExceeded, ValueError, OSError) as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from e
    finally:
        registry.catalog.close()
    typer.echo(f"imported map {map_id!r} into {root}; it recovers from the snapshot when the server starts")


def verify(
    map_id: Annotated[str | None, typer.Option("--map", help="One map (default: every map).")] = None,
    data_dir: Annotated[Path | None, typer.Option(help="Data directory (default: $CORTEXLOC_DATA_DIR "
                                                       "or ./var).")] = None,
) -> None:
    """Check maps offline, changing nothing: replay every row from the first and compare its stored
    winner cells, verify every snapshot's checksums and the projection. Exit 1 on any problem."""
    from service.maps.recovery import open_catalog, verify_map

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
            with progress(f"verify {record.map_id}") as tick:
                check = verify_map(catalog, record, progress=tick)
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
    finally:
        catalog.close()
    typer.echo(f"{len(records)} map(s) checked, {bad} with problems")
    if bad:
        raise typer.Exit(1)
