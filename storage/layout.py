"""Where everything lives in one data directory: the one layout every writer and reader uses
(docs/design/service.md §4.1).

    <root>/.lock                                (`storage.lock`: one process at a time)
    <root>/catalog.sqlite
    <root>/projections/<sha256>.npy             (`models.frontend.slsbh.save_projection`'s naming)
    <root>/maps/<map_id>/map.sqlite
    <root>/maps/<map_id>/snapshots/<snapshot_id>/

Example:
    >>> Layout("var").map_db("default")
    PosixPath('var/maps/default/map.sqlite')
"""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from pathlib import Path

__all__ = ["DB_FILE", "TMP_MARK", "Layout"]

#: A map's database, in its map directory and, under the same name, in each of its snapshots.
DB_FILE = "map.sqlite"
#: In the names of the temporary directories that a create or an import renames into place.
TMP_MARK = ".tmp-"


@dataclass(frozen=True)
class Layout:
    """The paths of one data directory `root` (nothing is created or checked here)."""

    root: Path

    def __init__(self, root: str | os.PathLike[str]) -> None:
        object.__setattr__(self, "root", Path(root))

    @property
    def catalog(self) -> Path:
        """The catalog database (`storage.catalog.Catalog`)."""
        return self.root / "catalog.sqlite"

    @property
    def lock(self) -> Path:
        """The file a process holds locked while it has the directory's maps open (`storage.lock`)."""
        return self.root / ".lock"

    @property
    def projections(self) -> Path:
        """The content-addressed projection files, shared by every map."""
        return self.root / "projections"

    def projection(self, sha256: str) -> Path:
        """The projection whose SHA-256 (`models.frontend.slsbh.projection_sha256`) is `sha256`."""
        return self.projections / f"{sha256}.npy"

    @property
    def maps(self) -> Path:
        """The parent of every map directory (and of an import's staging directory)."""
        return self.root / "maps"

    def map_dir(self, map_id: str) -> Path:
        return self.maps / map_id

    def discarded(self, map_id: str, token: str) -> Path:
        """Where a deleted map's directory goes before it is removed: out of the maps' names (no map id
        starts with a dot), so a removal cut short leaves no map-like directory."""
        return self.maps / f".deleted-{map_id}-{token}"

    def discarded_of(self, map_id: str) -> list[Path]:
        """The discarded directories (`discarded`) of map `map_id`, not of another id it begins (a token
        is a 32-digit hex uuid)."""
        if not self.maps.is_dir():
            return []
        pattern = re.compile(re.escape(f".deleted-{map_id}-") + "[0-9a-f]{32}")
        return [d for d in self.maps.glob(f".deleted-{glob.escape(map_id)}-*") if pattern.fullmatch(d.name)]

    def import_staging(self, token: str) -> Path:
        """Where `cortexloc import` unpacks a snapshot before it becomes a map's: out of the maps' names,
        and unpacked first into a temporary directory beside it (`.<its name>.tmp-*`, storage.snapshots)."""
        return self.maps / f".import-{token}"

    def discarded_dirs(self) -> list[Path]:
        """What a removal or an import cut short left, to remove at a start (with the directory's lock
        held: no import runs): the deleted maps' directories (`discarded`), and an import's staging
        directory and its temporary one (`import_staging`; a killed import leaves its unpacked size)."""
        if not self.maps.is_dir():
            return []
        staging = self.import_staging("*").name
        return sorted([*self.maps.glob(".deleted-*"), *self.maps.glob(staging),
                       *self.maps.glob(f".{staging}{TMP_MARK}*")])

    def map_db(self, map_id: str) -> Path:
        """The map's live database (`storage.mapstore.MapStore`)."""
        return self.map_dir(map_id) / DB_FILE

    def snapshots_dir(self, map_id: str) -> Path:
        return self.map_dir(map_id) / "snapshots"

    def snapshot_dir(self, map_id: str, snapshot_id: str) -> Path:
        return self.snapshots_dir(map_id) / snapshot_id

    @staticmethod
    def snapshot_relpath(map_id: str, snapshot_id: str) -> str:
        """A snapshot's directory relative to the data directory, as the catalog records it (so a data
        directory can be moved or copied whole)."""
        return Layout("").snapshot_dir(map_id, snapshot_id).as_posix()
