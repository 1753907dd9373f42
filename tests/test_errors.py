"""Error types live beside the layer that raises them; the old import places keep working."""

import ast
import importlib
from pathlib import Path

import pytest

import geofeat
import geofeat.errors as errors
from geofeat.errors import GeofeatError


@pytest.mark.parametrize("name", sorted(errors.MOVED))
def test_moved_errors_are_reexported(name):
    home = importlib.import_module(errors.MOVED[name])
    cls = getattr(home, name)
    assert cls.__module__ == errors.MOVED[name] and issubclass(cls, GeofeatError)
    assert getattr(errors, name) is cls
    namespace = {}
    exec(f"from geofeat.errors import {name}", namespace)
    assert namespace[name] is cls
    assert name in dir(errors)


def test_package_top_exports_and_core_errors():
    for name in (
        "CacheError",
        "DatasetError",
        "DescriptorError",
        "GeofeatError",
        "MeshError",
        "MissingDependencyError",
        "SpectralError",
    ):
        assert getattr(geofeat, name) is getattr(errors, name)
    from geofeat import DatasetError

    assert DatasetError is importlib.import_module("geofeat.datasets.errors").DatasetError
    with pytest.raises(AttributeError):
        errors.NoSuchError  # noqa: B018
    with pytest.raises(AttributeError):
        geofeat.NoSuchError  # noqa: B018


def test_the_core_errors_module_imports_no_layer():
    tree = ast.parse(Path(errors.__file__).read_text())
    imported = [n.module for n in tree.body if isinstance(n, ast.ImportFrom)]
    imported += [a.name for n in tree.body if isinstance(n, ast.Import) for a in n.names]
    assert not [m for m in imported if m and m.startswith("geofeat")]
