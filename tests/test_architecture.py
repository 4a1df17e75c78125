"""The house's rules, enforced (docs/architecture.md): the layers as import-linter contracts
(pyproject.toml `[tool.importlinter]`), no import cycle (type-checking-only imports included), and no
private module or name imported from another package."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("models", "storage", "service")


@pytest.fixture(scope="module")
def graph() -> grimp.ImportGraph:
    sys.path.insert(0, str(ROOT))
    try:
        return grimp.build_graph(*PACKAGES, include_external_packages=False)
    finally:
        sys.path.remove(str(ROOT))


def test_the_layer_contracts_hold():
    """routes -> domain -> models -> storage.base; no HTTP module imports storage's stores; storage
    imports nothing of the models; the models use only storage.base; the models' stages apart (each
    contract is named in pyproject.toml). In a child process: import-linter reconfigures logging, which
    later tests' log captures would miss."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    code = ("import sys; from importlinter.cli import lint_imports; "
            "sys.exit(lint_imports(config_filename='pyproject.toml', no_cache=True))")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]


def cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on.add(root)
        while work:
            v, children = work[-1]
            for w in children:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.find_modules_directly_imported_by(w)))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        found.append(sorted(comp))
    return found


def test_no_import_cycles(graph):
    """Between modules, TYPE_CHECKING imports included (grimp keeps them), and between the sub-packages
    of a package (a cycle through two packages' modules is a cycle of the packages)."""
    assert cycles(graph) == []
    for package in ("service", "service.maps", "models", "storage"):
        children = sorted(graph.find_children(package))
        mutual = [(a, b) for a in children for b in children
                  if a < b and all(graph.chain_exists(x, y, as_packages=True) for x, y in ((a, b), (b, a)))]
        assert mutual == [], f"sub-packages of {package} that import each other"


def test_the_cycle_finder_finds_a_cycle():
    g = grimp.ImportGraph()
    for m in ("p.a", "p.b", "p.c"):
        g.add_module(m)
    g.add_import(importer="p.a", imported="p.b")
    g.add_import(importer="p.b", imported="p.a")
    g.add_import(importer="p.b", imported="p.c")
    assert cycles(g) == [["p.a", "p.b"]]


def private_imports(root: Path) -> list[str]:
    """`module: target` for each import of a private module or name (a `_x` component) from outside the
    package that owns it."""
    bad = []
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            rel = path.relative_to(root).with_suffix("")
            parts = list(rel.parts)
            if parts[-1] == "__init__":
                parts.pop()
            module = ".".join(parts)
            own = module if path.name == "__init__.py" else module.rpartition(".")[0]
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                targets: list[str] = []
                if isinstance(node, ast.Import):
                    targets = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                    targets = [f"{node.module}.{a.name}" for a in node.names]
                for target in targets:
                    if target.split(".")[0] not in PACKAGES:
                        continue
                    names = target.split(".")
                    for i, name in enumerate(names):
                        if name.startswith("_") and not name.startswith("__"):
                            # a private module belongs to its package, a private name to its module's
                            is_module = (root.joinpath(*names[:i + 1]).is_dir()
                                         or root.joinpath(*names[:i], name + ".py").is_file())
                            owner = ".".join(names[:i] if is_module else names[:max(i - 1, 1)])
                            if not (own == owner or own.startswith(owner + ".")):
                                bad.append(f"{module}: {target}")
                            break
    return bad


def test_no_private_import_across_packages():
    assert private_imports(ROOT) == []


def test_the_private_import_check_finds_one(tmp_path):
    for package in PACKAGES:
        (tmp_path / package).mkdir()
        (tmp_path / package / "__init__.py").write_text("")
    (tmp_path / "storage" / "_common.py").write_text("X = 1\n")
    (tmp_path / "storage" / "catalog.py").write_text("from storage._common import X\n")
    (tmp_path / "service" / "errors.py").write_text("from storage._common import X\n")
    (tmp_path / "models" / "memory").mkdir()
    (tmp_path / "models" / "memory" / "_tm_kernels.py").write_text("def step(): ...\n")
    own = "from models.memory._tm_kernels import step\n"  # inside its package: allowed
    (tmp_path / "models" / "memory" / "temporal_memory.py").write_text(own)
    (tmp_path / "service" / "maps.py").write_text("from models.memory._tm_kernels import step\n"
                                                  "from storage.catalog import _private\n")
    assert private_imports(tmp_path) == ["service.errors: storage._common.X",
                                         "service.maps: models.memory._tm_kernels.step",
                                         "service.maps: storage.catalog._private"]


#: Modules of models/, service/ or benchmarks/ allowed to parse a command line with argparse: none.
#: Experiments and benchmarks are `cortexloc eval` / `cortexloc bench` commands (benchmarks/__init__.py).
ARGPARSE_ALLOWED: frozenset[str] = frozenset()
COMMAND_HOMES = ("models", "service", "benchmarks")


def argparse_users(root: Path) -> list[str]:
    """The .py files under models/, service/ and benchmarks/ that import argparse, or call
    `ArgumentParser` or `parse_args` (however argparse was reached)."""
    found = []
    for home in COMMAND_HOMES:
        for path in sorted((root / home).rglob("*.py")):
            for n in ast.walk(ast.parse(path.read_text(), str(path))):
                imported = (isinstance(n, (ast.Import, ast.ImportFrom))
                            and "argparse" in {a.name for a in n.names} | {getattr(n, "module", None)})
                called = (isinstance(n, ast.Call) and isinstance(n.func, (ast.Attribute, ast.Name))
                          and getattr(n.func, "attr", getattr(n.func, "id", None)) in ("ArgumentParser",
                                                                                     "parse_args"))
                if imported or called:
                    found.append(path.relative_to(root).as_posix())
                    break
    return found


def test_one_command_line_library_for_commands_and_experiments():
    """`cortexloc` is typer; no module of models/, service/ or benchmarks/ parses arguments another way:
    every experiment and benchmark is a `cortexloc eval` / `cortexloc bench` command."""
    assert [p for p in argparse_users(ROOT) if p not in ARGPARSE_ALLOWED] == []


def test_the_argparse_check_finds_one(tmp_path):
    for home in COMMAND_HOMES:
        (tmp_path / home).mkdir()
    (tmp_path / "benchmarks" / "bench_x.py").write_text("import argparse\n")
    (tmp_path / "models" / "sweep.py").write_text("from argparse import ArgumentParser\n")
    (tmp_path / "service" / "tool.py").write_text("def main(ap):\n    return ap.parse_args()\n")
    (tmp_path / "service" / "fine.py").write_text("import typer\n")
    assert argparse_users(tmp_path) == ["models/sweep.py", "service/tool.py", "benchmarks/bench_x.py"]
