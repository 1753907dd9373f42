"""Geometry on meshes: Laplacians, spectral bases, geodesic distances and partial shapes."""

from geofeat.geometry.geodesic import distances_from, geodesic_matrix
from geofeat.geometry.laplacian import Laplacian, laplacian
from geofeat.geometry.partial import PartialShape, make_partial
from geofeat.geometry.spectral import SpectralBasis, spectral_basis

__all__ = [
    "Laplacian",
    "PartialShape",
    "SpectralBasis",
    "distances_from",
    "geodesic_matrix",
    "laplacian",
    "make_partial",
    "spectral_basis",
]
