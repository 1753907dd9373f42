"""`DatasetError`, raised by the datasets layer (also importable from `geofeat.errors` and `geofeat`)."""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["DatasetError"]


class DatasetError(GeofeatError, ValueError):
    """A benchmark dataset cannot be used: folder layout, file contents or loader options are wrong."""
