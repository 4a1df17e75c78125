"""Every `§` citation in the repository's code and docs leads to a section of a document in the repository.

A citation is `<file>.md §N[.N…]` (optionally with more sections after it: `§3.7, §7`, `§1.2–§1.4`,
`§3.7/§3.8`).
How the file is found:

- a path with a folder (`docs/design/science.md §3.5`, the form the code uses) is relative to the
  repository root;
- a bare name (`results.md §7`) must name exactly one file under `docs/`; two files of that name make
  the citation ambiguous and it fails, so a bare name stays readable only while it cannot be misread.

The section is found when the file has a Markdown heading that starts with its number (`## 3. Temporal
Memory`, `### 3.5 Bounded memory`). Bare `§N` without a file name (inside a module that names its
document once) is not checked here, nor is this file, whose samples cite made-up documents.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SELF = Path(__file__).resolve()
DOCS = "docs"

_SECTION = r"\d+(?:\.\d+)*"
# The file name, an optional closing backtick, blanks or a comment marker (a citation broken over two
# comment lines), then `§N` and any further `, §M` / `–§M` / `/§M` / `and §M` sections.
CITATION = re.compile(
    r"(?P<file>[A-Za-z0-9_][A-Za-z0-9_./-]*\.md)`?(?:\s|#)*§\s?(?P<first>" + _SECTION + r")"
    r"(?P<more>(?:\s*(?:,|–|-|/|and|to)\s*§\s?" + _SECTION + r")*)")
_MORE = re.compile(r"§\s?(" + _SECTION + r")")
HEADING = re.compile(r"^#{1,6}\s+§?\s*(" + _SECTION + r")\.?(?:\s|$)", re.MULTILINE)


@dataclass(frozen=True)
class Citation:
    source: Path  # the citing file, relative to the root
    line: int
    file: str  # as written
    section: str

    def __str__(self) -> str:
        return f"{self.source}:{self.line}: {self.file} §{self.section}"


def _text_files(root: Path) -> Iterator[Path]:
    for folder, dirs, files in os.walk(root):
        # Pruned, not filtered: a .venv inside the clone holds tens of thousands of files.
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d != "__pycache__")
        for name in sorted(files):
            path = Path(folder) / name
            if path.suffix in (".py", ".md") and path != SELF:
                yield path


def citations(root: Path) -> list[Citation]:
    """Every `<file>.md §N` citation in the .py and .md files under `root`."""
    out = []
    for path in _text_files(root):
        text = path.read_text(encoding="utf-8")
        for m in CITATION.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            rel = path.relative_to(root)
            for section in [m["first"], *_MORE.findall(m["more"])]:
                out.append(Citation(rel, line, m["file"], section))
    return out


def headings(path: Path) -> set[str]:
    """Section numbers that have a heading in the Markdown file `path`."""
    return set(HEADING.findall(path.read_text(encoding="utf-8")))


def resolve(root: Path, name: str) -> tuple[Path | None, str]:
    """The document a citation names, or None and why not."""
    if "/" in name:
        path = root / name
        return (path, "") if path.is_file() else (None, f"no file {name} in the repository")
    found = sorted((root / DOCS).rglob(name)) if (root / DOCS).is_dir() else []
    if len(found) == 1:
        return found[0], ""
    if not found:
        return None, f"no file named {name} under {DOCS}/"
    names = ", ".join(str(p.relative_to(root)) for p in found)
    return None, f"{name} is ambiguous ({names}): cite it with its path"


def problems(root: Path) -> list[str]:
    """One line per citation that does not lead to a section heading inside `root`."""
    out, cache = [], {}
    for c in citations(root):
        path, why = resolve(root, c.file)
        if path is None:
            out.append(f"{c}: {why}")
            continue
        if path not in cache:
            cache[path] = headings(path)
        if c.section not in cache[path]:
            out.append(f"{c}: {path.relative_to(root)} has no heading for §{c.section}")
    return out


# ------------------------------------------------------------------------------------------ the repository


def test_every_citation_leads_to_a_section_inside_the_repository():
    found = citations(ROOT)
    assert len(found) > 100  # the code cites its design documents throughout; 0 would mean a broken pattern
    bad = problems(ROOT)
    assert not bad, f"{len(bad)} of {len(found)} citations do not resolve:\n" + "\n".join(bad)


# ------------------------------------------------------------------------------------------ the checker


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text, encoding="utf-8")
    return tmp_path


_DESIGN = "# Design\n\n## 3. Memory\n\n### 3.5 Bounded memory\n\n### 3.7 Presets\n\n## 7. Hashing\n"


def test_citation_forms_are_recognised(tmp_path):
    root = _tree(tmp_path, {
        "docs/design/theory.md": _DESIGN,
        "m.py": ('"""As in docs/design/theory.md §3.5 and `theory.md` §3.7, §7."""\n'
                 "# the > 90 % of docs/design/theory.md\n# §3.7, a citation over two comment lines\n"
                 "x = 1  # theory.md §3.5. Sentence ends; theory.md §3.5–§3.7 a range\n"
                 "y = 2  # theory.md §3.5/§7 a pair\n"),
    })
    got = [(c.line, c.file, c.section) for c in citations(root)]
    assert got == [(1, "docs/design/theory.md", "3.5"), (1, "theory.md", "3.7"), (1, "theory.md", "7"),
                   (2, "docs/design/theory.md", "3.7"), (4, "theory.md", "3.5"),
                   (4, "theory.md", "3.5"), (4, "theory.md", "3.7"), (5, "theory.md", "3.5"),
                   (5, "theory.md", "7")]
    assert problems(root) == []


def test_missing_files_sections_and_ambiguous_names_are_reported(tmp_path):
    root = _tree(tmp_path, {
        "docs/design/theory.md": _DESIGN,
        "docs/design/api.md": "## 1. Endpoints\n",
        "docs/old/api.md": "## 1. Endpoints\n",
        "m.py": ("# docs/design/theory.md §3.6\n# docs/spec/theory.md §3.5\n# api.md §1\n"
                 "# results.md §7\n# theory.md §3.5\n"),
        ".venv/lib/x.py": "# theory.md §99\n",  # outside the checked tree
    })
    assert problems(root) == [
        "m.py:1: docs/design/theory.md §3.6: docs/design/theory.md has no heading for §3.6",
        "m.py:2: docs/spec/theory.md §3.5: no file docs/spec/theory.md in the repository",
        "m.py:3: api.md §1: api.md is ambiguous (docs/design/api.md, docs/old/api.md): "
        "cite it with its path",
        "m.py:4: results.md §7: no file named results.md under docs/",
    ]
