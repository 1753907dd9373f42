"""Type and range checks of parameters at the API boundary, shared by descriptors and heads.

Values are checked by type, never by truthiness: ``"false"`` is not a boolean, ``True`` is
not an integer and ``2.0`` is not an integer either. NumPy scalars (``np.int64(8)``,
``np.float32(0.5)``, ``np.bool_(True)``, ``np.str_("robust")``) are accepted and returned
as the equal Python value, so that what is stored can enter a JSON cache key.

Every ``check_*`` function returns the canonical value and raises ``error`` (a subclass of
`geofeat.errors.GeofeatError`, `DescriptorError` by default) with the owner, the
parameter, what was expected and what was found.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from geofeat.errors import DescriptorError, GeofeatError

__all__ = [
    "canonical",
    "check_boolean",
    "check_choice",
    "check_integer",
    "check_number",
    "is_boolean",
    "is_finite_number",
    "is_integer",
    "parse_key_values",
]


def is_integer(value: Any) -> bool:
    """An int or NumPy integer, not a bool."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def is_finite_number(value: Any) -> bool:
    """A finite int, float or NumPy integer or float, not a bool."""
    real = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    return real and math.isfinite(value)


def is_boolean(value: Any) -> bool:
    """A bool or NumPy bool (not 0/1, not a string such as ``"false"``)."""
    return isinstance(value, (bool, np.bool_))


def canonical(value: Any) -> Any:
    """The plain-Python equal of a parameter value, for JSON keys and files.

    Parameters
    ----------
    value : Any
        NumPy scalars become ``int``/``float``/``bool``/``str``, paths become ``str``; lists,
        tuples and dicts are converted item by item (their type kept). Anything else is
        returned unchanged.

    Returns
    -------
    Any
    """
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    if isinstance(value, (list, tuple)):
        return type(value)(canonical(v) for v in value)
    if isinstance(value, Mapping):
        return {canonical(k): canonical(v) for k, v in value.items()}
    return value


def _found(value: Any) -> str:
    return f"{value!r} ({type(value).__name__})"


def _prefix(owner: str, name: str) -> str:
    return f"{owner}: {name}" if owner else name


def check_integer(
    value: Any,
    name: str,
    *,
    owner: str = "",
    low: int | None = None,
    high: int | None = None,
    error: type[GeofeatError] = DescriptorError,
    expected: str | None = None,
) -> int:
    """Check that ``value`` is an integer in ``[low, high]``; return it as a Python ``int``.

    Parameters
    ----------
    value : Any
        An ``int`` or NumPy integer; bools, floats (even ``2.0``) and strings are refused.
    name : str
        Parameter name, for the message.
    owner : str
        Descriptor or head name, for the message.
    low, high : int, optional
        Inclusive bounds.
    error : type
        Exception raised on failure.
    expected : str, optional
        What the message says was expected (e.g. ``"a positive integer number of
        eigenpairs"``); by default ``"an integer"`` and the bounds.

    Returns
    -------
    int
    """
    if not is_integer(value) or (low is not None and value < low) or (high is not None and value > high):
        if low is not None and high is not None:
            where = f" in [{low}, {high}]"
        elif low is not None:
            where = f" >= {low}"
        elif high is not None:
            where = f" <= {high}"
        else:
            where = ""
        raise error(f"{_prefix(owner, name)} must be {expected or 'an integer' + where}; found {_found(value)}.")
    return int(value)


def check_number(
    value: Any,
    name: str,
    *,
    owner: str = "",
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    high_open: bool = False,
    error: type[GeofeatError] = DescriptorError,
    expected: str | None = None,
) -> float:
    """Check that ``value`` is a finite number in the interval ``low .. high``; return it as a Python ``float``.

    Parameters
    ----------
    value : Any
        An int, float or NumPy number; bools and strings are refused.
    name, owner, error, expected
        As for `check_integer` (``expected`` defaults to ``"a finite number"`` and the bounds).
    low, high : float
        Bounds; ``low_open`` / ``high_open`` exclude the bound itself.

    Returns
    -------
    float
    """
    ok = is_finite_number(value) and (value > low if low_open else value >= low)
    if not (ok and (value < high if high_open else value <= high)):
        if math.isinf(high) and math.isinf(low):
            where = ""
        elif math.isinf(high):
            where = f" {'>' if low_open else '>='} {low}"
        elif math.isinf(low):
            where = f" {'<' if high_open else '<='} {high}"
        else:
            where = f" in {'(' if low_open else '['}{low}, {high}{')' if high_open else ']'}"
        raise error(f"{_prefix(owner, name)} must be {expected or 'a finite number' + where}; found {_found(value)}.")
    return float(value)


def check_boolean(value: Any, name: str, *, owner: str = "", error: type[GeofeatError] = DescriptorError) -> bool:
    """Check that ``value`` is a bool (or NumPy bool); return it as a Python ``bool``.

    Strings such as ``"false"`` and the integers 0 and 1 are refused: ``bool("false")`` is
    True, so accepting them would silently do the opposite of what was asked.
    """
    if not is_boolean(value):
        raise error(f"{_prefix(owner, name)} must be True or False; found {_found(value)}.")
    return bool(value)


def check_choice(
    value: Any, name: str, choices: Iterable[Any], *, owner: str = "", error: type[GeofeatError] = DescriptorError
) -> Any:
    """Check that ``value`` is one of ``choices``; return its canonical form (see `canonical`)."""
    choices = tuple(choices)
    value = canonical(value)
    if isinstance(value, bool) or value not in choices:
        raise error(f"{_prefix(owner, name)} must be one of {choices}; found {_found(value)}.")
    return value


def parse_key_values(
    items: Iterable[str], option: str = "--param", *, error: type[GeofeatError] = DescriptorError
) -> dict[str, Any]:
    """Command-line ``KEY=VALUE`` items as a dict: ``["n_descr=128", "laplacian=cotan"]`` -> ``{"n_descr": 128, "laplacian": "cotan"}``.

    Each value is read as JSON when it parses (numbers, ``true``/``false``, ``null``, lists),
    else kept as the string; the receiver checks the values. Keys are stripped of spaces.

    Parameters
    ----------
    items : iterable of str
        The values of a repeated option, as given.
    option : str
        The option's name, for messages (``"--param"``, ``"--head-param"``).
    error : type
        The `GeofeatError` subclass to raise (`ExtractError` for ``geofeat extract``).

    Raises
    ------
    GeofeatError
        Of type ``error``: an item without ``=`` or with an empty key, or a key given twice.
    """
    params: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise error(f"{option} expects KEY=VALUE (for example {option} n_descr=128); found {item!r}.")
        if key in params:
            raise error(f"{option} {key} is given twice ({params[key]!r} and {text!r}); give it once.")
        try:
            params[key] = json.loads(text)
        except ValueError:
            params[key] = text
    return params
