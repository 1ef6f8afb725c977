"""The user-facing documents (README.md and the site's pages) carry no development history:
no "stop N", no commit hashes, no "MISS" (history goes in CHANGELOG.md and commit messages).

The generated benchmark pages and the paper reproduction are records of a measurement: they
name the commit they measured and the targets a run missed, and are checked by their own
tests (tests/benchmarks/test_pages.py)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from benchmarks.common import REPO

GENERATED = {REPO / "docs" / "paper-reproduction.md"} | set(
    (REPO / "docs" / "benchmarks").glob("*.md")
) - {REPO / "docs" / "benchmarks" / "running.md"}
DOCUMENTS = sorted(
    {REPO / "README.md", *(REPO / "docs").rglob("*.md")} - GENERATED,
    key=lambda path: path.as_posix(),
)
HISTORY = {
    "a development stop": re.compile(r"\bstops? \d+", re.IGNORECASE),
    "a commit hash": re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}\b"),
    "MISS": re.compile(r"\bMISS\b"),
}


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda path: path.relative_to(REPO).as_posix())
def test_no_development_history(path: Path) -> None:
    found = [
        f"{path.relative_to(REPO)}:{number}: {what}: {match.group(0)!r}"
        for number, line in enumerate(path.read_text().splitlines(), 1)
        for what, pattern in HISTORY.items()
        for match in pattern.finditer(line)
    ]
    assert not found, "\n".join(found)


def test_the_readme_is_a_front_page() -> None:
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    # the test command CI runs (.ci/run -> scripts/test) is the one the README names
    assert "scripts/test             # the whole test suite" in text
    assert "CI (`.ci/run`) runs exactly it" in text


def test_the_changelog_page_includes_the_changelog() -> None:
    assert '--8<-- "CHANGELOG.md"' in (REPO / "docs" / "changelog.md").read_text()
    assert (REPO / "CHANGELOG.md").is_file()
