"""One home per rule (issue 38 item 2; docs/architecture.md "Rules and their homes").

Each rule that was decided in several places has one home, a function the others call. `HOMES` lists
them; the test reads every module of the package and the benchmarks (not the tests: an oracle may state
a rule again on purpose) and fails where a rule's formula or decision is written anywhere but its home.
"""

from __future__ import annotations

import ast
import importlib
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("models", "service", "storage", "benchmarks")


def _text(node: ast.AST) -> str:
    return ast.unparse(node)


def _level_above_background(node: ast.AST) -> bool:
    """`b + share * (1 - b)` (or its commuted forms): a level read above a background `b`."""
    if not isinstance(node, ast.BinOp) or not isinstance(node.op, ast.Add):
        return False
    for base, scaled in ((node.left, node.right), (node.right, node.left)):
        if isinstance(scaled, ast.BinOp) and isinstance(scaled.op, ast.Mult):
            for factor in (scaled.left, scaled.right):
                if (isinstance(factor, ast.BinOp) and isinstance(factor.op, ast.Sub)
                        and isinstance(factor.left, ast.Constant) and factor.left.value == 1
                        and _text(factor.right) == _text(base)):
                    return True
    return False


#: a confidence (or an array of them): a name or attribute `conf`, `confidence(s)`, or `x["confidence"]`
_CONFIDENCE = re.compile(r"(?:^|\.)conf(?:idences?)?$|\[['\"]confidence['\"]\]$")


def _confidence_threshold(node: ast.AST) -> bool:
    """`confidence >= threshold` (or `threshold <= confidence`): the revisit decision's comparison."""
    if not isinstance(node, ast.Compare) or len(node.ops) != 1:
        return False
    op, left, right = node.ops[0], node.left, node.comparators[0]
    return ((isinstance(op, ast.GtE) and bool(_CONFIDENCE.search(_text(left))))
            or (isinstance(op, ast.LtE) and bool(_CONFIDENCE.search(_text(right)))))


def _revisit_gate(node: ast.AST) -> bool:
    """`informative and narrow`: whether an answer may be a revisit at all."""
    if not isinstance(node, ast.BoolOp) or not isinstance(node.op, ast.And):
        return False
    ends = {_text(v).rsplit(".", 1)[-1] for v in node.values}
    return {"informative", "narrow"} <= ends


def _readiness(node: ast.AST) -> bool:
    """A comprehension over check results that compares to "fail": which checks fail (ready iff none)."""
    if not isinstance(node, (ast.ListComp, ast.SetComp, ast.GeneratorExp, ast.DictComp)):
        return False
    return any(isinstance(n, ast.Compare) and any(isinstance(c, ast.Constant) and c.value == "fail"
                                                  for c in [*n.comparators, n.left])
               for n in ast.walk(node))


#: the names of a map's states (service/maps/states.py)
_MAP_STATES = {"ready", "replaying", "recovering", "failed"}


def _map_state(node: ast.AST) -> bool:
    """A map's state compared with a state's name (`m.state == "ready"`, `state in ("ready", ...)`, a
    `case "failed":`): what a map in that state serves, decided."""
    if isinstance(node, ast.MatchValue):
        return isinstance(node.value, ast.Constant) and node.value.value in _MAP_STATES
    if not isinstance(node, ast.Compare):
        return False
    sides = [node.left, *node.comparators]
    named = {c.value for n in sides for c in ast.walk(n) if isinstance(c, ast.Constant)} & _MAP_STATES
    return bool(named) and any(re.search(r"state['\"\]]*$", _text(n)) for n in sides)


_SEQUENCE = {"last_learned_seq", "own_seq"}


def _sequence_reset(node: ast.AST) -> bool:
    """A stream's context emptied (`x.context.reset()`) or its sequence bookkeeping set to None: the
    start of a new sequence."""
    if isinstance(node, ast.Call):
        f = node.func
        return (isinstance(f, ast.Attribute) and f.attr == "reset" and isinstance(f.value, ast.Attribute)
                and f.value.attr == "context")
    if isinstance(node, ast.Assign):
        targets = [t for tgt in node.targets for t in (tgt.elts if isinstance(tgt, ast.Tuple) else [tgt])]
        return (any(isinstance(t, ast.Attribute) and t.attr in _SEQUENCE for t in targets)
                and any(isinstance(c, ast.Constant) and c.value is None for c in ast.walk(node.value)))
    return False


#: rule -> (its home "path:qualified name", how its decision reads when written out). The docs list the
#: same (docs/architecture.md "Rules and their homes").
HOMES: dict[str, tuple[str, Callable[[ast.AST], bool]]] = {
    "level above background": ("models/localisation/trail.py:above_background", _level_above_background),
    "revisit threshold": ("models/localisation/localiser.py:reaches", _confidence_threshold),
    "revisit gate": ("models/localisation/localiser.py:Place.decidable", _revisit_gate),
    "sequence reset": ("models/pipeline/state.py:Stream.new_sequence", _sequence_reset),
    "readiness": ("service/routes/health.py:failing", _readiness),
    "what a map's state serves": ("service/maps/states.py:serving", _map_state),
}


def _functions(tree: ast.AST, prefix: str = "") -> Iterator[tuple[str, ast.AST]]:
    """(qualified name, node) of every function and class body in `tree`, outermost first."""
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            name = f"{prefix}{node.name}"
            yield name, node
            yield from _functions(node, name + ".")
        else:
            yield from _functions(node, prefix)


def where(source: str, path: str, found: Callable[[ast.AST], bool]) -> list[str]:
    """`path:line (innermost function)` of each place in `source` where `found` matches."""
    tree = ast.parse(source)
    owner: dict[int, str] = {}
    for name, fn in _functions(tree):  # inner functions come later and overwrite their lines
        for n in ast.walk(fn):
            if hasattr(n, "lineno"):
                owner[id(n)] = name
    return [f"{path}:{n.lineno} ({owner.get(id(n), '<module>')})" for n in ast.walk(tree) if found(n)]


def _modules() -> Iterator[Path]:
    for top in SOURCES:
        yield from sorted((ROOT / top).rglob("*.py"))


@pytest.mark.parametrize("rule", sorted(HOMES))
def test_each_rule_is_decided_in_its_home_only(rule: str) -> None:
    home, found = HOMES[rule]
    path, _, qualname = home.partition(":")
    hits = [h for p in _modules() for h in where(p.read_text(), p.relative_to(ROOT).as_posix(), found)]
    inside = [h for h in hits if h.startswith(path + ":") and h.endswith(f"({qualname})")]
    assert inside, f"{rule}: not found in its home {home} (moved? update HOMES and docs/architecture.md)"
    elsewhere = [h for h in hits if h not in inside]
    assert not elsewhere, f"{rule} is decided outside its home {home}: call it instead at {elsewhere}"


@pytest.mark.parametrize("rule", sorted(HOMES))
def test_each_home_exists(rule: str) -> None:
    path, _, qualname = HOMES[rule][0].partition(":")
    obj = importlib.import_module(path.removesuffix(".py").replace("/", "."))
    for part in qualname.split("."):
        obj = getattr(obj, part)


@pytest.mark.parametrize(("rule", "duplicate"), [
    ("level above background", "level = b + c * (1.0 - b)"),
    ("level above background", "level = (1 - bg) * departure + bg"),
    ("revisit threshold", "called = answered & (found.confidence >= t)"),
    ("revisit threshold", "ok = threshold <= conf"),
    ("revisit gate", "ok = place.informative and place.narrow and not refused"),
    ("sequence reset", "st.step, st.last_learned_seq, st.own_seq = 0, None, None"),
    ("sequence reset", "st.context.reset()"),
    ("readiness", "ready = all(c.get('status') != 'fail' for c in checks.values())"),
    ("what a map's state serves", "ok = self.state == 'ready'"),
    ("what a map's state serves", "ok = m.state in ('ready', 'replaying')"),
    ("what a map's state serves", "bad = [k for k, v in states.items() if v['state'] == 'recovering']"),
])
def test_a_duplicate_is_found(rule: str, duplicate: str) -> None:
    """The check sees each rule written out again (so the test above would fail on it)."""
    assert where(f"def f():\n    {duplicate}\n", "x.py", HOMES[rule][1]) == ["x.py:2 (f)"]


def test_the_docs_list_the_homes() -> None:
    """docs/architecture.md names each rule's home as the table does."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    for rule, (home, _) in HOMES.items():
        assert f"{rule}: `{home}`" in text, f"docs/architecture.md lacks '{rule}: `{home}`'"
