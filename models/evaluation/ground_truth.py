"""Ground truth read from a file, for image sets whose matches are not given by equal file names.

Two formats, chosen by the file's suffix; indices count from 0 in the sorted image names of each folder
(the order `cortexloc eval images --gt` reads them in):

- **CSV** (`.csv`): one row per query, `query_index,query_file,matching_ref_indices`, an optional header
  row with those names; `matching_ref_indices` holds database indices separated by spaces or semicolons
  (empty: the query has no match, so any answer to it is a false positive). `query_file` is checked
  against the query folder's name at that index, so a file for other images is refused; it may carry a
  folder (`query/0000000.jpg`, `query\\0000000.jpg`), which is not compared (the query folder may be
  named otherwise here).

      query_index,query_file,matching_ref_indices
      0,images-00010.png,0 1
      1,images-00020.png,1;2

- **VPR-Bench** `ground_truth_new.npy` (`.npy`): an object array of rows `[query_index, array(ref
  indices)]`. numpy stores object arrays as a pickle, and unpickling can run arbitrary code; this reader
  never calls `np.load(allow_pickle=True)`: it unpickles with a restricted unpickler that resolves only
  the numpy names an array of integer arrays needs and refuses everything else.
"""

from __future__ import annotations

import csv
import io
import pickle
import re
from collections.abc import Sequence
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

CSV_HEADER = ("query_index", "query_file", "matching_ref_indices")

# What pickled numpy integer arrays reference (numpy 1.x wrote numpy.core, numpy 2 writes numpy._core).
_SAFE_GLOBALS = {(mod, name) for mod in ("numpy.core.multiarray", "numpy._core.multiarray")
                 for name in ("_reconstruct", "scalar")} | {("numpy", "ndarray"), ("numpy", "dtype")}


class _NumpyOnly(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _SAFE_GLOBALS:
            raise pickle.UnpicklingError(f"refusing {module}.{name}: not part of a numpy integer array")
        return super().find_class(module, name)


def _dense(pairs: Sequence[tuple[int, Sequence[int]]], n_db: int, n_q: int, where: str) -> np.ndarray:
    gt = np.zeros((n_db, n_q), dtype=bool)
    seen: set[int] = set()
    for q, refs in pairs:
        if not 0 <= q < n_q:
            raise ValueError(f"{where}: query index {q} is outside the {n_q} query images")
        if q in seen:
            raise ValueError(f"{where}: query index {q} appears twice")
        seen.add(q)
        for r in refs:
            if not 0 <= r < n_db:
                raise ValueError(f"{where}: query {q}: database index {r} is outside the {n_db} images")
            gt[r, q] = True
    return gt


def _read_csv(path: Path, n_db: int, n_q: int, query_names: Sequence[str] | None) -> np.ndarray:
    pairs = []
    with open(path, newline="", encoding="utf-8") as fh:
        for lineno, row in enumerate(csv.reader(fh), start=1):
            if not row or (lineno == 1 and tuple(c.strip() for c in row) == CSV_HEADER):
                continue
            where = f"{path}: line {lineno}"
            if len(row) != 3:
                raise ValueError(f"{where}: expected 3 fields {','.join(CSV_HEADER)}, got {len(row)}")
            try:
                q = int(row[0])
                refs = [int(t) for t in re.split(r"[;\s]+", row[2].strip()) if t]
            except ValueError:
                raise ValueError(f"{where}: indices must be whole numbers, got {row!r}") from None
            # The file column may carry the folder, as VPR data sets write it: `query/0000000.jpg`.
            given = row[1].strip()
            name = PurePosixPath(given.replace("\\", "/")).name
            if query_names is not None and 0 <= q < len(query_names) and name != query_names[q]:
                raise ValueError(f"{where}: query {q} is {query_names[q]!r} in the query folder, "
                                 f"not {given!r}")
            pairs.append((q, refs))
    if not pairs:
        raise ValueError(f"{path}: no ground-truth rows")
    return _dense(pairs, n_db, n_q, str(path))


def _read_npy(path: Path, n_db: int, n_q: int) -> np.ndarray:
    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        readers = {(1, 0): np.lib.format.read_array_header_1_0, (2, 0): np.lib.format.read_array_header_2_0}
        if version not in readers:
            raise ValueError(f"{path}: .npy format version {version} is not supported")
        shape, _, dtype = readers[version](fh, max_header_size=10_000)
        if dtype.hasobject:
            arr = np.asarray(_NumpyOnly(io.BytesIO(fh.read())).load())
        else:
            raise ValueError(f"{path}: expected VPR-Bench's object array of [query, refs] rows, "
                             f"got dtype {dtype}, shape {shape}")
    pairs = []
    for k, row in enumerate(arr):
        if len(row) != 2:
            raise ValueError(f"{path}: row {k}: expected [query_index, array(ref_indices)]")
        pairs.append((int(row[0]), [int(r) for r in np.atleast_1d(np.asarray(row[1])).ravel()]))
    return _dense(pairs, n_db, n_q, str(path))


def load(path: str | Path, n_db: int, n_q: int, query_names: Sequence[str] | None = None) -> np.ndarray:
    """(n_db, n_q) bool ground truth (database rows, query columns) from a `.csv` or `.npy` file.

    Raises:
        ValueError: unknown suffix, malformed rows, indices out of range, or a query file name that
            does not match `query_names`; the message names the file (and the line for CSV).
    """
    p = Path(path)
    suffix = p.suffix.lower()
    try:
        if suffix == ".csv":
            return _read_csv(p, n_db, n_q, query_names)
        if suffix == ".npy":
            return _read_npy(p, n_db, n_q)
    except (pickle.UnpicklingError, EOFError, UnicodeDecodeError) as e:
        raise ValueError(f"{p}: not a readable ground-truth file ({e})") from e
    raise ValueError(f"{p}: ground truth must be a .csv or a VPR-Bench .npy file")
