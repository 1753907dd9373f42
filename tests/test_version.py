"""`__version__` lives in `geofeat._version`, and pyproject.toml reads it from there."""

import ast
import importlib.metadata
from pathlib import Path

from packaging.version import Version  # a dependency of pytest

import geofeat
from geofeat._version import __version__

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: pytest depends on tomli there
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


def test_one_version():
    """The installed distribution, the package and pyproject.toml (dynamic) all give the one `_version.__version__`."""
    assert geofeat.__version__ == __version__
    assert importlib.metadata.version("geofeat") == __version__  # reinstall (scripts/install.sh) after changing it
    version = Version(__version__)  # raises InvalidVersion for a string that is not PEP 440
    assert str(version) == __version__ and len(version.release) == 3  # normalised, MAJOR.MINOR.PATCH

    with open(ROOT / "pyproject.toml", "rb") as handle:
        pyproject = tomllib.load(handle)
    assert "version" not in pyproject["project"] and pyproject["project"]["dynamic"] == ["version"]
    assert pyproject["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "geofeat._version.__version__"}


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
