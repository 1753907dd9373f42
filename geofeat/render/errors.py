"""`RenderError`, raised by the rendering layer (also importable from `geofeat.errors`)."""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["RenderError"]


class RenderError(GeofeatError, ValueError):
    """Bad input to the rendering layer (cameras, image size, mesh tensors, settings)."""
