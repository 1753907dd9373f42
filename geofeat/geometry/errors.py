"""`SpectralError`, raised by the geometry layer (also importable from `geofeat.errors` and `geofeat`).

Bad meshes raise the core's `geofeat.errors.MeshError`.
"""

from __future__ import annotations

from geofeat.errors import GeofeatError

__all__ = ["SpectralError"]


class SpectralError(GeofeatError, RuntimeError):
    """The Laplace-Beltrami eigenproblem could not be solved, even after every fallback."""
