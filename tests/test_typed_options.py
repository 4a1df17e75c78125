"""A map's option sections are typed end to end (issue 38 item 3; docs/design/service.md §1.1).

The TM, sLSBH, localiser and keyframes sections reach the code as frozen dataclasses
(`models.presets.TmOptions`, `SlsbhOptions`, `models.localisation.LocaliserOptions`,
`models.geometry.KeyframeOptions`): a stored map's JSON is converted once, where its configuration is
checked (`service.maps.config.MapConfig.sections`, each section's `of`). The test walks the package's
source and fails on a string-key read of an option (`x["beam"]`, `x.get("adapt_tau")`) anywhere: a read
by name would bypass the section's defaults and types.
"""

from __future__ import annotations

import ast
import dataclasses
from collections.abc import Iterator
from pathlib import Path

from models.geometry import KeyframeOptions
from models.localisation import LocaliserOptions
from models.presets import SlsbhOptions, TmOptions

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("models", "service", "storage")

#: Every option name of the four sections.
NAMES = frozenset(f.name for cls in (TmOptions, SlsbhOptions, LocaliserOptions, KeyframeOptions)
                  for f in dataclasses.fields(cls))
#: Names other dicts use as well (a projection file's `k`, a result row's `seed`): a read of one counts
#: only from an expression that names a section.
COMMON = frozenset({"k", "s", "seed", "max", "features"})
SECTION_WORDS = ("slsbh", "s_conf", "keyframes", "localiser", "tm", "conf", "options", "params")

#: Dicts that share an option's name but are no map's section, each with why.
NOT_SECTIONS = {
    # the frontend's own configuration (backbone, runtime, its sLSBH with `projection`): the evaluations'
    # encoder, never a map's (a map's projection comes from its sections, service.maps.encoding)
    "models/frontend/embedding.py",
    # the MCN ablation's parameters (models.presets.MCN_DEFAULTS), no map option
    "models/memory/mcn.py",
    # parameter sweeps: grids and result rows keyed by the names they sweep
    "models/evaluation/sweeps/sweep.py",
    "models/evaluation/sweeps/nordland_sweep.py",
    "models/evaluation/sweeps/localiser_sweep.py",
}
#: Dicts of a module that are no map's section (path, the expression read), each with why.
NOT_SECTION_READS = {
    ("models/evaluation/bench.py", "enc.conf['slsbh']"),  # the frontend's own configuration (above)
    ("service/cli/evaluate.py", "c"),  # a run's recorded settings, printed in its report
}


def _key(node: ast.AST) -> tuple[str, ast.AST] | None:
    """(name, the expression read) of `x["name"]` or `x.get("name", ...)`."""
    if (isinstance(node, ast.Subscript) and isinstance(node.ctx, ast.Load)
            and isinstance(node.slice, ast.Constant) and isinstance(node.slice.value, str)):
        return node.slice.value, node.value
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get"
            and node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str)):
        return node.args[0].value, node.func.value
    return None


def string_key_reads(tree: ast.AST, path: str = "") -> Iterator[tuple[int, str]]:
    """(line, source) of each string-key read of an option name in `tree` (the module at `path`)."""
    for node in ast.walk(tree):
        found = _key(node)
        if found is None or found[0] not in NAMES:
            continue
        name, obj = found
        text = ast.unparse(obj)
        if name in COMMON and not any(word in text for word in SECTION_WORDS):
            continue
        if (path, text) in NOT_SECTION_READS:
            continue
        yield node.lineno, ast.unparse(node)  # type: ignore[attr-defined]


def _modules() -> Iterator[Path]:
    for top in SOURCES:
        yield from sorted((ROOT / top).rglob("*.py"))


def test_no_option_is_read_by_a_string_key() -> None:
    bad = []
    for path in _modules():
        rel = path.relative_to(ROOT).as_posix()
        if rel in NOT_SECTIONS:
            continue
        bad += [f"{rel}:{line}: {src}" for line, src in string_key_reads(ast.parse(path.read_text()), rel)]
    assert not bad, "read the typed section (MapConfig.sections, `<Section>.of`) instead:\n" + "\n".join(bad)


def test_the_walk_finds_the_reads_it_forbids() -> None:
    found = list(string_key_reads(ast.parse(
        'a = conf["beam"]\nb = config.slsbh.get("adapt_tau", 0)\nc = row["seed"]\nd = s_conf["k"]\n'
        'e = keyframes["max"]\n')))
    assert [line for line, _ in found] == [1, 2, 4, 5]


def test_a_stored_map_missing_an_option_takes_the_sections_default() -> None:
    # the one conversion: a map made before an option existed runs with its default, as it did
    assert LocaliserOptions.of({"beam": 64}) == dataclasses.replace(LocaliserOptions(), beam=64)
    assert SlsbhOptions.of({"k": 64}).adapt_tau == SlsbhOptions().adapt_tau == 0
    assert TmOptions.of({}) == TmOptions()
    assert KeyframeOptions.of({"max": 300}) == KeyframeOptions(max=300)
