"""Ground truth read from files: the CSV layout and VPR-Bench's ground_truth_new.npy, read safely."""

from __future__ import annotations

import os

import numpy as np
import pytest

from models.evaluation import ground_truth


def test_csv_with_header_spaces_and_semicolons(tmp_path):
    f = tmp_path / "gt.csv"
    f.write_text("query_index,query_file,matching_ref_indices\n0,a.png,0 1\n1,b.png,1;2\n2,c.png,\n")
    gt = ground_truth.load(f, 4, 3, ["a.png", "b.png", "c.png"])
    assert gt.shape == (4, 3)
    assert np.flatnonzero(gt[:, 0]).tolist() == [0, 1]
    assert np.flatnonzero(gt[:, 1]).tolist() == [1, 2]
    assert not gt[:, 2].any()  # a query without a match


def test_csv_query_files_may_carry_their_folder(tmp_path):
    """VPR data sets write the file column as `query/0000000.jpg`: the folder is not the query's name."""
    f = tmp_path / "gt.csv"
    f.write_text("query_index,query_file,matching_ref_indices\n0,query/a.png,0\n1,winter\\b.png,1\n")
    assert np.flatnonzero(ground_truth.load(f, 4, 2, ["a.png", "b.png"])).tolist() == [0, 3]


@pytest.mark.parametrize(("text", "message"), [
    ("0,query/b.png,0\n", "'a.png' in the query folder, not 'query/b.png'"),
    ("0,a.png,5\n", "outside the 4"),
    ("7,a.png,0\n", "query index 7"),
    ("0,b.png,0\n", "'a.png' in the query folder"),
    ("0,a.png\n", "expected 3 fields"),
    ("0,a.png,x\n", "whole numbers"),
    ("0,a.png,0\n0,a.png,1\n", "appears twice"),
])
def test_csv_errors_name_the_line(tmp_path, text, message):
    f = tmp_path / "gt.csv"
    f.write_text(text)
    with pytest.raises(ValueError, match=message):
        ground_truth.load(f, 4, 3, ["a.png", "b.png", "c.png"])


def test_vpr_bench_npy(tmp_path):
    rows = np.empty((3, 2), dtype=object)
    for q, refs in enumerate(([0, 1], [1], [])):
        rows[q, 0], rows[q, 1] = q, np.array(refs, dtype=np.int64)
    f = tmp_path / "ground_truth_new.npy"
    np.save(f, rows, allow_pickle=True)
    gt = ground_truth.load(f, 4, 3)
    assert gt.astype(int).T.tolist() == [[1, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]]


class _Payload:
    def __reduce__(self):
        return (os.system, ("echo unsafe > /dev/null",))


def test_a_pickle_that_runs_code_is_refused(tmp_path):
    bad = np.empty(1, dtype=object)
    bad[0] = _Payload()
    f = tmp_path / "ground_truth_new.npy"
    np.save(f, bad, allow_pickle=True)
    with pytest.raises(ValueError, match="refusing"):
        ground_truth.load(f, 4, 3)


def test_other_files_are_refused(tmp_path):
    f = tmp_path / "gt.npy"
    np.save(f, np.eye(3))
    with pytest.raises(ValueError, match="object array"):
        ground_truth.load(f, 3, 3)
    with pytest.raises(ValueError, match=r"\.csv or a VPR-Bench"):
        ground_truth.load(tmp_path / "gt.txt", 3, 3)
