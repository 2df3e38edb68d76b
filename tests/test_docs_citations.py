"""The sources cite the project's own theory notes (docs/theory/), never files outside the
repository: no ``../shared`` path and none of the external reading notes, and every
``docs/...md`` page (and quoted section) a source file cites exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"

#: references to material that lives outside the repository
OUTSIDE = re.compile(r"\.\./shared|NOTES\.md|DERIVATIONS\.md")
#: the paper's reading notes must not be cited from the text files either (benchmark inputs
#: under ../shared/bench are data, not citations, and are allowed there)
PAPER_OUTSIDE = re.compile(r"\.\./shared/paper|NOTES\.md|DERIVATIONS\.md")
DOC_PATH = re.compile(r"docs/[\w/.-]+\.md")
#: a cited section: docs/x.md, "Heading" (the heading may be wrapped over lines)
DOC_SECTION = re.compile(r"(docs/[\w/.-]+\.md),\s+\"([^\"]+)\"")
HEADING = re.compile(r"^#+\s+(.*?)\s*$", re.MULTILINE)
MD_LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")


def _source_files() -> list[Path]:
    files = sorted(p for p in SRC.rglob("*") if p.is_file() and p.suffix in {".py", ".md", ".toml"})
    assert files, f"no source files found under {SRC}"
    return files


def _text_files() -> list[Path]:
    """README, docs/**.md and the tests other than this one."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
    files += sorted(p for p in (ROOT / "tests").glob("*.py") if p.name != Path(__file__).name)
    return [p for p in files if p.is_file()]


def _cited_docs() -> dict[str, list[str]]:
    cited: dict[str, list[str]] = {}
    for path in _source_files():
        for match in DOC_PATH.findall(path.read_text(encoding="utf-8")):
            cited.setdefault(match, []).append(str(path.relative_to(ROOT)))
    return cited


def test_sources_cite_nothing_outside_the_repository():
    offenders = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _source_files()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert not offenders, "cite docs/theory/ instead:\n" + "\n".join(offenders)


def test_readme_docs_and_tests_cite_no_external_paper_notes():
    offenders = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _text_files()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if PAPER_OUTSIDE.search(line)
    ]
    assert not offenders, "cite docs/theory/ instead:\n" + "\n".join(offenders)


def test_cited_doc_pages_exist():
    cited = _cited_docs()
    assert any(p.startswith("docs/theory/") for p in cited), "no docs/theory/ citation found"
    missing = {page: users for page, users in cited.items() if not (ROOT / page).is_file()}
    assert not missing, f"cited pages missing from the repository: {missing}"


def test_cited_sections_exist():
    checked = 0
    for path in _source_files():
        text = path.read_text(encoding="utf-8")
        for page, section in DOC_SECTION.findall(text):
            target = ROOT / page
            if not target.is_file():
                continue  # reported by test_cited_doc_pages_exist
            wanted = " ".join(section.split())
            headings = {" ".join(h.split()) for h in HEADING.findall(target.read_text("utf-8"))}
            assert wanted in headings, (
                f"{path.relative_to(ROOT)} cites section {wanted!r} of {page}, which has only "
                f"{sorted(headings)}"
            )
            checked += 1
    assert checked, "no section citations found (the pattern no longer matches the sources)"


@pytest.mark.parametrize(
    "page", sorted((ROOT / "docs" / "theory").glob("*.md")), ids=lambda p: p.name
)
def test_theory_page_links_resolve(page: Path):
    for link in MD_LINK.findall(page.read_text(encoding="utf-8")):
        if "://" in link:
            continue
        assert (page.parent / link).exists(), f"{page.name}: broken link {link}"


def test_theory_pages_exist():
    names = {p.name for p in (ROOT / "docs" / "theory").glob("*.md")}
    assert {"index.md", "conventions.md", "paper-typos.md", "exact-flows.md",
            "two-polar.md"} <= names
