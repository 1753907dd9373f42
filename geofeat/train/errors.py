"""`TrainingError`, raised by the training layer (also importable from `geofeat.errors`)."""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["TrainingError"]


class TrainingError(GeofeatError, ValueError):
    """Bad input to a training routine (loss tensors of the wrong shape, dtype or values, bad options)."""
