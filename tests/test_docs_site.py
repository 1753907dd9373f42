"""The built documentation site says what a user should read, and shows the examples the tests run.

The site is built once for this module with ``mkdocs build --strict`` into a temporary
folder; the checks read the text of every page as rendered, included tables and notes
included (the Markdown tests of ``test_docs.py`` see only ``docs/*.md``, not the files they
include).
"""

from __future__ import annotations

import html
import re
import subprocess
import sys
from html.parser import HTMLParser
from pathlib import Path

import pytest
from shapes import REPO
from test_docs import ISSUE, pages_with_runnable_blocks, runnable_blocks

#: A full git commit hash (40 hex digits, on its own).
COMMIT_HASH = re.compile(r"(?<![0-9A-Za-z])[0-9a-f]{40}(?![0-9A-Za-z])")
#: Phrases of an evidence log, not of a user guide: missing provenance, or how a result was come by.
LOG_PHRASES = re.compile(
    r"not recorded|could not be opened|not available to us|as quoted by a third-party|the code as it was before",
    flags=re.I,
)


class _ArticleText(HTMLParser):
    """The text of a page's ``<article>`` (its content, without navigation), and its code blocks."""

    def __init__(self) -> None:
        super().__init__()
        self.depth = 0
        self.skip = 0
        self.in_code = 0
        self.parts: list[str] = []
        self.code_blocks: list[str] = []
        self._code: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag == "article":
            self.depth += 1
        elif tag in ("script", "style"):
            self.skip += 1
        elif tag == "pre" and self.depth:
            self.in_code += 1
            self._code = []

    def handle_endtag(self, tag):
        if tag == "article":
            self.depth -= 1
        elif tag in ("script", "style"):
            self.skip -= 1
        elif tag == "pre" and self.in_code:
            self.in_code -= 1
            self.code_blocks.append("".join(self._code))

    def handle_data(self, data):
        if self.depth and not self.skip:
            self.parts.append(data)
            if self.in_code:
                self._code.append(data)


def _article(path: Path) -> _ArticleText:
    parser = _ArticleText()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site, built once for this module (strict: a warning fails the build)."""
    out = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, f"mkdocs build --strict failed:\n{result.stderr[-4000:]}"
    return out


def _pages(site: Path) -> list[Path]:
    return sorted(p for p in site.rglob("index.html") if p.relative_to(site).parts[0] not in ("assets", "search"))


def test_every_page_is_built(site):
    names = {str(p.parent.relative_to(site)) for p in _pages(site)}
    assert {".", "tutorial", "concepts", "heads", "validation", "troubleshooting", "changelog", "citing"} <= names, names


def test_no_commit_hash_issue_number_or_log_phrase_on_any_page(site):
    """What a user reads, tables and notes included: no commit hashes, no issue numbers, no 'not recorded'."""
    found = []
    for page in _pages(site):
        text = html.unescape(" ".join(_article(page).parts))
        for pattern in (COMMIT_HASH, ISSUE, LOG_PHRASES):
            for match in pattern.finditer(text):
                context = text[max(0, match.start() - 60) : match.end() + 60].replace("\n", " ")
                found.append(f"{page.parent.relative_to(site)}: {match.group(0)!r} in ...{context}...")
    assert not found, "\n".join(found)


def _normalised(code: str) -> str:
    return "\n".join(line.rstrip() for line in code.strip().splitlines())


@pytest.mark.parametrize("page", [p for p in pages_with_runnable_blocks() if p.parent.name == "docs"], ids=lambda p: p.name)
def test_the_runnable_examples_are_the_ones_shown(site, page):
    """Every runnable block of a page (the code the tests run) is shown as written on the built page."""
    built = site / ("" if page.stem == "index" else page.stem) / "index.html"
    shown = {_normalised(code) for code in _article(built).code_blocks}
    missing = [number for number, block in enumerate(runnable_blocks(page), start=1) if _normalised(block) not in shown]
    assert not missing, f"{page.name}: runnable block(s) {missing} are not shown as written on the built page"


@pytest.mark.parametrize(
    ("text", "flagged"),
    [
        ("commit a87e1184c1fb5b7ededda8957c497f37a5542f79 of the notes", True),
        ("machine not recorded in results.json", True),
        ("see issue 12", True),
        ("sha256 fff7941b5db873f53820cb0f1f1a931d62f3e50a2e9677a475982fe86f8465a8", False),
        ("tr_reg_080, 2026-11-23, 0.004 x the diagonal", False),
    ],
)
def test_the_site_patterns(text, flagged):
    """The patterns catch what they are for and spare ordinary text (a 64-digit checksum is not a commit)."""
    assert bool(COMMIT_HASH.search(text) or ISSUE.search(text) or LOG_PHRASES.search(text)) is flagged
