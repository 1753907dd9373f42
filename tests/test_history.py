"""The code says what it does: no issue numbers, checklist labels or stories of how it came to be.

The ``.py`` files of ``geofeat/``, ``adapters/``, ``tests/``, ``scripts/`` and ``benchmarks/``
(``benchmarks/results/`` left out) are scanned line by line. How code came to be belongs in
commit messages; a measurement belongs in ``benchmarks/results/`` or ``docs/``.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from shapes import REPO
from test_docs import ISSUE

#: Folders whose ``.py`` files are scanned.
SCANNED = ("geofeat", "adapters", "tests", "scripts", "benchmarks")
#: Files that hold examples of what the patterns catch, on purpose.
EXAMPLES = {Path("tests/test_docs.py"), Path("tests/test_docs_site.py"), Path("tests/test_history.py")}
#: A checklist item as a whole string or as the prefix of an id (``"R7"``, ``"D3-load"``); norm names are spared.
LABEL = re.compile(r"""(?<![\w"'])["'](?!(?:L[0-9]|F1)["'])[A-Z]\d{1,2}(?:-[a-z][\w-]*)?["']""")
#: A list named after a review pass (``SECOND_PASS``), or the word checklist.
CHECKLIST = re.compile(r"\b[A-Z]+_PASS\b|(?i:(?<![a-z])check-?lists?(?![a-z]))")
#: Phrases that tell the history of a change rather than what the code does.
STORY = re.compile(r"\b(?:before|after) (?:this|the) (?:change|fix)\b|\b(?:earlier|previous|this) session\b", flags=re.I)
PATTERNS = {"issue number": ISSUE, "checklist label": LABEL, "checklist": CHECKLIST, "story": STORY}


def scanned_files() -> list[Path]:
    """The scanned ``.py`` files, relative to the repository root."""
    files = []
    for top in SCANNED:
        for path in (REPO / top).rglob("*.py"):
            relative = path.relative_to(REPO)
            if relative.parts[:2] != ("benchmarks", "results") and relative not in EXAMPLES:
                files.append(relative)
    return sorted(files)


def findings(text: str) -> list[str]:
    """``"line: kind: match"`` for every line of ``text`` that a pattern catches."""
    found = []
    for number, line in enumerate(text.splitlines(), start=1):
        for kind, pattern in PATTERNS.items():
            found += [f"{number}: {kind}: {m.group(0)!r} in {line.strip()!r}" for m in pattern.finditer(line)]
    return found


def test_the_scan_covers_the_code():
    files = scanned_files()
    assert Path("geofeat/mesh.py") in files and Path("adapters/heads.py") in files and Path("tests/test_robustness.py") in files
    assert not any(f.parts[:2] == ("benchmarks", "results") for f in files)


def test_no_issue_numbers_checklists_or_stories_in_the_code():
    found = [f"{path}:{line}" for path in scanned_files() for line in findings((REPO / path).read_text(encoding="utf-8"))]
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    ("text", "flagged"),
    [
        ("# see issue 13 for the reasons", True),
        ('"""As asked in #24."""', True),
        ('Row("R7", load_saved_head("nan"))', True),
        ('Row("D3-load-during-60-saves-never-torn", torn_loads)', True),
        ("SECOND_PASS += [", True),
        ("def test_every_checklist_item_has_rows():", True),
        ("# before this change the loop hung", True),
        ("found in an earlier session", True),
        ('norm="L2"', False),
        ("pair_id = 13  # the 13th pair", False),
        ('colour = "#ffffff"', False),
        ("DAMAGED_FILES = [", False),
        ("the first pass of each shape compiles", False),
        ("functional maps fitted by ridge regression", False),
        ('row = ("R", 7)', False),
    ],
)
def test_the_patterns(text, flagged):
    """A planted line is caught; ordinary code is spared."""
    assert bool(findings(text)) is flagged
