"""Every reference to a document resolves inside the repository.

The repository must explain itself through ``docs/``. This test scans the repository's text
files (.py, .ipynb, .md, .cfg, .toml, .txt) and reports:

- references that leave the repository (a parent folder's ``shared`` notes, absolute machine
  paths);
- bare names of design notes that are not part of the repository (the upper-case method,
  conventions, dataset-format and style notes and the renderer-contract note): references go to
  ``docs/<file>.md`` instead;
- a section reference ``<file>.md §N`` whose file is not under ``docs/``;
- ``docs/<file>`` paths that do not exist, and ``docs/<file>.md §N`` (also ``§N-M`` and
  ``§N, §M``) or ``docs/<file>.md, "Heading"`` references whose section is not a heading of that
  file (numbered sections are the ``## N. Title`` headings);
- inside a ``docs/`` page, a bare ``§N`` that is not one of the page's own sections.

The patterns below are written so that this file does not match them itself.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
SCANNED_SUFFIXES = (".py", ".ipynb", ".md", ".cfg", ".toml", ".txt")
SKIPPED_DIRS = {"__pycache__", "runs", "build", "dist", "node_modules"}

# Leaving the repository: the parent's shared notes, or an absolute path of the machine.
OUTSIDE = re.compile(r"\.\./+shared\b|/wor[k]/")
# Design notes that live outside the repository, by bare name.
BARE_NOTE = re.compile(r"\b(?:METHOD|CONVENTIONS|DATASET_FORMAT|STYLE)\.md\b|\brender_contrac[t]\.md\b")
# One section number or range: "§4", "§ 6-9", "§5–8".
_SEC = r"§\s*(\d+)(?:\s*[-–]\s*(\d+))?"
# A docs path, optionally followed by sections "§N", "§N-M", "§N, §M" or a quoted heading.
DOCS_REF = re.compile(
    r"(?<![\w.-])docs/([\w./-]+?\.[A-Za-z]+)\b"
    r"(?P<secs>\s*" + _SEC + r"(?:\s*,\s*" + _SEC + r")*)?"
    r"(?:,?\s*\"(?P<title>[^\"\n]+)\")?"
)
SECTION = re.compile(_SEC)
# Any "<file>.md §N": the file must be a docs/ page.
ANY_MD_SECTION = re.compile(r"([\w./-]*\w\.md)`?\s*§\s*\d")
HEADING = re.compile(r"^#{1,6}\s+(?:(\d+)\.\s+)?(.+?)\s*$", re.M)


def doc_sections(text):
    """(numbers, titles) of a markdown page: the N of every ``## N. Title`` heading, and every
    heading's title without its number."""
    numbers, titles = set(), set()
    for m in HEADING.finditer(text):
        if m.group(1) is not None and m.group(0).startswith("## "):
            numbers.add(int(m.group(1)))
        titles.add(m.group(2).strip())
    return numbers, titles


def docs_index(docs_dir=DOCS):
    """{relative path under docs/: (numbers, titles) or None for a non-markdown file}."""
    index = {}
    for path in sorted(docs_dir.rglob("*")):
        if path.is_file():
            rel = path.relative_to(docs_dir).as_posix()
            index[rel] = doc_sections(path.read_text(encoding="utf-8")) if path.suffix == ".md" else None
    return index


def _numbers(match_text):
    out = []
    for m in SECTION.finditer(match_text):
        lo = int(m.group(1))
        hi = int(m.group(2)) if m.group(2) else lo
        out.extend(range(lo, hi + 1) if hi >= lo else [lo, hi])
    return out


def find_dangling(text, index, own_doc=None):
    """Problems in ``text``: a list of (line number, message). ``index`` is ``docs_index()``;
    ``own_doc`` names the docs page the text is (its bare ``§N`` are checked against it)."""
    problems = []

    def line_of(pos):
        return text.count("\n", 0, pos) + 1

    for m in OUTSIDE.finditer(text):
        problems.append((line_of(m.start()), f"reference outside the repository: {m.group(0)!r}"))
    for m in BARE_NOTE.finditer(text):
        problems.append((line_of(m.start()), f"{m.group(0)} is not in the repository; point at docs/<file>.md §N"))
    for m in ANY_MD_SECTION.finditer(text):
        path = re.sub(r"^(?:\.\.?/)+", "", m.group(1))
        if not path.startswith("docs/"):
            problems.append((line_of(m.start()), f"section reference into {m.group(1)!r}, which is not a docs/ page"))
    spans = []
    for m in DOCS_REF.finditer(text):
        spans.append(m.span())
        name, where = m.group(1), line_of(m.start())
        if name not in index:
            problems.append((where, f"docs/{name} does not exist"))
            continue
        sections = index[name]
        if m.group("secs"):
            if sections is None:
                problems.append((where, f"docs/{name} has no sections"))
                continue
            for n in _numbers(m.group("secs")):
                if n not in sections[0]:
                    problems.append((where, f"docs/{name} has no section §{n} (it has {sorted(sections[0])})"))
        title = m.group("title")
        if title and sections is not None and title not in sections[1]:
            problems.append((where, f"docs/{name} has no heading {title!r}"))
    if own_doc is not None and index.get(own_doc) is not None:
        own = index[own_doc][0]
        for m in SECTION.finditer(text):
            if any(a <= m.start() < b for a, b in spans):
                continue  # a section of another page, checked above
            for n in _numbers(m.group(0)):
                if n not in own:
                    problems.append((line_of(m.start()), f"§{n} is not a section of docs/{own_doc}"))
    return problems


def _text_of(path):
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".ipynb":  # the cells' sources, without JSON escaping of quotes
        nb = json.loads(text)
        text = "\n".join("".join(c.get("source", [])) for c in nb.get("cells", []))
    return text


def repository_text_files(root=ROOT):
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if any(p.startswith(".") or p in SKIPPED_DIRS or p.endswith(".egg-info") for p in rel.parts[:-1]):
            continue
        if path.is_file() and path.suffix in SCANNED_SUFFIXES and not rel.name.startswith("."):
            yield path


def test_the_four_docs_exist_with_numbered_sections():
    index = docs_index()
    for name in ("method.md", "conventions.md", "dataset_format.md", "architecture.md"):
        assert name in index, f"docs/{name} is missing"
        assert index[name][0], f"docs/{name} has no '## N. Title' sections"
    assert set(range(1, 11)) <= index["method.md"][0]  # the method's sections 1-10


def test_no_reference_in_the_repository_dangles():
    index = docs_index()
    found = []
    for path in repository_text_files():
        rel = path.relative_to(ROOT).as_posix()
        own = rel[len("docs/"):] if rel.startswith("docs/") else None
        for line, msg in find_dangling(_text_of(path), index, own):
            where = f"{rel} (cell text line {line})" if path.suffix == ".ipynb" else f"{rel}:{line}"
            found.append(f"{where}: {msg}")
    assert not found, f"{len(found)} dangling reference(s):\n" + "\n".join(found)


# ------------------------------------------------------------------ the checker on synthetic text
# The synthetic references are assembled from pieces so that this file does not contain them.
_D, _S = "docs/", "§"
_INDEX = {"method.md": ({1, 2, 3}, {"Input", "Scene", "Rendering"}), "overview.png": None}


def _msgs(text, own=None):
    return [msg for _, msg in find_dangling(text, _INDEX, own)]


def test_checker_accepts_references_that_resolve():
    ok = (f"see `{_D}method.md {_S}2`, {_D}method.md {_S}1-3 and {_D}method.md {_S}1, {_S}3;\n"
          f'{_D}method.md, "Rendering"; ![x]({_D}overview.png)')
    assert _msgs(ok) == []
    assert _msgs(f"as in {_S}2 and {_S}1-3", own="method.md") == []


def test_checker_flags_dangling_references():
    cases = {
        "see .." + "/shared/notes": "outside the repository",
        "/wor" + "k/main/x.py": "outside the repository",
        "the " + "METHOD" + ".md equations": "not in the repository",
        "render_" + "contract.md": "not in the repository",
        "CONVENTIONS" + f".md {_S}2": "not a docs/ page",
        f"method.md {_S}2": "not a docs/ page",
        f"{_D}method.md {_S}4": "no section §4",
        f"{_D}method.md {_S}2-5": "no section §4",
        f"{_D}method.md {_S}1, {_S}9": "no section §9",
        f"{_D}missing.md {_S}1": "does not exist",
        f'{_D}method.md, "Losses"': "no heading 'Losses'",
        f"{_D}overview.png {_S}1": "has no sections",
    }
    for text, expected in cases.items():
        msgs = _msgs(text)
        assert any(expected in m for m in msgs), (text, msgs)
    assert any("§7 is not a section" in m for m in _msgs(f"see {_S}7", own="method.md"))
    # a section of another page inside a docs page is checked against that page, not this one
    assert _msgs(f"see {_D}method.md {_S}3", own="method.md") == []
