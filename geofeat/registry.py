"""The one registry of names behind descriptors, datasets and heads: `Registry`.

A `Registry` maps names to `LazyEntry` records. One rule for every registry:

* names are case-insensitive, ``-`` equals ``_`` and surrounding spaces are ignored
  (``"FAUST-R "`` is ``"faust_r"``; see `canonical_name`);
* registering a name that is already there raises the registry's error unless
  ``overwrite=True`` is passed;
* an entry's ``"module:attr"`` target is imported on first use (`Registry.load`), after its
  optional dependencies are checked: a missing one raises `MissingDependencyError` naming the
  extra to install;
* an unknown name raises the registry's error, listing the valid names and suggesting close
  ones (`unknown_name_error`).

Used by `geofeat.descriptors.registry`, `geofeat.datasets.registry` and
`geofeat.adapters.heads`.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.util
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from geofeat.errors import GeofeatError, MissingDependencyError

__all__ = ["LazyEntry", "Registry", "canonical_name", "unknown_name_error"]


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
        Settings fixed by this name (e.g. ``partiality="cuts"`` of the dataset ``shrec16_cuts``).
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


def canonical_name(name: Any) -> str:
    """The registry form of ``name``: stripped, lower case, ``-`` replaced by ``_``."""
    return str(name).strip().lower().replace("-", "_")


class Registry:
    """Names to `LazyEntry` records, with one rule for case, duplicates and unknown names.

    Parameters
    ----------
    kind : str
        What the registry holds (``"descriptor"``, ``"dataset"``, ``"head"``), for messages.
    error : type
        The `GeofeatError` subclass raised for an unknown or duplicate name.

    Examples
    --------
    >>> from geofeat.errors import GeofeatError
    >>> things = Registry("thing", GeofeatError)
    >>> things.register(LazyEntry("Pretty-Print", "json:dumps", summary="JSON text")).name
    'pretty_print'
    >>> things.load("PRETTY_PRINT ")({"a": 1})
    '{"a": 1}'
    >>> things.names()
    ['pretty_print']
    """

    def __init__(self, kind: str, error: type[GeofeatError]) -> None:
        self.kind = kind
        self.error = error
        self._entries: dict[str, LazyEntry] = {}

    def register(self, entry: LazyEntry, overwrite: bool = False) -> LazyEntry:
        """Add ``entry`` under the canonical form of its name.

        Parameters
        ----------
        entry : LazyEntry
            The record; its name is stored in canonical form (`canonical_name`).
        overwrite : bool
            Replace an entry of the same name instead of raising.

        Returns
        -------
        LazyEntry
            The stored record (its name canonical).

        Raises
        ------
        GeofeatError
            Of the registry's error type: the name is taken and ``overwrite`` is false, or
            ``entry`` is not a `LazyEntry`.
        """
        if not isinstance(entry, LazyEntry):
            raise self.error(
                f"a {self.kind} is registered as a geofeat.registry.LazyEntry(name, 'module:attr', ...); "
                f"found {type(entry).__name__}."
            )
        key = canonical_name(entry.name)
        if not key:
            raise self.error(f"a {self.kind} name must not be empty; found {entry.name!r}.")
        if key in self._entries and not overwrite:
            raise self.error(f"a {self.kind} named {key!r} is already registered; pass overwrite=True to replace it.")
        stored = entry if entry.name == key else replace(entry, name=key)
        self._entries[key] = stored
        return stored

    def unregister(self, name: str) -> LazyEntry:
        """Remove ``name`` and return its entry (the registry's error for an unknown name)."""
        return self._entries.pop(self.entry(name).name)

    def entry(self, name: Any) -> LazyEntry:
        """The entry of ``name``, not imported yet.

        Raises
        ------
        GeofeatError
            Of the registry's error type, for an unknown name (valid names and close ones listed).
        """
        key = canonical_name(name)
        if key not in self._entries:
            raise unknown_name_error(name, self._entries, self.kind, self.error, probe=key)
        return self._entries[key]

    def load(self, name: Any) -> Any:
        """The target of ``name``, imported now (see `LazyEntry.load`).

        Raises
        ------
        GeofeatError
            Of the registry's error type, for an unknown name.
        MissingDependencyError
            An optional module of the entry is missing (the message names the extra).
        """
        return self.entry(name).load(self.kind)

    def names(self) -> list[str]:
        """The registered names (canonical), sorted."""
        return sorted(self._entries)

    def copy(self) -> Registry:
        """A new registry with the same kind, error and entries (e.g. to register temporary names in a test)."""
        other = Registry(self.kind, self.error)
        other._entries = dict(self._entries)
        return other

    def __contains__(self, name: object) -> bool:
        return canonical_name(name) in self._entries

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __len__(self) -> int:
        return len(self._entries)

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {len(self)} names)"
