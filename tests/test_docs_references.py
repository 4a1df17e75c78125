"""What the docs name exists in the code: module paths, `package.module` names, `cortexloc` commands and the
map schema version (issue 38 item 6).

- **Modules.** In README.md, CHANGELOG.md and the Markdown files under docs/, a path of ours anywhere
  (`models/…/x.py`, a folder `service/maps/`, optionally `x.py:name` or `x.py: NAME`; docs/architecture.md's
  rooms and its walk of an observation are made of them) and a dotted name of ours in backticks
  (`service.maps.runtime.MapRuntime`; in prose a sentence ends with a dot) must name a file or folder of
  the repository, and the `:name`, or the first attribute after the module, a name the module binds
  (read with `ast`, nothing imported). A name beyond the first attribute (`Class.method`) is not checked.
- **Commands.** `cortexloc <command> [<sub>]` in backticks or at the start of a code-block line must be a
  command of the typer app (`service/cli/`), and a sub-command of a group one of the group's. The other
  way round, every `cortexloc eval` and `cortexloc bench` command (the experiments and the benchmarks,
  docs/benchmarks.md) is written in README.md or docs/ at least once.
- **Schema.** `storage/mapschema.py`'s docstring and docs/design/service.md §4.2 say what every map.sqlite
  version from 2 to `SCHEMA_VERSION` added, CHANGELOG.md has an entry for `SCHEMA_VERSION` (what an
  existing map keeps), and no doc names a schema version above it.

Everything is compared with the code as it is, never with a number written here.
"""

from __future__ import annotations

import ast
import functools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = "docs/architecture.md"
SERVICE_DESIGN = "docs/design/service.md"
MAPSCHEMA = "storage/mapschema.py"
PACKAGES = ("models", "storage", "service", "clients", "benchmarks", "tests")
DOTTED_PACKAGES = ("models", "storage", "service")  # importable top-level packages of the repository

FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)
INLINE = re.compile(r"`([^`\n]+)`")
# A repository path of ours: a .py file (with an optional `:name` / `: NAME`) or a folder ending in `/`.
PATH = re.compile(r"(?<![\w./-])((?:" + "|".join(PACKAGES) + r")/[\w./-]*?(?:\.py|/))(?::\s?([A-Za-z_]\w*))?"
                  r"(?![\w-])")
DOTTED = re.compile(r"(?<![\w./-])((?:" + "|".join(DOTTED_PACKAGES) + r")(?:\.[A-Za-z_]\w*)+)(?![\w/-])")
NOT_MODULES = (".md", ".py", ".json", ".toml", ".txt", ".sqlite", ".yaml", ".html")
#: Dotted names that are not modules: fields of the memory resource (`GET /v1/maps/{id}/memory`).
NOT_DOTTED = frozenset({"storage.keyframes", "storage.keyframe_bytes"})
#: Folders a command makes, ignored by git (`make bench` writes its JSON there).
OUTPUTS = ("benchmarks/results/",)
# A command line: optional `$ `, environment assignments and a path to the script, then `cortexloc`.
COMMAND = re.compile(r"^(?:\$\s+)?(?:[A-Z_]+=\S*\s+)*(?:\S*/)?cortexloc(?P<rest>(?:\s.*)?)$")
WORD = re.compile(r"^[a-z][a-z0-9-]*$")


@dataclass(frozen=True)
class Ref:
    doc: str  # relative to the root
    line: int
    text: str  # as written

    def __str__(self) -> str:
        return f"{self.doc}:{self.line}: {self.text}"


def documents(root: Path) -> list[Path]:
    """The Markdown files whose references are checked."""
    docs = [root / "README.md", root / "CHANGELOG.md", *sorted((root / "docs").rglob("*.md"))]
    return [p for p in docs if p.is_file()]


def _line(text: str, pos: int) -> int:
    return text.count("\n", 0, pos) + 1


def command_lines(text: str) -> Iterator[tuple[int, str]]:
    """(offset, words after `cortexloc`) of every command written in a Markdown text: a code-block line
    that starts with it, or a backticked span that does."""
    blocks = [(m.start(), m.end()) for m in FENCE.finditer(text)]
    for a, b in blocks:
        pos = a
        for line in text[a:b].split("\n"):
            m = COMMAND.match(line.strip())
            if m:
                yield pos, m["rest"]
            pos += len(line) + 1
    for m in INLINE.finditer(text):
        if any(a <= m.start() < b for a, b in blocks):
            continue
        c = COMMAND.match(m.group(1).strip())
        if c:
            yield m.start(1), c["rest"]


# ------------------------------------------------------------------------------------------ modules


@functools.cache
def bound_names(path: Path) -> frozenset[str]:
    """Every name a Python file binds at any depth: functions, classes, assignments, imports."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
            names.add(node.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((a.asname or a.name).split(".")[0] for a in node.names)
    return frozenset(names)


def module_file(root: Path, dotted: list[str]) -> Path | None:
    """The file of module `dotted` (a package's __init__.py), or None."""
    base = root.joinpath(*dotted)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def path_problem(root: Path, path: str, name: str | None) -> str | None:
    target = root / path
    if path in OUTPUTS:
        return None
    if path.endswith("/"):
        return None if target.is_dir() else "no such folder"
    if not target.is_file():
        return "no such file"
    if name is not None and name not in bound_names(target):
        return f"{path} defines no `{name}`"
    return None


def dotted_problem(root: Path, dotted: str) -> str | None:
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        found = module_file(root, parts[:n])
        if found is not None:
            break
    else:
        return "no such module"
    rest = parts[n:]
    # (a submodule its package does not import is still a module: `pkg.sub` with pkg/sub/ a folder)
    if rest and rest[0] not in bound_names(found) and not root.joinpath(*parts[:n + 1]).is_dir():
        return f"{'.'.join(parts[:n])} has no `{rest[0]}`"
    return None


def module_problems(root: Path) -> tuple[int, list[str]]:
    """(references checked, one line per reference to a module, folder or name that does not exist)."""
    checked, out = 0, []
    for doc in documents(root):
        rel = doc.relative_to(root).as_posix()
        text = doc.read_text(encoding="utf-8")
        for m in PATH.finditer(text):
            checked += 1
            why = path_problem(root, m[1], m[2])
            if why:
                out.append(f"{Ref(rel, _line(text, m.start()), m[0])}: {why}")
        # dotted names only in backticks, code blocks included (in prose a sentence ends with `.`)
        for m in INLINE.finditer(text):
            for d in DOTTED.finditer(m.group(1)):
                if d[1].endswith(NOT_MODULES) or d[1] in NOT_DOTTED:
                    continue
                checked += 1
                why = dotted_problem(root, d[1])
                if why:
                    out.append(f"{Ref(rel, _line(text, m.start(1) + d.start()), d[1])}: {why}")
    return checked, out


# ------------------------------------------------------------------------------------------ commands


def command_tree() -> dict[str, dict]:
    """The typer app's commands: name -> its sub-commands' tree ({} for a command that takes none)."""
    import typer.main

    from service.cli import app

    def tree(cmd) -> dict[str, dict]:
        return {name: tree(sub) for name, sub in getattr(cmd, "commands", {}).items()}

    return tree(typer.main.get_command(app))


def command_problem(tree: dict[str, dict], words: str) -> str | None:
    """Why `cortexloc <words>` names no command of `tree`, or None. At each group level the next word
    (and its `|` alternatives) must be a command; an option, a placeholder or a path ends the check."""
    tokens = words.replace("|", " | ").split()
    level, i = tree, 0
    while level and i < len(tokens):
        names = [tokens[i]]
        while i + 2 < len(tokens) and tokens[i + 1] == "|":
            names.append(tokens[i + 2])
            i += 2
        if not all(WORD.match(n) for n in names):
            return None  # an option, a placeholder (MAP, <cmd>, ...), a path: no more command words
        for name in names:
            if name not in level:
                return f"no command `{name}` (there are: {', '.join(sorted(level))})"
        if len(names) > 1:
            return None
        level, i = level[names[0]], i + 1
    return None


def command_problems(root: Path, tree: dict[str, dict]) -> tuple[int, list[str]]:
    checked, out = 0, []
    for doc in documents(root):
        rel = doc.relative_to(root).as_posix()
        text = doc.read_text(encoding="utf-8")
        for offset, words in command_lines(text):
            checked += 1
            why = command_problem(tree, words)
            if why:
                out.append(f"{Ref(rel, _line(text, offset), 'cortexloc' + words)}: {why}")
    return checked, out


DOCUMENTED_GROUPS = ("eval", "bench")  # every command of these groups is documented somewhere


def documented_commands(root: Path) -> set[tuple[str, ...]]:
    """(group, sub-command) pairs, and lone commands, that README.md or docs/ write after `cortexloc`
    (`|` alternatives each count)."""
    found: set[tuple[str, ...]] = set()
    for doc in documents(root):
        for _, words in command_lines(doc.read_text(encoding="utf-8")):
            tokens = words.replace("|", " | ").split()
            if not tokens:
                continue
            found.add((tokens[0],))
            i = 1
            while i < len(tokens) and WORD.match(tokens[i]):
                found.add((tokens[0], tokens[i]))
                if i + 2 < len(tokens) and tokens[i + 1] == "|":
                    i += 2
                else:
                    break
    return found


def undocumented_commands(root: Path, tree: dict[str, dict]) -> list[str]:
    """`cortexloc GROUP NAME` for each command of DOCUMENTED_GROUPS that no doc writes."""
    said = documented_commands(root)
    return [f"cortexloc {group} {name}" for group in DOCUMENTED_GROUPS for name in sorted(tree.get(group, {}))
            if (group, name) not in said]


# ------------------------------------------------------------------------------------------ schema


SCHEMA_SENTENCE = re.compile(r"[Ss]chema\s+version\s+(\d+)\s+added")
SCHEMA_MENTION = re.compile(r"\b(?:map\.sqlite )?[Ss]chema (?:version )?(\d+)\b")


def section(text: str, number: str) -> str:
    """The text of the Markdown section `number` (its heading to the next heading of any level)."""
    m = re.search(r"^#{1,6}\s+" + re.escape(number) + r"\s.*?$(.*?)(?=^#{1,6}\s|\Z)", text,
                  re.MULTILINE | re.DOTALL)
    assert m, f"no section {number}"
    return m.group(1)


def schema_problems(root: Path, version: int) -> list[str]:
    out = []
    wanted = set(range(2, version + 1))
    doc = ast.get_docstring(ast.parse((root / MAPSCHEMA).read_text(encoding="utf-8"))) or ""
    said = {int(n) for n in re.findall(r"\b[Vv]ersion\s+(\d+)\b", doc)}
    if wanted - said:
        out.append(f"{MAPSCHEMA}'s docstring says nothing of schema version(s) {sorted(wanted - said)}")
    if said - set(range(1, version + 1)):
        out.append(f"{MAPSCHEMA}'s docstring names version(s) {sorted(said - set(range(1, version + 1)))}"
                   f" beyond SCHEMA_VERSION {version}")
    design = section((root / SERVICE_DESIGN).read_text(encoding="utf-8"), "4.2")
    added = {int(n) for n in SCHEMA_SENTENCE.findall(design)}
    if added != wanted:
        out.append(f"{SERVICE_DESIGN} §4.2 says 'Schema version N added' for {sorted(added)}, "
                   f"the code's versions 2..{version} are {sorted(wanted)}")
    changelog = root / "CHANGELOG.md"
    if changelog.is_file() and f"map.sqlite schema {version}" not in changelog.read_text(encoding="utf-8"):
        out.append(f"CHANGELOG.md does not say what map.sqlite schema {version} changed for an existing map")
    for path in documents(root):
        text = path.read_text(encoding="utf-8")
        for m in SCHEMA_MENTION.finditer(text):
            if int(m[1]) > version:
                out.append(f"{Ref(path.relative_to(root).as_posix(), _line(text, m.start()), m[0])}: "
                           f"SCHEMA_VERSION is {version}")
    return out


# ------------------------------------------------------------------------------------------ the repository


def test_documented_modules_exist():
    checked, bad = module_problems(ROOT)
    assert checked > 200  # architecture.md alone names well over a hundred; few would mean a broken pattern
    assert not bad, f"{len(bad)} of {checked} module references name nothing:\n" + "\n".join(bad)


def test_documented_commands_exist():
    tree = command_tree()
    checked, bad = command_problems(ROOT, tree)
    assert checked > 50
    assert not bad, f"{len(bad)} of {checked} documented commands do not exist:\n" + "\n".join(bad)


def test_every_experiment_and_benchmark_command_is_documented():
    tree = command_tree()
    assert len(tree["eval"]) > 20 and len(tree["bench"]) > 20
    assert undocumented_commands(ROOT, tree) == []


def test_documented_schema_versions_are_the_code_s():
    from storage.mapschema import SCHEMA_VERSION

    assert not schema_problems(ROOT, SCHEMA_VERSION)


# ------------------------------------------------------------------------------------------ the checker


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text, encoding="utf-8")
    return tmp_path


def test_a_module_or_name_that_is_gone_is_reported(tmp_path):
    root = _tree(tmp_path, {
        "models/__init__.py": "",
        "models/a.py": "from models.b import C\n\ndef f():\n    x = 1\n",
        "models/b.py": "class C:\n    def m(self): ...\n",
        "docs/architecture.md": ("# A\n\n```\nstep   models/a.py:f, models/a.py:x, models/a.py:gone\n```\n"
                                 "- `models/b.py`: C. `models/c.py` and `models/d/`\n"
                                 "- `models.a.C`, `models.a.h`, `models.e`, `models.b.C.anything`\n"),
        "README.md": ("In prose models/a.py is checked, but not models.gone.\n\n"
                      "```\npython models/z.py\n```\n`storage.keyframes` (a field), `service.md` (a file)\n"),
    })
    checked, bad = module_problems(root)
    assert bad == [
        "README.md:4: models/z.py: no such file",
        "docs/architecture.md:4: models/a.py:gone: models/a.py defines no `gone`",
        "docs/architecture.md:6: models/c.py: no such file",
        "docs/architecture.md:6: models/d/: no such folder",
        "docs/architecture.md:7: models.a.h: models.a has no `h`",
        "docs/architecture.md:7: models.e: models has no `e`",
    ]
    assert checked == 12


def test_a_command_that_is_gone_is_reported(tmp_path):
    tree = {"eval": {"grid": {}, "images": {}}, "serve": {}, "shards": {"list": {}, "move": {}}}
    for ok in (" eval grid --seeds 3", " eval grid | images ...", " eval", " serve --ray", " shards move MAP",
               " eval <cmd>", " serve"):
        assert command_problem(tree, ok) is None, ok
    assert command_problem(tree, " eval slam --half tune") == "no command `slam` (there are: grid, images)"
    assert command_problem(tree, " bench tm").startswith("no command `bench`")
    assert command_problem(tree, " eval grid | slam").startswith("no command `slam`")
    text = ("Run `cortexloc eval gone`, or\n\n```\n$ cortexloc bench tm\n"
            "CORTEXLOC_X=1 .venv/bin/cortexloc serve\npython -m x cortexloc nothing\n```\n"
            "Not a command: cortexloc answers.\n")
    root = _tree(tmp_path, {"README.md": text})
    checked, bad = command_problems(root, tree)
    assert checked == 3
    assert bad == ["README.md:4: cortexloc bench tm: no command `bench` (there are: eval, serve, shards)",
                   "README.md:1: cortexloc eval gone: no command `gone` (there are: grid, images)"]


def test_a_schema_version_the_docs_do_not_describe_is_reported(tmp_path):
    files = {
        MAPSCHEMA: '"""Version 2 added metadata; version 3 the closures."""\nSCHEMA_VERSION = 3\n',
        SERVICE_DESIGN: ("## 4. Storage\n### 4.2 Schema\nSchema version 3 added closures. Schema\n"
                         "version 2 added metadata.\n### 4.3 Next\nThe durable write.\n"),
        "CHANGELOG.md": "## Round 2 (map.sqlite schema 3)\n",
    }
    assert schema_problems(_tree(tmp_path, files), 3) == []
    (tmp_path / "docs/scaling.md").write_text("Schema version 9 added nothing.\n", encoding="utf-8")
    bad = schema_problems(tmp_path, 4)  # the code moved on, the docs did not
    assert bad[0] == f"{MAPSCHEMA}'s docstring says nothing of schema version(s) [4]"
    assert bad[1].startswith(f"{SERVICE_DESIGN} §4.2 says 'Schema version N added' for [2, 3]")
    assert bad[2:] == ["CHANGELOG.md does not say what map.sqlite schema 4 changed for an existing map",
                       "docs/scaling.md:1: Schema version 9: SCHEMA_VERSION is 4"]
    assert schema_problems(tmp_path, 2)[0] == (f"{MAPSCHEMA}'s docstring names version(s) [3] beyond "
                                               "SCHEMA_VERSION 2")


def test_an_undocumented_command_is_reported(tmp_path):
    root = _tree(tmp_path, {
        "README.md": "```\ncortexloc eval grid --seeds 3\ncortexloc bench http | index [--quick]\n```\n",
        "docs/benchmarks.md": "Run `cortexloc bench all --quick`; `cortexloc eval` alone names none.\n",
    })
    tree = {"eval": {"grid": {}, "span": {}}, "bench": {"http": {}, "index": {}, "all": {}, "gpu": {}},
            "serve": {}}
    assert undocumented_commands(root, tree) == ["cortexloc eval span", "cortexloc bench gpu"]
