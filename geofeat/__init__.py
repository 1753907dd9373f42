"""geofeat: per-vertex features for non-rigid and partial 3D shape matching.

>>> import geofeat
>>> mesh = geofeat.load_mesh("tr_reg_000.off")
>>> geofeat.compute(mesh, "wks").shape
(4999, 128)
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("geofeat")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

from geofeat.cache import FeatureCache
from geofeat.config import cache_dir, set_cache_dir
from geofeat.descriptors import Descriptor, compute, compute_many, descriptors
from geofeat.errors import (
    CacheError,
    DatasetError,
    DescriptorError,
    GeofeatError,
    MeshError,
    MissingDependencyError,
    SpectralError,
)
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
    "__version__",
    "cache_dir",
    "compute",
    "compute_many",
    "descriptors",
    "load_mesh",
    "normalize",
    "set_cache_dir",
]
