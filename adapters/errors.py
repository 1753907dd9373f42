"""Error types of the heads layer (also importable from `geofeat.errors`).

`HeadError` and `UnusablePair` live beside the heads, in `geofeat.adapters.heads`.
"""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["FunctionalMapError", "DiffusionNetError"]


class FunctionalMapError(GeofeatError, ValueError):
    """Bad input to a functional-map routine (shapes, sizes, indices)."""


class DiffusionNetError(GeofeatError, ValueError):
    """Bad input to DiffusionNet: options, feature tensors or operators that do not fit together."""
