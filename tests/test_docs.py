"""The repository as a reader meets it: the documents' links lead somewhere, and the tree checks out alike on a
case-insensitive file system (macOS and Windows by default)."""

from __future__ import annotations

import functools
import os
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Markdown links and images: [text](target) and ![alt](target); the target ends at a space or the closing parenthesis.
LINK = re.compile(r"\]\(([^)\s]+)\)")
DOCUMENTS = ["README.md", "docs", "results"]
# The folders the project writes or installs into, which git ignores: they are not the reader's tree.
GENERATED = {".git", ".venv", "runs", "demo_out", "__pycache__", ".mypy_cache", ".ruff_cache", ".pytest_cache"}


def _markdown_files() -> list[Path]:
    files = []
    for name in DOCUMENTS:
        path = ROOT / name
        files.extend([path] if path.is_file() else sorted(path.rglob("*.md")))
    return files


def test_the_documents_links_lead_to_files_of_the_repository():
    """A relative link of the README, ``docs/`` or a committed report names a file or folder that exists, relative to
    the document (a link written relative to the repository root from inside ``docs/`` is broken on GitHub)."""
    files = _markdown_files()
    assert len(files) > 5, files  # the README and the docs are found, so the test reads something
    broken = []
    for doc in files:
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if target.startswith(("http://", "https://", "mailto:", "#")):
                continue
            if not (doc.parent / target.split("#")[0]).exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not broken, broken


def test_no_two_paths_of_a_folder_differ_only_in_case():
    """Two names of one folder that differ only in case (``results/Almighty`` and ``results/almighty``) become one on
    a case-insensitive file system, where a clone mixes their files."""
    clashes = []
    for folder, dirs, files in os.walk(ROOT):
        dirs[:] = [d for d in dirs if d not in GENERATED and not d.endswith(".egg-info")]
        seen: dict[str, str] = {}
        for name in dirs + files:
            other = seen.setdefault(name.lower(), name)
            if other != name:
                clashes.append(f"{Path(folder).relative_to(ROOT) / other} ~ {name}")
    assert not clashes, clashes


@functools.cache
def _anchors(doc: Path) -> frozenset[str]:
    """The anchors GitHub gives ``doc``'s headings: lower case, every character but letters, digits, spaces, hyphens
    and underscores dropped, spaces as hyphens, and a repeated anchor numbered (-1, -2, …). Fenced code is skipped.
    Read once per document: most section links point into docs/learning.md."""
    anchors: set[str] = set()
    fenced = False
    for line in doc.read_text(encoding="utf-8").splitlines():
        fenced ^= line.startswith("```")
        heading = re.match(r"#{1,6} (.*)", line)
        if fenced or not heading:
            continue
        slug = "".join(c for c in heading.group(1).strip().lower() if c.isalnum() or c in " -_").replace(" ", "-")
        anchor, n = slug, 0
        while anchor in anchors:
            n += 1
            anchor = f"{slug}-{n}"
        anchors.add(anchor)
    return frozenset(anchors)


def test_the_documents_section_links_name_headings_that_exist():
    """A link to a section (``#anchor``, or ``file.md#anchor``) names a heading of that document: a heading retitled
    without its links leaves them at the top of the page."""
    checked, broken = 0, []
    for doc in _markdown_files():
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            path, _, anchor = target.partition("#")
            if not anchor or target.startswith(("http://", "https://")):
                continue
            page = doc if not path else doc.parent / path
            if page.suffix != ".md" or not page.is_file():
                continue
            checked += 1
            if anchor not in _anchors(page):
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert checked > 10, checked  # the README's and the docs' section links are found, so the test reads something
    assert not broken, broken
