"""Every error type is a plain subclass of `GeofeatError`, defined in `geofeat/errors.py` and nowhere else."""

import ast
import inspect
from pathlib import Path

import pytest

import geofeat
import geofeat.errors as errors
from geofeat.errors import GeofeatError

ROOT = Path(geofeat.__file__).parents[1]
ERROR_TYPES = [cls for _, cls in inspect.getmembers(errors, inspect.isclass) if cls.__module__ == errors.__name__]


def test_every_error_type_is_exported_and_derives_from_the_base():
    assert sorted(errors.__all__) == sorted(cls.__name__ for cls in ERROR_TYPES)
    for cls in ERROR_TYPES:
        assert issubclass(cls, GeofeatError)
        assert getattr(geofeat, cls.__name__) is cls, f"geofeat.{cls.__name__} is not exported"


@pytest.mark.parametrize("cls", [c for c in ERROR_TYPES if c is not GeofeatError], ids=lambda c: c.__name__)
def test_error_types_are_caught_as_a_builtin_type_too(cls):
    assert any(issubclass(cls, builtin) for builtin in (ValueError, RuntimeError, OSError, ImportError, MemoryError))


def test_the_errors_module_imports_nothing_of_geofeat():
    tree = ast.parse(Path(errors.__file__).read_text())
    imported = [n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    imported += [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    assert [m for m in imported if m != "__future__"] == []


def test_no_exception_class_is_defined_outside_the_errors_module():
    """Only a private signal that never leaves its module (``_OutOfBudget`` of the eigensolver) may live elsewhere."""
    geofeat_types = {cls.__name__ for cls in ERROR_TYPES}
    offenders = []
    for path in [*(ROOT / "geofeat").rglob("*.py"), *(ROOT / "adapters").rglob("*.py")]:
        if path == Path(errors.__file__):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                bases = {b.id if isinstance(b, ast.Name) else getattr(b, "attr", "") for b in node.bases}
                private_signal = node.name.startswith("_") and bases == {"Exception"}
                if (bases & geofeat_types or any(b.endswith(("Error", "Exception")) for b in bases)) and not private_signal:
                    offenders.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert offenders == []


def test_unknown_names_are_attribute_errors():
    with pytest.raises(AttributeError):
        errors.NoSuchError  # noqa: B018
    with pytest.raises(AttributeError):
        geofeat.NoSuchError  # noqa: B018
