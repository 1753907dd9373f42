"""`BackboneError`, raised by the backbones layer (also importable from `geofeat.errors`)."""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["BackboneError"]


class BackboneError(GeofeatError, ValueError):
    """A DINO backbone cannot be loaded or used: missing or malformed weights, bad options or images."""
