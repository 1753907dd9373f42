"""The Tutorial page's output and pictures, written by running the page's own runnable blocks.

    python -m benchmarks.tables.tutorial

Runs the ``<!-- runnable -->`` Python blocks of ``docs/tutorial.md`` in order, in one
namespace, in a temporary folder with a temporary feature cache (about half a minute on two
cores), and writes into ``benchmarks/results/tutorial/``:

- ``output.md``: what the blocks printed, as the page shows it, with the machine and the date;
- ``pck.png`` and ``pairs.png``: the two pictures the blocks write.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import io
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

from benchmarks.common import REPO, RESULTS, machine

PAGE = REPO / "docs" / "tutorial.md"
#: A runnable block: the marker line right above a python fence (the rule of tests/test_docs.py).
RUNNABLE = re.compile(r"^<!-- runnable -->[ \t]*\n```python[ \t]*\n(.*?)^```[ \t]*$", flags=re.S | re.M)
PICTURES = ("pck.png", "pairs.png")


def runnable_blocks(page: Path = PAGE) -> list[str]:
    """The runnable Python blocks of ``page``, in order."""
    return RUNNABLE.findall(page.read_text(encoding="utf-8"))


def run_blocks(blocks: list[str], work: Path) -> str:
    """Run ``blocks`` in one namespace inside ``work``; returns what they printed."""
    printed = io.StringIO()
    namespace: dict = {"__name__": "__tutorial__"}
    previous = Path.cwd()
    os.chdir(work)
    try:
        with contextlib.redirect_stdout(printed):
            for number, block in enumerate(blocks, start=1):
                exec(compile(block, f"{PAGE.name} (runnable block {number})", "exec"), namespace)
    finally:
        os.chdir(previous)
    return printed.getvalue()


def output_markdown(printed: str, when: str, where: str) -> str:
    """The page's "what you should see" block: the matching lines of the output, then the run's date and machine."""
    lines = [line for line in printed.splitlines() if "error x100" in line]
    return "```text\n" + "\n".join(lines) + "\n```\n\n" + f"`python -m benchmarks.tables.tutorial`; {when}, {where}.\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=RESULTS / "tutorial", help="folder of output.md and the pictures")
    args = parser.parse_args(argv)
    blocks = runnable_blocks()
    if not blocks:
        raise SystemExit(f"{PAGE}: no runnable blocks")
    with tempfile.TemporaryDirectory(prefix="geofeat-tutorial-") as tmp:
        work = Path(tmp) / "work"
        work.mkdir()
        os.environ["GEOFEAT_CACHE_DIR"] = str(Path(tmp) / "cache")
        printed = run_blocks(blocks, work)
        args.out.mkdir(parents=True, exist_ok=True)
        for name in PICTURES:
            shutil.copyfile(work / name, args.out / name)
    text = output_markdown(printed, datetime.date.today().isoformat(), machine())
    (args.out / "output.md").write_text(text, encoding="utf-8")
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
