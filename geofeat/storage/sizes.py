"""Sizes in bytes: read from settings (``"4G"``, ``"512M"``) and written for messages (``"6.4 GB"``).

>>> parse_size("1.5k", "limit")
1536
>>> format_size(6_400_000_000)
'6.4 GB'
"""

from __future__ import annotations

import re

import numpy as np

from geofeat.errors import GeofeatError

__all__ = ["format_size", "parse_size"]

_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(value: int | float | str, name: str, error: type[GeofeatError] = GeofeatError) -> int:
    """A number of bytes from ``4294967296``, ``"4G"``, ``"4GB"``, ``"4GiB"``, ``"512M"`` or ``"1.5g"`` (powers of 1024).

    Parameters
    ----------
    value : int, float or str
        A number of bytes, or a number followed by ``k``, ``m``, ``g`` or ``t`` (any case,
        optionally followed by ``b`` or ``ib``).
    name : str
        What the size sets (an argument or an environment variable), for the message.
    error : type of GeofeatError
        The error raised for a bad ``value``.

    Returns
    -------
    int
        Bytes, zero or more.

    Raises
    ------
    GeofeatError
        (``error``) For anything else, a negative size included; the message names ``name``.
    """
    if isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool):
        number, unit = float(value), ""
    else:
        found = re.fullmatch(r"\s*([0-9]+(?:\.[0-9]*)?)\s*([kmgt]?)(?:i?b)?\s*", str(value), re.IGNORECASE)
        if found is None:
            raise error(f"{name} must be a size in bytes such as 4G, 512M or 1073741824; found {value!r}.")
        number, unit = float(found.group(1)), found.group(2).lower()
    if not np.isfinite(number) or number < 0:
        raise error(f"{name} must be a size of zero bytes or more; found {value!r}.")
    return int(number * _UNITS[unit])


def format_size(n_bytes: float) -> str:
    """``"6.4 GB"``: a size for messages, in powers of 1000."""
    for unit, factor in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n_bytes >= factor:
            return f"{n_bytes / factor:.1f} {unit}"
    return f"{int(n_bytes)} bytes"
