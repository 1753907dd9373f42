"""Geometry on meshes: Laplacians and spectral bases."""

from geofeat.geometry.laplacian import Laplacian, laplacian
from geofeat.geometry.spectral import SpectralBasis, spectral_basis

__all__ = ["Laplacian", "SpectralBasis", "laplacian", "spectral_basis"]
