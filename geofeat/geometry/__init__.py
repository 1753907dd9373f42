"""Geometry on meshes and point clouds: Laplacians, spectral bases, geodesic distances, surface points and partial shapes."""

from geofeat.geometry.geodesic import distances_from, geodesic_matrix
from geofeat.geometry.laplacian import Laplacian, laplacian
from geofeat.geometry.partial import PartialShape, make_partial
from geofeat.geometry.spectral import SpectralBasis, spectral_basis
from geofeat.geometry.surface_points import SurfacePoints

__all__ = [
    "Laplacian",
    "PartialShape",
    "SpectralBasis",
    "SurfacePoints",
    "distances_from",
    "geodesic_matrix",
    "laplacian",
    "make_partial",
    "spectral_basis",
]
