"""PR-curve and similarity-matrix figures (docs/design/science.md §8.1, §8.6)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.evaluation.metrics import pr_curve
from models.evaluation.plots import plot_pr_curves, plot_similarity, similarity_caption, similarity_figure

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE
    # IHDR is the first chunk: width and height are its first two big-endian 32-bit fields.
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


def test_plot_pr_curves_writes_a_png(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    GT = np.eye(20, dtype=bool)
    curves = {
        "InputSDR": pr_curve(rng.random((20, 20)) + GT * 0.5, GT),
        "HTM": pr_curve(rng.random((20, 20)) + GT * 1.0, GT),
        "list input": ([1.0, 1.0, 0.5], [0.0, 0.5, 1.0]),
    }
    out = plot_pr_curves(curves, tmp_path / "figs" / "pr.png", "grid a=5 n=0.5, paper scoring")
    assert out == tmp_path / "figs" / "pr.png"
    assert out.stat().st_size > 1000
    width, height = _png_size(out)
    assert width > 100 and height > 100


def test_plot_similarity_writes_a_png(tmp_path: Path) -> None:
    S = np.random.default_rng(1).random((30, 40))
    out = plot_similarity(S, str(tmp_path / "S.png"), "InputSDR Dice")
    assert Path(out).is_file() and Path(out).stat().st_size > 1000
    _png_size(Path(out))


def test_the_similarity_image_explains_its_holes_and_negative_values(tmp_path: Path) -> None:
    S = np.random.default_rng(1).normal(size=(30, 40))  # negative values, as a sequence score has
    S[:, :5] = -np.inf  # no full path at the route's start
    S[3, 20] = np.nan
    caption = similarity_caption(S)
    assert "White: no score (151 of 1,200 cells)" in caption and "not a similarity of 0" in caption
    assert "Below 0: scores, not anticorrelations" in caption
    fig = similarity_figure(S, "htm-seq")
    assert [" ".join(t.get_text().split()) for t in fig.texts] == [" ".join(caption.split())]
    assert plot_similarity(S, tmp_path / "S.png", "htm-seq").stat().st_size > 1000
    # A plain similarity (Dice in [0, 1], every cell scored) needs no caption.
    assert similarity_caption(np.random.default_rng(2).random((4, 5))) == ""
    assert similarity_figure(np.eye(3), "t").texts == []


def test_plot_similarity_rejects_non_matrices(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="2-D"):
        plot_similarity(np.ones(5), tmp_path / "bad.png", "bad")


def test_matplotlib_is_loaded_lazily_and_pyplot_never(tmp_path: Path) -> None:
    # A fresh interpreter, because this test session may already have imported matplotlib elsewhere.
    code = (
        "import sys, numpy as np\n"
        "from models.evaluation import plots\n"
        "assert 'matplotlib' not in sys.modules\n"
        f"plots.plot_similarity(np.eye(3), {str(tmp_path / 'b.png')!r}, 't')\n"
        "assert 'matplotlib.pyplot' not in sys.modules\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "b.png").is_file()


def test_match_gallery_frames_right_answers_green_and_wrong_ones_red(tmp_path: Path) -> None:
    import cv2

    from models.evaluation import plots

    rng = np.random.default_rng(0)
    paths = []
    for i in range(6):
        p = tmp_path / f"img-{i}.png"
        cv2.imwrite(str(p), rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
        paths.append(p)
    queries, best = [0, 1, 2, 3, 4], [0, 3, 2, 0, 4]
    correct = [q == b for q, b in zip(queries, best, strict=True)]
    out = plots.match_gallery(paths, paths, queries, best, correct, [0.9, 0.1, 0.8, 0.2, 0.7],
                              tmp_path / "g.png", n=4, cols=2)
    img = cv2.imread(str(out), cv2.IMREAD_COLOR)
    cw, ch = plots.gallery_cell_size()
    assert img.shape == (2 * ch, 2 * cw, 3)  # 4 of 5 queries, evenly spaced: 0, 1, 3, 4
    # The frame's top-left pixel of each cell carries the verdict's colour.
    colours = [tuple(int(v) for v in img[r * ch + 1, c * cw + 1]) for r in range(2) for c in range(2)]
    green, red = plots.RIGHT_BGR, plots.WRONG_BGR
    assert colours == [green, red, red, green]
    # The query tile sits inside the frame, resized to TILE: its pixels are the image's, not a colour.
    tile = img[plots.BORDER:plots.BORDER + plots.TILE[1], plots.BORDER:plots.BORDER + plots.TILE[0]]
    expected = cv2.resize(cv2.imread(str(paths[0])), plots.TILE, interpolation=cv2.INTER_NEAREST)
    np.testing.assert_array_equal(tile, expected)
