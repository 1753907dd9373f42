"""geofeat: per-vertex features for non-rigid and partial 3D shape matching.

>>> import geofeat
>>> mesh = geofeat.load_mesh("tr_reg_000.off")
>>> geofeat.compute(mesh, "wks").shape
(4999, 128)
"""

from geofeat._version import __version__
from geofeat.descriptors import Descriptor, compute, compute_many, descriptors, make_descriptor
from geofeat.descriptors.cache import FeatureCache
from geofeat.errors import (
    BackboneError,
    CacheError,
    DamagedCheckpointError,
    DatasetError,
    DescriptorError,
    DeviceError,
    DiffusionNetError,
    DistributedError,
    ExtractError,
    FunctionalMapError,
    GeodesicMemoryError,
    GeofeatError,
    HeadError,
    MeshError,
    MetricError,
    MissingDependencyError,
    RenderError,
    SpectralError,
    StoreError,
    TrainingError,
    UnknownSplitError,
    UnusablePair,
)
from geofeat.mesh import Mesh, load_mesh, normalize
from geofeat.storage.cache_folder import cache_dir, set_cache_dir

__all__ = [
    "BackboneError",
    "CacheError",
    "DamagedCheckpointError",
    "DatasetError",
    "Descriptor",
    "DescriptorError",
    "DeviceError",
    "DiffusionNetError",
    "DistributedError",
    "ExtractError",
    "FeatureCache",
    "FunctionalMapError",
    "GeodesicMemoryError",
    "GeofeatError",
    "HeadError",
    "Mesh",
    "MeshError",
    "MetricError",
    "MissingDependencyError",
    "RenderError",
    "SpectralError",
    "StoreError",
    "TrainingError",
    "UnknownSplitError",
    "UnusablePair",
    "__version__",
    "cache_dir",
    "compute",
    "compute_many",
    "descriptors",
    "load_mesh",
    "make_descriptor",
    "normalize",
    "set_cache_dir",
]
