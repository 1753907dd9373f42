"""Every import in `geofeat/` and `adapters/` points down the layer table of the architecture page.

The table (``docs/architecture.md``, columns ``layer | where | owns``) lists the layers from
the bottom up; its ``where`` column names folders (``geofeat/render/``), single files
(``geofeat/__init__.py``) or the files directly in a folder (``geofeat/*.py``). A module may
import its own layer and those below it. Imports inside functions count, and so do the
``"module:attr"`` strings of the lazy registries, which are imports deferred to first use.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"
#: Source folder of each installed package that does not live under its own name.
PACKAGE_FOLDERS = {"geofeat.adapters": "adapters"}
LAZY_TARGET = re.compile(r"^(geofeat(?:\.\w+)+):\w+$")


def layer_table(text: str) -> list[tuple[str, list[str]]]:
    """``[(layer, [where, ...]), ...]`` from the first ``| layer | where | owns |`` table, bottom layer first."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if re.match(r"\|\s*layer\s*\|\s*where\s*\|", line))
    rows = []
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        rows.append((cells[0], re.findall(r"`([^`]+)`", cells[1])))
    return rows


def layer_of(path: str, table: list[tuple[str, list[str]]]) -> int | None:
    """Index in ``table`` of the layer holding ``path`` (relative, ``/``-separated): the most specific match wins."""
    best, best_rank = None, -1
    for index, (_, places) in enumerate(table):
        for place in places:
            if place == path:
                rank = 10_000
            elif place.endswith("/*.py"):
                rank = len(place) if path.startswith(place[:-4]) and "/" not in path[len(place) - 4 :] else -1
            elif place.endswith("/"):
                rank = len(place) if path.startswith(place) else -1
            else:
                rank = -1
            if rank > best_rank:
                best, best_rank = index, rank
    return best


def module_file(module: str) -> str | None:
    """The source file of a geofeat module name (None for other packages or names that are no module)."""
    for package, folder in PACKAGE_FOLDERS.items():
        if module == package or module.startswith(package + "."):
            module = folder + module[len(package) :]
            break
    else:
        if module != "geofeat" and not module.startswith("geofeat."):
            return None
    base = module.replace(".", "/")
    for candidate in (f"{base}.py", f"{base}/__init__.py"):
        if (ROOT / candidate).is_file():
            return candidate
    return None


def package_of(path: str) -> str:
    """The dotted package a source file belongs to (``adapters/heads.py`` -> ``geofeat.adapters``)."""
    parts = path.split("/")[:-1]
    dotted = ".".join(parts)
    for package, folder in PACKAGE_FOLDERS.items():
        if dotted == folder or dotted.startswith(folder + "."):
            return package + dotted[len(folder) :]
    return dotted


def imported_files(path: str, source: str, runtime_only: bool = False) -> list[tuple[int, str]]:
    """``[(line, imported file), ...]`` for every geofeat module that ``source`` imports, however deferred.

    ``runtime_only``: leave out what never runs as an import, the lazy registry strings and
    the imports under ``if TYPE_CHECKING:``.
    """
    tree = ast.parse(source)
    type_only = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            type_only.update(id(sub) for stmt in node.body for sub in ast.walk(stmt))
    found = []
    for node in ast.walk(tree):
        if runtime_only and (id(node) in type_only or isinstance(node, ast.Constant)):
            continue
        modules: list[str] = []
        if isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                package = package_of(path).split(".")
                package = package[: len(package) - (node.level - 1)]
                base = ".".join([*package, base] if base else package)
            # ``from pkg import submodule`` imports the submodule, ``from module import name`` the module
            submodules = [f"{base}.{alias.name}" for alias in node.names if module_file(f"{base}.{alias.name}")]
            modules = submodules or [base]
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            match = LAZY_TARGET.match(node.value)
            modules = [match.group(1)] if match else []
        for module in modules:
            target = module_file(module)
            if target is not None:
                found.append((node.lineno, target))
    return found


def upward_imports(table: list[tuple[str, list[str]]], sources: dict[str, str]) -> list[str]:
    """Every import of ``sources`` (path -> text) that points to a higher layer, as readable lines."""
    problems = []
    for path, source in sources.items():
        own = layer_of(path, table)
        for line, target in imported_files(path, source):
            theirs = layer_of(target, table)
            if theirs is not None and own is not None and theirs > own:
                problems.append(f"{path}:{line} ({table[own][0]}) imports {target} ({table[theirs][0]})")
    return problems


def source_files() -> dict[str, str]:
    paths = [*(ROOT / "geofeat").rglob("*.py"), *(ROOT / "adapters").rglob("*.py")]
    return {p.relative_to(ROOT).as_posix(): p.read_text() for p in sorted(paths)}


def import_cycles(sources: dict[str, str]) -> list[list[str]]:
    """The cycles of the graph "module imports module" (runtime imports only, deferred ones included)."""
    graph: dict[str, set[str]] = {}
    for path, source in sources.items():
        graph[path] = {target for _, target in imported_files(path, source, runtime_only=True) if target != path}
    cycles, state = [], {}

    def visit(node: str, stack: list[str]) -> None:
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, set())):
            if state.get(nxt) == "open":
                cycles.append(stack[stack.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt, stack)
        stack.pop()
        state[node] = "done"

    for node in sorted(graph):
        if node not in state:
            visit(node, [])
    return cycles


@pytest.fixture(scope="module")
def table():
    return layer_table(ARCHITECTURE.read_text())


def test_every_module_has_a_layer(table):
    assert [path for path in source_files() if layer_of(path, table) is None] == []


def test_no_import_points_up_the_layers(table):
    assert upward_imports(table, source_files()) == []


def test_the_check_sees_planted_upward_imports(table):
    """A top-level, a deferred, a relative and a lazy-registry import of a higher layer are each reported."""
    planted = {
        "geofeat/mesh.py": "from geofeat.descriptors.compute import compute\n",
        "geofeat/geometry/partial.py": "def f():\n    from geofeat.adapters import heads\n",
        "adapters/matchers.py": "from ..apps import cli\n",
        "geofeat/render/cameras.py": "ENTRY = 'geofeat.train.trainer:GeoLoraTrainer'\n",
    }
    problems = upward_imports(table, planted)
    assert len(problems) == 4, problems
    assert "geofeat/geometry/partial.py:2 (geometry) imports adapters/heads.py (heads)" in problems
    # the same imports pointing down (or within a layer) are fine
    assert upward_imports(table, {"geofeat/apps/cli.py": "".join(planted.values())}) == []


def test_no_module_imports_itself_back_through_others():
    """No import circle, however deferred (``a`` imports ``b`` which imports ``a``, at import or at call time)."""
    sources = source_files()
    assert import_cycles({p: s for p, s in sources.items() if not p.endswith("__init__.py")}) == []
    planted = {
        "adapters/heads.py": "from .release import check_state\n",
        "adapters/release.py": "def f():\n    from .heads import Head\n",
    }
    assert import_cycles(planted) == [["adapters/heads.py", "adapters/release.py", "adapters/heads.py"]]
