"""The README stays short, true to the files it names, and in step with the generated tables it shows."""

from __future__ import annotations

import importlib.util
import re

from shapes import REPO

README = REPO / "README.md"


def _readme_includes():
    spec = importlib.util.spec_from_file_location("readme_includes", REPO / "scripts" / "readme_includes.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_fits_on_a_few_screens():
    size = len(README.read_bytes())
    assert size <= 11_000, f"README.md is {size} bytes; keep it near 10 KB and move detail into docs/"


def test_included_tables_are_the_generated_files():
    includes = _readme_includes()
    text = README.read_text(encoding="utf-8")
    paths = includes.included_paths(text)
    assert "benchmarks/results/main/results.md" in paths
    assert includes.refreshed(text) == text, "run: python scripts/readme_includes.py"


def test_a_stale_table_is_detected(tmp_path):
    includes = _readme_includes()
    (tmp_path / "t.md").write_text("| a |\n|---|\n| 1 |\n", encoding="utf-8")
    stale = "x\n<!-- include: t.md -->\n| a |\n|---|\n| 0 |\n<!-- end include -->\ny\n"
    assert includes.refreshed(stale, root=tmp_path) == "x\n<!-- include: t.md -->\n| a |\n|---|\n| 1 |\n<!-- end include -->\ny\n"


def test_local_links_and_pictures_exist():
    text = README.read_text(encoding="utf-8")
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if not re.match(r"[a-z]+://", t)]
    assert local, "the README links to no docs page"
    missing = [t for t in local if not (REPO / t).exists()]
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_the_test_command_is_the_one_ci_runs():
    text = README.read_text(encoding="utf-8")
    assert "```bash\npython -m pytest -q\n```" in text
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    assert ".venv/bin/python -m pytest -q\n" in ci


def test_no_development_history_in_the_readme():
    text = README.read_text(encoding="utf-8")
    assert not re.search(r"\bissue \d+", text, flags=re.I)
    assert not re.search(r"\bcommit [0-9a-f]{7,}\b", text)
