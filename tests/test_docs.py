"""The documentation's links resolve, and its headings carry no history.

Every relative link and image in ``README.md`` and ``docs/`` must name a file of the
repository, and an ``#anchor`` into a Markdown page must name one of its headings (GitHub's
slugs) or an explicit ``<a id="...">``. Headings say what a section is, never when it was
written: no dates, no "session", no issue numbers.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = sorted([REPO / "README.md", *(REPO / "docs").rglob("*.md")])
# Pages that another line of work adds to docs/ and that the index already links to: a link to
# one of them is checked like any other as soon as the page exists.
ADDED_ELSEWHERE: set[str] = set()

_FENCE = re.compile(r"^```.*?^```[ \t]*$", re.DOTALL | re.MULTILINE)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$", re.MULTILINE)
_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"")
_DATE = re.compile(r"\b\d{4}-\d{2}-\d{2}\b")
_HISTORY = re.compile(r"\bsession\b|\bissue\b", re.IGNORECASE)


def _prose(text: str) -> str:
    """The text without fenced blocks and code spans (their brackets are not links)."""
    return _CODE_SPAN.sub("", _FENCE.sub("", text))


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"<[^>]+>", "", heading).lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """Every anchor a link may name in ``page``: heading slugs (numbered when repeated) and
    explicit ``<a id>`` tags."""
    text = _FENCE.sub("", page.read_text(encoding="utf-8"))
    found: set[str] = set(_ANCHOR.findall(text))
    seen: dict[str, int] = {}
    for match in _HEADING.finditer(text):
        slug = _slug(match.group(2))
        count = seen.get(slug, 0)
        seen[slug] = count + 1
        found.add(slug if count == 0 else f"{slug}-{count}")
    return found


def broken_links(page: Path) -> list[str]:
    """The relative links of ``page`` whose file or anchor does not exist."""
    broken = []
    for target in _LINK.findall(_prose(page.read_text(encoding="utf-8"))):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("/"):
            continue  # a URL (http:, mailto:) or a path on the running server
        path_part, _, anchor = target.partition("#")
        resolved = (page.parent / path_part).resolve() if path_part else page
        relative = resolved.relative_to(REPO).as_posix() if resolved.is_relative_to(REPO) else ""
        if not resolved.exists():
            if relative not in ADDED_ELSEWHERE:
                broken.append(target)
            continue
        if anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(target)
    return broken


def test_the_checker_finds_a_missing_file_and_a_missing_anchor(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# Other\n\n## Real rooms (`bench/x.py`)\n")
    page.write_text(
        "# Page\n\n[ok](other.md#real-rooms-benchxpy) [gone](missing.md) "
        "[no anchor](other.md#nowhere) [self](#page) ![img](other.md) "
        "`[code](missing.md)` [web](https://example.org/x.md)\n"
        "```\n[fenced](missing-too.md)\n```\n"
    )
    assert broken_links(page) == ["missing.md", "other.md#nowhere"]


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(REPO).as_posix())
def test_every_relative_link_resolves(page: Path) -> None:
    assert broken_links(page) == []


@pytest.mark.parametrize("page", PAGES, ids=lambda page: page.relative_to(REPO).as_posix())
def test_headings_carry_no_history(page: Path) -> None:
    text = _FENCE.sub("", page.read_text(encoding="utf-8"))
    for match in _HEADING.finditer(text):
        heading = match.group(2)
        assert not _DATE.search(heading) and not _HISTORY.search(heading), heading


def test_the_index_links_every_page() -> None:
    """A page no map leads to is not found: docs/index.md links every page under docs/."""
    index = REPO / "docs" / "index.md"
    linked = {
        (index.parent / target.partition("#")[0]).resolve()
        for target in _LINK.findall(_prose(index.read_text(encoding="utf-8")))
        if not re.match(r"^[a-z][a-z0-9+.-]*:", target)
    }
    pages = {page.resolve() for page in (REPO / "docs").rglob("*.md")} - {index.resolve()}
    assert sorted(p.relative_to(REPO).as_posix() for p in pages - linked) == []
