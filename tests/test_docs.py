"""The documentation stays true: its runnable examples run, its includes and pictures exist, it cites no commits or issues.

A Python block of ``docs/*.md`` (or README.md) is runnable when the line right above its
fence is ``<!-- runnable -->``: it must run on a fresh clone with nothing downloaded. A block
that needs FAUST_r is marked ``<!-- runnable: needs FAUST_r -->`` instead, and the text just
above the marker must link to where FAUST_r comes from. The blocks of one page run in order,
in one namespace, in a temporary working folder, with a temporary ``GEOFEAT_CACHE_DIR`` (the
``isolated_cache`` fixture). A plain block runs with no data at all (no ``FAUST_r/``, no
``GEOFEAT_DATA``); a block that needs FAUST_r runs with ``FAUST_r/`` linked into the folder
and ``GEOFEAT_DATA`` set.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from shapes import DATA_ENV, REPO

import geofeat

DOCS = REPO / "docs"
RUNNABLE = re.compile(r"^<!-- runnable(?:: needs (FAUST_r))? -->[ \t]*\n```python[ \t]*\n(.*?)^```[ \t]*$", flags=re.S | re.M)
MARKER = "<!-- runnable -->"
MARKER_LINE = re.compile(r"^<!-- runnable(?:: needs FAUST_r)? -->[ \t]*$", flags=re.M)
#: What the text above a ``needs FAUST_r`` marker must hold: a link to where the data comes from.
DATA_SOURCE_LINK = re.compile(r"\]\((?:datasets\.md)?#registered-datasets\)|\]\(https://github\.com/llorz/")
#: ``--8<-- "path"`` (or ``"path:FROM:TO"``) lines of pymdownx.snippets (paths relative to the repository root).
INCLUDE = re.compile(r'^\s*--8<--\s+"([^":]+)(?::[-0-9:,]*)?"\s*$', flags=re.M)  # a line range may follow
#: Markdown images ``![alt](path)`` and HTML ``<img src="path">``.
IMAGE = re.compile(r'!\[[^\]]*\]\(([^)\s]+)(?:\s+"[^"]*")?\)|<img\s[^>]*src="([^"]+)"')
#: Seven or more hex digits with at least one letter and one digit: what a commit hash looks like.
HEXLIKE = re.compile(r"(?<![0-9A-Za-z_./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![0-9A-Za-z_-])")
ISSUE = re.compile(r"\bissues?\s*#?\s*\d+|(?<![\w&])#\d+\b", flags=re.I)


def doc_pages() -> list[Path]:
    """Every Markdown page of the site (the ``results`` link to benchmark output excluded)."""
    return sorted(p for p in DOCS.rglob("*.md") if "results" not in p.relative_to(DOCS).parts)


def pages_with_runnable_blocks() -> list[Path]:
    pages = [*doc_pages(), REPO / "README.md"]
    return [p for p in pages if p.is_file() and MARKER_LINE.search(p.read_text(encoding="utf-8"))]


def runnable_blocks_and_needs(page: Path) -> list[tuple[str, str]]:
    """``(needs, code)`` of the runnable Python blocks of ``page``, in order (``needs``: "" or "FAUST_r").

    Every marker must sit right above a python fence.
    """
    text = page.read_text(encoding="utf-8")
    blocks = RUNNABLE.findall(text)
    markers = len(MARKER_LINE.findall(text))
    assert len(blocks) == markers, (
        f"{page.relative_to(REPO)}: {markers} '{MARKER}' marker line(s) but {len(blocks)} python block(s) "
        "right below one; put the marker on the line just above the ```python fence"
    )
    return blocks


def runnable_blocks(page: Path) -> list[str]:
    """The runnable Python blocks of ``page``, in order."""
    return [code for _, code in runnable_blocks_and_needs(page)]


def test_docs_have_runnable_blocks():
    names = {p.name for p in pages_with_runnable_blocks()}
    assert {"index.md", "descriptors.md", "cache.md", "extract.md"} <= names, names


@pytest.mark.parametrize("page", pages_with_runnable_blocks(), ids=lambda p: str(p.relative_to(REPO)))
def test_runnable_blocks_run(page, faust_dir, tmp_path, monkeypatch, isolated_cache):
    """The page's runnable blocks run as written, in order, in one namespace; plain ones with no data at all."""
    work = tmp_path / "work"
    work.mkdir()
    linked = work / "FAUST_r"
    monkeypatch.chdir(work)
    namespace: dict = {"__name__": "__docs__"}
    for number, (needs, block) in enumerate(runnable_blocks_and_needs(page), start=1):
        if needs:  # the data the page says to fetch, where the page says to put it
            if not linked.is_symlink():
                linked.symlink_to(faust_dir, target_is_directory=True)
            monkeypatch.setenv(DATA_ENV, str(faust_dir.parent))
        else:  # a fresh clone: nothing downloaded
            if linked.is_symlink():
                linked.unlink()
            monkeypatch.delenv(DATA_ENV, raising=False)
        code = compile(block, f"{page.relative_to(REPO)} (runnable block {number})", "exec")
        exec(code, namespace)
    assert geofeat.cache_dir() == isolated_cache  # nothing was written to the user's cache


def test_blocks_that_need_data_say_where_to_get_it():
    """A ``needs FAUST_r`` marker follows, within the 6 lines above it, a link to where FAUST_r comes from."""
    missing = []
    for page in pages_with_runnable_blocks():
        lines = page.read_text(encoding="utf-8").splitlines()
        for number, line in enumerate(lines):
            if line.strip() == "<!-- runnable: needs FAUST_r -->":
                above = "\n".join(lines[max(0, number - 6) : number])
                if not DATA_SOURCE_LINK.search(above):
                    missing.append(f"{page.relative_to(REPO)}:{number + 1}")
    assert not missing, "blocks that need FAUST_r without a link to its source just above: " + ", ".join(missing)


def test_includes_and_pictures_exist():
    """Every ``--8<--`` include (from the repository root) and every picture (from its page) names a file."""
    missing = []
    for page in doc_pages():
        text = page.read_text(encoding="utf-8")
        for include in INCLUDE.findall(text):
            if not (REPO / include).is_file():
                missing.append(f"{page.relative_to(REPO)}: include {include}")
        for markdown, html in IMAGE.findall(text):
            target = markdown or html
            if re.match(r"[a-z]+://", target):
                missing.append(f"{page.relative_to(REPO)}: picture {target} is remote; commit it under benchmarks/results")
            elif not (page.parent / target).is_file():
                missing.append(f"{page.relative_to(REPO)}: picture {target}")
    assert not missing, "\n".join(missing)


def test_results_link_points_at_the_benchmark_results():
    link = DOCS / "results"
    assert link.is_symlink() and link.resolve() == (REPO / "benchmarks" / "results").resolve()


def test_no_commit_hashes_or_issue_numbers():
    """User pages speak to users: no commit hashes, no "issue N" (those belong in commit messages and NOTES.md)."""
    found = []
    for page in doc_pages():
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), start=1):
            for match in [*HEXLIKE.finditer(line), *ISSUE.finditer(line)]:
                found.append(f"{page.relative_to(REPO)}:{number}: {match.group(0)!r} in {line.strip()!r}")
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    ("text", "flagged"),
    [
        ("fixed in commit 562a458", True),
        ("see d0fc6d0 for the change", True),
        ("the goal of issue 13", True),
        ("as in #24", True),
        ("sha256 of the weights, a 64-digit key", False),
        ('--8<-- "benchmarks/results/speed_dino.md"', False),
        ("step_0050000 and tr_reg_080", False),
        ("float16 at 1e-4, 0.004 x the diagonal", False),
        ("colour #ffffff", False),
    ],
)
def test_the_hash_and_issue_patterns(text, flagged):
    """The patterns above catch what they are for and spare ordinary text."""
    assert bool(HEXLIKE.search(text) or ISSUE.search(text)) is flagged
