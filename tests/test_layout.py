"""The tests mirror the source tree (issue 38 item 5; docs/architecture.md, "Elsewhere"): a test file
sits in the folder of the package it tests, `tests/service/maps/runtime/` for `service/maps/runtime/`,
`tests/clients/ros2/` for `clients/ros2/`, so that a module's tests are found where the module is.

A folder of tests mirrors a source folder when the same path without `tests/` is a folder of the
repository that holds Python code. The cross-cutting suites are the stated exceptions (`CROSS_CUTTING`).
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Test folders that test no one package, each with its reason.
CROSS_CUTTING = {
    # the whole repository at once: import contracts, docs, rule homes, typed options, benchmarks' smoke
    "tests": "the house's own checks",
    # whole processes over HTTP: `cortexloc serve`, a crash, the Ray scale-out, the viewer in a browser
    "tests/e2e": "end-to-end runs of the service",
}


def misplaced(root: Path) -> list[str]:
    """The test files (`test_*.py` under `root/tests`) whose folder is neither cross-cutting nor the
    mirror of a folder of Python code outside `tests/`."""
    out = []
    for path in sorted((root / "tests").rglob("test_*.py")):
        folder = path.parent.relative_to(root).as_posix()
        if folder in CROSS_CUTTING:
            continue
        source = root / Path(folder).relative_to("tests")
        if not (source.is_dir() and any(source.rglob("*.py"))):
            out.append(f"{path.relative_to(root).as_posix()}: no source folder {source.relative_to(root)}/")
    return out


def test_every_test_file_sits_in_the_mirror_of_a_source_package() -> None:
    wrong = misplaced(ROOT)
    assert not wrong, "test files outside the mirror of the source tree:\n" + "\n".join(wrong)


def test_a_test_folder_that_mirrors_nothing_is_found(tmp_path: Path) -> None:
    for rel in ("service/maps/__init__.py", "tests/service/maps/test_a.py", "tests/e2e/test_b.py",
                "tests/test_c.py", "tests/service/http/test_d.py", "tests/ingest/test_e.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("", encoding="utf-8")
    assert misplaced(tmp_path) == ["tests/ingest/test_e.py: no source folder ingest/",
                                   "tests/service/http/test_d.py: no source folder service/http/"]
