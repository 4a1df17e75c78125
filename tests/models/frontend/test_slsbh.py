"""sLSBH hashing, its projections and their persistence (docs/design/science.md §7, §5)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from models import sdr
from models.frontend import slsbh
from models.frontend.slsbh import Hasher, ProjectionError, SparseProjection

D, K = 500, 64


def _unit_rows(X: np.ndarray) -> np.ndarray:
    return (X / np.linalg.norm(X, axis=-1, keepdims=True)).astype(np.float32)


def _features(n: int, d: int = D, seed: int = 0) -> np.ndarray:
    return _unit_rows(np.random.default_rng(seed).standard_normal((n, d)))


def _reference(Y: np.ndarray, s: float) -> np.ndarray:
    """Specification by full stable sort: order by value, then by lower index, for both halves."""
    n = slsbh.n_ones(Y.shape[1], s)
    top = np.sort(np.argsort(-Y, axis=1, kind="stable")[:, :n], axis=1)
    bottom = np.sort(np.argsort(Y, axis=1, kind="stable")[:, :n], axis=1)
    return np.concatenate([top, bottom + Y.shape[1]], axis=1).astype(np.int32)


@pytest.fixture(scope="module")
def dense_p() -> np.ndarray:
    return slsbh.make_projection(D, K, seed=0)


# --------------------------------------------------------------------------------------------------
# Dense projection


def test_projection_shape_dtype_and_unit_norm_columns(dense_p: np.ndarray) -> None:
    P = dense_p
    assert P.shape == (D, K) and P.dtype == np.float32 and P.flags.c_contiguous
    np.testing.assert_allclose(np.linalg.norm(P.astype(np.float64), axis=0), 1.0, atol=1e-6)


def test_projection_follows_the_documented_draw_order(dense_p: np.ndarray) -> None:
    P = dense_p
    raw = np.random.Generator(np.random.PCG64(0)).standard_normal((D, K), dtype=np.float32)
    raw64 = raw.astype(np.float64)
    expected = (raw64 / np.sqrt((raw64 * raw64).sum(axis=0))).astype(np.float32)
    np.testing.assert_array_equal(P, expected)


def test_projection_is_deterministic_per_seed_and_differs_across_seeds(dense_p: np.ndarray) -> None:
    P = dense_p
    again = slsbh.make_projection(D, K, seed=0)
    np.testing.assert_array_equal(P, again)
    assert slsbh.projection_sha256(P) == slsbh.projection_sha256(again)
    other = slsbh.make_projection(D, K, seed=1)
    assert not np.array_equal(P, other)
    assert slsbh.projection_sha256(P) != slsbh.projection_sha256(other)


def test_projection_sha256_hashes_little_endian_c_order_bytes(dense_p: np.ndarray) -> None:
    P = dense_p
    import hashlib

    sha = slsbh.projection_sha256(P)
    assert sha == hashlib.sha256(P.astype("<f4").tobytes(order="C")).hexdigest()
    # The same values in another layout or byte order identify the same matrix.
    assert slsbh.projection_sha256(np.asfortranarray(P)) == sha
    assert slsbh.projection_sha256(P.astype(">f4")) == sha
    with pytest.raises(ProjectionError):
        slsbh.projection_sha256(P.astype(np.float64))


def test_make_projection_rejects_empty_shapes() -> None:
    with pytest.raises(ValueError):
        slsbh.make_projection(0, 4)
    with pytest.raises(ValueError):
        slsbh.make_projection(4, 0)


def test_real_shape_projection_and_hash() -> None:
    """The paper's size (§7: 64,896 × 1,024, 265,814,016 bytes); about 2 s."""
    P = slsbh.make_projection()
    assert P.shape == (64_896, 1024) and P.nbytes == 265_814_016
    norms = np.linalg.norm(P[:, :: 97].astype(np.float64), axis=0)
    np.testing.assert_allclose(norms, 1.0, atol=1e-6)
    codes = Hasher(P, s=0.25)(_features(2, d=64_896))
    assert codes.shape == (2, 512)
    assert np.all(np.diff(codes, axis=1) > 0)


# --------------------------------------------------------------------------------------------------
# n_ones


@pytest.mark.parametrize(
    ("k", "s", "n"),
    [
        (1024, 0.25, 256),  # paper Nordland: 512 ones of 2048
        (1024, 0.025, 26),  # 25.6 → 26: 52 ones
        (1024, 0.02, 20),  # 20.48 → 20: 40 ones
        (1024, 0.0205, 21),  # 20.99 → 21: 42 ones
        (1024, 0.5, 512),
        (10, 0.25, 3),  # 2.5 rounds half up
        (10, 0.05, 1),  # 0.5 rounds half up
        (3, 0.5, 2),
    ],
)
def test_n_ones_rounds_half_up(k: int, s: float, n: int) -> None:
    assert slsbh.n_ones(k, s) == n


@pytest.mark.parametrize("s", [0.0, -0.1, 0.5000001, 1.0, float("nan"), float("inf")])
def test_n_ones_rejects_s_outside_range(s: float) -> None:
    with pytest.raises(ValueError):
        slsbh.n_ones(1024, s)


def test_n_ones_rejects_bad_k_and_empty_codes() -> None:
    for k in (0, -3, 2.5):
        with pytest.raises(ValueError):
            slsbh.n_ones(k, 0.25)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n=0"):
        slsbh.n_ones(1024, 1e-4)


# --------------------------------------------------------------------------------------------------
# hash_projected


@pytest.mark.parametrize("s", [0.25, 0.05, 0.5])
def test_codes_have_exactly_2n_sorted_ones(s: float) -> None:
    Y = np.random.default_rng(1).standard_normal((50, K)).astype(np.float32)
    codes = slsbh.hash_projected(Y, s)
    n = slsbh.n_ones(K, s)
    assert codes.shape == (50, 2 * n) and codes.dtype == np.int32
    assert np.all(np.diff(codes, axis=1) > 0)  # sorted and distinct
    assert np.all(codes[:, :n] < K) and np.all((codes[:, n:] >= K) & (codes[:, n:] < 2 * K))


def test_top_half_is_largest_and_bottom_half_is_smallest() -> None:
    Y = np.random.default_rng(2).standard_normal((30, K)).astype(np.float32)
    n = slsbh.n_ones(K, 0.25)
    codes = slsbh.hash_projected(Y, 0.25)
    for y, c in zip(Y, codes, strict=True):
        top, bottom = c[:n], c[n:] - K
        rest_top = np.setdiff1d(np.arange(K), top)
        rest_bottom = np.setdiff1d(np.arange(K), bottom)
        assert y[top].min() > y[rest_top].max()
        assert y[bottom].max() < y[rest_bottom].min()
    np.testing.assert_array_equal(codes, _reference(Y, 0.25))


def test_ties_go_to_the_lower_index_in_both_halves() -> None:
    # n = 2: the three 3s tie for the top two places, the two 0s fill the bottom.
    assert slsbh.hash_projected(np.array([[1, 3, 3, 3, 0, 0]], np.float32), 0.34).tolist() == [[1, 2, 10, 11]]
    # n = 3: top = every 2 (indices 0, 2, 5); bottom = both 0s, then the 1 at index 3.
    Y = np.array([[2, 0, 2, 1, 0, 2]], np.float32)
    assert slsbh.hash_projected(Y, 0.5).tolist() == [[0, 2, 5, 7, 9, 10]]
    # n = 2 of the same row: top {0, 2}, bottom {1, 4}.
    assert slsbh.hash_projected(Y, 0.34).tolist() == [[0, 2, 7, 10]]


def test_constant_rows_take_the_first_n_indices() -> None:
    n = slsbh.n_ones(K, 0.25)
    codes = slsbh.hash_projected(np.full((3, K), 0.5, np.float32), 0.25)
    expected = np.concatenate([np.arange(n), K + np.arange(n)])
    np.testing.assert_array_equal(codes, np.tile(expected, (3, 1)))


@pytest.mark.parametrize("levels", [2, 3, 5, 17])
@pytest.mark.parametrize("s", [0.25, 0.025, 0.5])
def test_many_ties_match_a_stable_sort(levels: int, s: float) -> None:
    rng = np.random.default_rng(levels)
    k = 1024
    Y = rng.integers(-(levels // 2), levels - levels // 2, size=(40, k)).astype(np.float32)
    Y[0] = 0.0
    Y[1, ::2] = -0.0  # −0 and +0 are the same value
    np.testing.assert_array_equal(slsbh.hash_projected(Y, s), _reference(Y, s))


def test_odd_k_at_s_half_may_mark_an_entry_in_both_halves() -> None:
    # k = 3, s = 0.5 → n = 2 > k/2: the middle entry is the 2nd largest and the 2nd smallest.
    assert slsbh.hash_projected(np.array([[0.0, 1.0, 2.0]], np.float32), 0.5).tolist() == [[1, 2, 3, 4]]


def test_hash_projected_input_checks() -> None:
    with pytest.raises(ValueError):
        slsbh.hash_projected(np.zeros(K, np.float32), 0.25)
    Y = np.zeros((2, K), np.float32)
    Y[1, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        slsbh.hash_projected(Y, 0.25)
    assert slsbh.hash_projected(np.zeros((0, K), np.float32), 0.25).shape == (0, 32)


# --------------------------------------------------------------------------------------------------
# Hasher


def test_hasher_projects_then_hashes(dense_p: np.ndarray) -> None:
    P = dense_p
    X = _features(8)
    h = Hasher(P, s=0.25)
    assert (h.d, h.k, h.n, h.width) == (D, K, 16, 128)
    assert h.sha256() == slsbh.projection_sha256(P)
    np.testing.assert_allclose(h.project(X), X @ P, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(h(X), slsbh.hash_projected(h.project(X), 0.25))


def test_hasher_accepts_torch_float64_and_single_vectors(dense_p: np.ndarray) -> None:
    P = dense_p
    X = _features(5)
    h = Hasher(P, s=0.25)
    codes = h(X)
    np.testing.assert_array_equal(h(torch.from_numpy(X)), codes)
    np.testing.assert_array_equal(h(X.astype(np.float64)), codes)
    one = h(X[2])
    assert one.shape == (32,)
    np.testing.assert_array_equal(one, codes[2])
    with pytest.raises(ValueError):
        h(np.zeros((2, D + 1), np.float32))


def test_overlap_dice_and_hamming_rank_alike(dense_p: np.ndarray) -> None:
    """docs/design/science.md §5: with constant weight 2n, Dice = overlap/(2n), Hamming = 4n − 2·overlap."""
    P = dense_p
    h = Hasher(P, s=0.25)
    db = list(h(_features(30, seed=3)))
    queries = list(h(_features(10, seed=4)))
    ov = sdr.overlap_matrix(db, queries)
    S = sdr.dice_matrix(db, queries)
    dense_db = np.stack([sdr.to_dense(c, h.width) for c in db]).astype(np.int64)
    dense_q = np.stack([sdr.to_dense(c, h.width) for c in queries]).astype(np.int64)
    H = (dense_db[:, None, :] != dense_q[None, :, :]).sum(axis=2)
    np.testing.assert_allclose(S, ov / (2 * h.n))
    np.testing.assert_array_equal(H, 4 * h.n - 2 * ov)
    by_overlap = np.argsort(-ov, axis=0, kind="stable")
    np.testing.assert_array_equal(np.argsort(-S, axis=0, kind="stable"), by_overlap)
    np.testing.assert_array_equal(np.argsort(H, axis=0, kind="stable"), by_overlap)


@pytest.mark.parametrize("sparse", [False, True])
def test_similar_inputs_share_more_ones(dense_p: np.ndarray, sparse: bool) -> None:
    P = dense_p
    proj = slsbh.make_sparse_projection(D, K, seed=0) if sparse else P
    h = Hasher(proj, s=0.25)
    rng = np.random.default_rng(5)
    x = _features(40, seed=6)
    mean_dice = []
    for eps in (0.1, 0.5, 2.0):
        y = _unit_rows(x + eps * _unit_rows(rng.standard_normal(x.shape)))
        mean_dice.append(np.mean([sdr.dice(a, b) for a, b in zip(h(x), h(y), strict=True)]))
    unrelated = np.mean([sdr.dice(a, b) for a, b in zip(h(x), h(_features(40, seed=7)), strict=True)])
    assert mean_dice[0] > mean_dice[1] > mean_dice[2] > unrelated
    assert mean_dice[0] > 0.85 and unrelated < 0.35  # chance level is about s = 0.25


# --------------------------------------------------------------------------------------------------
# Persistence


def test_save_load_round_trip(dense_p: np.ndarray, tmp_path: Path) -> None:
    P = dense_p
    path, sha = slsbh.save_projection(P, tmp_path / "proj")
    assert path == tmp_path / "proj" / f"{sha}.npy"
    assert sha == slsbh.projection_sha256(P)
    loaded = slsbh.load_projection(path, sha, shape=(D, K))
    assert isinstance(loaded, np.memmap) and not loaded.flags.writeable
    np.testing.assert_array_equal(loaded, P)
    np.testing.assert_array_equal(slsbh.load_projection(path, sha.upper(), mmap=False), P)
    np.testing.assert_array_equal(Hasher(loaded, 0.25)(_features(3)), Hasher(P, 0.25)(_features(3)))
    assert [p.name for p in path.parent.iterdir()] == [path.name]  # no temporary file left


def test_save_verifies_an_existing_file_instead_of_rewriting(dense_p: np.ndarray, tmp_path: Path) -> None:
    P = dense_p
    path, sha = slsbh.save_projection(P, tmp_path)
    before = os.stat(path)
    assert slsbh.save_projection(P.copy(), tmp_path) == (path, sha)
    after = os.stat(path)
    assert (after.st_ino, after.st_mtime_ns) == (before.st_ino, before.st_mtime_ns)


def test_save_replaces_a_corrupt_file_under_the_checksum_name(dense_p: np.ndarray, tmp_path: Path) -> None:
    P = dense_p
    path, sha = slsbh.save_projection(P, tmp_path)
    _flip_last_byte(path)
    with pytest.warns(RuntimeWarning, match="corrupt"):
        slsbh.save_projection(P, tmp_path)
    np.testing.assert_array_equal(slsbh.load_projection(path, sha), P)


def _flip_last_byte(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[-1] ^= 0x01
    path.write_bytes(bytes(data))


def test_load_refuses_a_checksum_mismatch(dense_p: np.ndarray, tmp_path: Path) -> None:
    P = dense_p
    path, sha = slsbh.save_projection(P, tmp_path)
    other = slsbh.projection_sha256(slsbh.make_projection(D, K, seed=1))
    with pytest.raises(ProjectionError, match="does not match"):
        slsbh.load_projection(path, other)
    _flip_last_byte(path)
    with pytest.raises(ProjectionError, match="does not match"):
        slsbh.load_projection(path, sha)
    assert issubclass(ProjectionError, ValueError)


def test_load_refuses_wrong_dtype_shape_order_and_bad_input(dense_p: np.ndarray, tmp_path: Path) -> None:
    P = dense_p
    cases = {
        "f8.npy": P.astype(np.float64),
        "be.npy": P.astype(">f4"),
        "1d.npy": P.ravel(),
        "fortran.npy": np.asfortranarray(P),
    }
    for name, arr in cases.items():
        np.save(tmp_path / name, arr)
        # The right checksum of the values does not make a wrong file acceptable.
        with pytest.raises(ProjectionError):
            slsbh.load_projection(tmp_path / name, slsbh.projection_sha256(P))
    path, sha = slsbh.save_projection(P, tmp_path / "ok")
    with pytest.raises(ProjectionError, match="shape"):
        slsbh.load_projection(path, sha, shape=(K, D))
    with pytest.raises(ProjectionError, match="64 hex"):
        slsbh.load_projection(path, "abc")
    with pytest.raises(ProjectionError, match="64 hex"):  # `$` matches before a last newline: fullmatch
        slsbh.load_projection(path, sha + "\n")
    with pytest.raises(ProjectionError, match="cannot read"):
        slsbh.load_projection(tmp_path / "missing.npy", sha)
    truncated = tmp_path / "truncated.npy"
    truncated.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ProjectionError):
        slsbh.load_projection(truncated, sha)


# --------------------------------------------------------------------------------------------------
# Very sparse projection


@pytest.fixture(scope="module")
def sparse_p() -> SparseProjection:
    return slsbh.make_sparse_projection(D, K, seed=0)


def test_sparse_projection_density_norms_and_layout(sparse_p: SparseProjection) -> None:
    S = sparse_p
    density = 1 / np.sqrt(D)
    # nnz ~ Binomial(d·k, 1/√d): mean 1431, sd 37; 6 sd is a safe band.
    assert abs(S.nnz - density * D * K) < 6 * np.sqrt(D * K * density)
    assert S.density == S.nnz / (D * K)
    dense = S.to_dense()
    np.testing.assert_allclose(np.linalg.norm(dense.astype(np.float64), axis=0), 1.0, atol=1e-6)
    assert set(np.unique(S.signs).tolist()) == {-1, 1}
    for j in range(K):
        rows = S.indices[S.indptr[j] : S.indptr[j + 1]]
        assert rows.size > 0 and np.all(np.diff(rows) > 0)
        np.testing.assert_allclose(np.abs(dense[rows, j]), 1 / np.sqrt(rows.size), rtol=1e-6)


def test_sparse_projection_custom_density_and_errors() -> None:
    S = slsbh.make_sparse_projection(2000, 32, seed=2, density=0.1)
    assert abs(S.density - 0.1) < 0.01
    for bad in (0.0, -0.5, 1.5, float("nan")):
        with pytest.raises(ValueError):
            slsbh.make_sparse_projection(100, 8, density=bad)
    with pytest.raises(ValueError, match="empty"):
        slsbh.make_sparse_projection(100, 8, density=1e-9)


def test_sparse_projection_is_deterministic_and_checksummed(sparse_p: SparseProjection) -> None:
    S = sparse_p
    again = slsbh.make_sparse_projection(D, K, seed=0)
    assert again.sha256() == S.sha256()
    np.testing.assert_array_equal(again.indices, S.indices)
    other = slsbh.make_sparse_projection(D, K, seed=1)
    assert other.sha256() != S.sha256()
    flipped = SparseProjection(D, K, S.indptr, S.indices, S.signs.copy())
    flipped.signs[0] *= -1
    assert flipped.sha256() != S.sha256()


def test_sparse_projection_validates_its_arrays(sparse_p: SparseProjection) -> None:
    S = sparse_p
    with pytest.raises(ProjectionError):
        SparseProjection(D, K, S.indptr.astype(np.int32), S.indices, S.signs)
    with pytest.raises(ProjectionError):
        SparseProjection(D - 1, K, S.indptr, S.indices + 1, S.signs)
    with pytest.raises(ProjectionError):
        SparseProjection(D, K, S.indptr, S.indices, np.zeros_like(S.signs))


def test_sparse_matmul_matches_dense_and_is_batch_independent(sparse_p: SparseProjection) -> None:
    S = sparse_p
    X = _features(9, seed=8)
    Y = S.matmul(X)  # batch kernel (≥ 4 rows)
    np.testing.assert_allclose(Y, X.astype(np.float64) @ S.to_dense().astype(np.float64), atol=1e-6)
    # The per-row kernel sums in the same order: bit-identical results.
    for i in range(len(X)):
        np.testing.assert_array_equal(S.matmul(X[i : i + 1])[0], Y[i])
    h = Hasher(S, s=0.25)
    assert h.sparse and h.sha256() == S.sha256()
    np.testing.assert_array_equal(h(X), slsbh.hash_projected(Y, 0.25))
    np.testing.assert_array_equal(h(X[4]), h(X)[4])
