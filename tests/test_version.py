"""`__version__` lives in `geofeat._version`, and pyproject.toml reads it from there."""

import ast
import re
from pathlib import Path

import geofeat
from geofeat._version import __version__

ROOT = Path(__file__).resolve().parents[1]


def test_one_version():
    assert geofeat.__version__ == __version__ and re.fullmatch(r"\d+\.\d+\.\d+\S*", __version__)
    pyproject = (ROOT / "pyproject.toml").read_text()
    assert 'dynamic = ["version"]' in pyproject and 'attr = "geofeat._version.__version__"' in pyproject
    assert not re.search(r"^version\s*=\s*\"", pyproject, flags=re.MULTILINE)


def test_nothing_below_imports_the_package_top():
    """Modules of the package import submodules, never ``geofeat`` itself (its __init__ imports them)."""
    offenders = []
    for path in [*(ROOT / "geofeat").rglob("*.py"), *(ROOT / "adapters").rglob("*.py")]:
        if path.name == "__init__.py" and path.parent.name == "geofeat":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import) and any(alias.name == "geofeat" for alias in node.names):
                offenders.append(f"{path.relative_to(ROOT)}: import geofeat")
            if isinstance(node, ast.ImportFrom) and node.module == "geofeat" and node.level == 0:
                names = [a.name for a in node.names]
                if any(
                    not (ROOT / "geofeat" / n).with_suffix(".py").exists() and not (ROOT / "geofeat" / n).is_dir() for n in names
                ):
                    offenders.append(f"{path.relative_to(ROOT)}: from geofeat import {', '.join(names)}")
    assert offenders == []
