"""geofeat: per-vertex features for non-rigid and partial 3D shape matching.

>>> import geofeat
>>> mesh = geofeat.load_mesh("tr_reg_000.off")
>>> geofeat.compute(mesh, "wks").shape
(4999, 128)
"""

from geofeat._version import __version__
from geofeat.cache import CacheError, FeatureCache
from geofeat.config import cache_dir, set_cache_dir
from geofeat.descriptors import Descriptor, compute, compute_many, descriptors
from geofeat.errors import DescriptorError, GeofeatError, MeshError, MissingDependencyError, StoreError
from geofeat.geometry.errors import SpectralError
from geofeat.mesh import Mesh, load_mesh, normalize

__all__ = [
    "CacheError",
    "DatasetError",
    "Descriptor",
    "DescriptorError",
    "FeatureCache",
    "GeofeatError",
    "Mesh",
    "MeshError",
    "MissingDependencyError",
    "SpectralError",
    "StoreError",
    "__version__",
    "cache_dir",
    "compute",
    "compute_many",
    "descriptors",
    "load_mesh",
    "normalize",
    "set_cache_dir",
]


def __getattr__(name: str):
    """``geofeat.DatasetError``, imported on first use (``import geofeat`` does not load the datasets)."""
    if name == "DatasetError":
        from geofeat.datasets.errors import DatasetError

        return DatasetError
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
