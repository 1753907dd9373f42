"""The one lazy-registry mechanism behind descriptor, dataset and head names.

A registry is a plain ``dict`` from a name to a `LazyEntry` (a bare ``"module:attr"``
string is accepted as an entry without dependencies). The entry imports its target on
first use, checks its optional dependencies first and, when one is missing, raises
`MissingDependencyError` naming the extra to install. An unknown name raises the
registry's own error type, listing the valid names and suggesting close ones.

Used by `geofeat.descriptors.registry`, `geofeat.datasets.registry` and
`geofeat.adapters.heads` (`head_class`).
"""

from __future__ import annotations

import difflib
import importlib
import importlib.util
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from geofeat.errors import GeofeatError, MissingDependencyError

__all__ = ["LazyEntry", "as_entry", "lookup", "unknown_name_error"]


@dataclass(frozen=True)
class LazyEntry:
    """One registered name.

    Attributes
    ----------
    name : str
        Registry name.
    target : str or object
        ``"module:attr"``, imported on first use (`load`), or the object itself.
    requires : tuple of str
        Modules that must be importable before the target is imported.
    extra : str or None
        The ``pip install 'geofeat[extra]'`` that provides them.
    summary : str
        One line for listings.
    options : dict
        Settings fixed by this name (e.g. the dataset preset ``partiality="cuts"``).
    """

    name: str
    target: Any
    requires: tuple[str, ...] = field(default_factory=tuple)
    extra: str | None = None
    summary: str = ""
    options: Mapping[str, Any] = field(default_factory=dict)

    def missing(self) -> list[str]:
        """The modules of `requires` that cannot be imported here."""
        return [module for module in self.requires if importlib.util.find_spec(module) is None]

    def install_hint(self, missing: Iterable[str] | None = None) -> str:
        """``pip install 'geofeat[extra]'`` (or the bare missing modules when there is no extra)."""
        missing = self.missing() if missing is None else list(missing)
        return f"pip install 'geofeat[{self.extra}]'" if self.extra else f"pip install {' '.join(missing)}"

    def load(self, kind: str = "entry") -> Any:
        """The target, imported now.

        Parameters
        ----------
        kind : str
            What the registry holds (``"descriptor"``, ``"dataset"``, ``"head"``), for messages.

        Raises
        ------
        MissingDependencyError
            A module of `requires` is missing (the message names the extra to install).
        """
        missing = self.missing()
        if missing:
            raise MissingDependencyError(
                f"{kind} {self.name!r} needs {', '.join(missing)}, which is not installed: {self.install_hint(missing)}"
            )
        if not isinstance(self.target, str):
            return self.target
        module_name, _, attr = self.target.partition(":")
        return getattr(importlib.import_module(module_name), attr)


def as_entry(name: str, value: LazyEntry | str | Any) -> LazyEntry:
    """``value`` as a `LazyEntry` (a ``"module:attr"`` string or an object gets a plain entry)."""
    return value if isinstance(value, LazyEntry) else LazyEntry(name, value)


def unknown_name_error(
    name: Any, names: Iterable[str], kind: str, error: type[GeofeatError], probe: str | None = None
) -> GeofeatError:
    """``error`` for an unknown ``name``: the valid names and up to three close ones (to ``probe``, default ``name``).

    Returns
    -------
    GeofeatError
        Of type ``error``, message ``"unknown <kind> 'x'; valid names: a, b. Did you mean 'a'?"``.
    """
    names = sorted(names)
    close = difflib.get_close_matches(str(name) if probe is None else probe, names, n=3)
    hint = f" Did you mean {', '.join(map(repr, close))}?" if close else ""
    return error(f"unknown {kind} {name!r}; valid names: {', '.join(names)}.{hint}")


def lookup(
    registry: Mapping[str, LazyEntry | str | Any],
    name: Any,
    kind: str,
    error: type[GeofeatError],
    canonical: Callable[[Any], str] | None = None,
) -> LazyEntry:
    """The entry of ``name`` in ``registry`` (not imported yet).

    Parameters
    ----------
    registry : Mapping
        Name to `LazyEntry` (or ``"module:attr"``).
    name : Any
        The name asked for; ``canonical(name)`` is looked up when given.
    kind : str
        For messages.
    error : type
        Raised for an unknown name (see `unknown_name_error`).
    canonical : callable, optional
        Normalises names (e.g. case and ``-`` / ``_``).

    Returns
    -------
    LazyEntry
    """
    key = canonical(name) if canonical is not None else name
    if not isinstance(key, str) or key not in registry:
        raise unknown_name_error(name, registry, kind, error, probe=str(key))
    return as_entry(key, registry[key])
