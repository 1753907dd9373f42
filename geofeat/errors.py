"""Every exception type geofeat raises on purpose; all derive from `GeofeatError`.

Each type is a plain subclass, defined here and nowhere else, so that this module imports
nothing and any layer can raise any of them. Each also derives from the built-in type a
caller would catch without knowing geofeat (`ValueError` for bad input, `OSError` for
stores on disk, `ImportError` for a missing extra, ...).

========================  ===================================================================
type                      raised for
========================  ===================================================================
``MeshError``             mesh arrays and mesh files
``DescriptorError``       descriptor names and parameters (the default of `geofeat.checks`)
``MissingDependencyError``  an optional dependency that is not installed
``DeviceError``           torch devices
``StoreError``            stores of computed arrays on disk (`geofeat.storage.entry_folder.EntryFolder`)
``CacheError``            the feature cache
``SpectralError``         the Laplace-Beltrami eigenproblem
``GeodesicMemoryError``   an all-pairs geodesic matrix that does not fit in memory
``RenderError``           cameras, rasterization, shading and back-projection
``BackboneError``         DINO backbones, their weights and LoRA
``DatasetError``          benchmark folders, files and loader options
``MetricError``           inputs to the metrics
``TrainingError``         GeoLoRA training: losses, options, checkpoints
``DamagedCheckpointError``  a damaged training checkpoint (resuming falls back to an older one)
``DistributedError``      the ``torchrun`` environment and process groups
``ExtractError``          ``geofeat extract``: collections and export targets
``FunctionalMapError``    functional-map routines
``DiffusionNetError``     DiffusionNet options, features and operators
``HeadError``             head settings, inputs and checkpoints
``UnusablePair``          a training pair a head cannot learn from (skipped by ``fit``)
========================  ===================================================================
"""

from __future__ import annotations

__all__ = [
    "BackboneError",
    "CacheError",
    "DamagedCheckpointError",
    "DatasetError",
    "DescriptorError",
    "DeviceError",
    "DiffusionNetError",
    "DistributedError",
    "ExtractError",
    "FunctionalMapError",
    "GeodesicMemoryError",
    "GeofeatError",
    "HeadError",
    "MeshError",
    "MetricError",
    "MissingDependencyError",
    "RenderError",
    "SpectralError",
    "StoreError",
    "TrainingError",
    "UnknownSplitError",
    "UnusablePair",
]


class GeofeatError(Exception):
    """Base class of every error geofeat raises on purpose."""


# ----------------------------------------------------------------------------- core


class MeshError(GeofeatError, ValueError):
    """A mesh (arrays or file) is malformed: wrong shape, dtype, values or format."""


class DescriptorError(GeofeatError, ValueError):
    """An unknown descriptor name or a bad descriptor parameter."""


class MissingDependencyError(GeofeatError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


class DeviceError(GeofeatError, ValueError):
    """An unknown torch device, or CUDA requested where there is none."""


class StoreError(GeofeatError, OSError):
    """A store of computed arrays on disk (`geofeat.storage.entry_folder.EntryFolder`) cannot be read, written or cleared."""


class CacheError(StoreError):
    """The feature cache cannot be used (bad location, unwritable directory)."""


class DistributedError(GeofeatError, RuntimeError):
    """The torchrun environment is inconsistent, or the process group cannot be started."""


# ----------------------------------------------------------------------------- geometry


class SpectralError(GeofeatError, RuntimeError):
    """The Laplace-Beltrami eigenproblem could not be solved, even after every fallback."""


class GeodesicMemoryError(GeofeatError, MemoryError):
    """An all-pairs geodesic matrix does not fit in memory."""


# ----------------------------------------------------------------------------- rendering and backbones


class RenderError(GeofeatError, ValueError):
    """Bad input to the rendering layer: cameras, image size, mesh tensors, shading or back-projection settings."""


class BackboneError(GeofeatError, ValueError):
    """A DINO backbone cannot be loaded or used: missing or malformed weights, bad options or images."""


# ----------------------------------------------------------------------------- datasets, metrics, training


class DatasetError(GeofeatError, ValueError):
    """A benchmark dataset cannot be used: folder layout, file contents or loader options are wrong."""


class UnknownSplitError(DatasetError):
    """A dataset was asked for a split it does not have (the message names those it has)."""


class MetricError(GeofeatError, ValueError):
    """Inputs to a metric have the wrong shape, dtype or values."""


class TrainingError(GeofeatError, ValueError):
    """Bad input to a training routine (loss tensors of the wrong shape, dtype or values, bad options, checkpoints)."""


class DamagedCheckpointError(TrainingError):
    """A training checkpoint that cannot be read (truncated, not written by the trainer); resuming falls back to an older one."""


# ----------------------------------------------------------------------------- heads


class FunctionalMapError(GeofeatError, ValueError):
    """Bad input to a functional-map routine (shapes, sizes, indices)."""


class DiffusionNetError(GeofeatError, ValueError):
    """Bad input to DiffusionNet: options, feature tensors or operators that do not fit together."""


class HeadError(GeofeatError, ValueError):
    """Bad head settings, inputs or checkpoints."""


class UnusablePair(HeadError):
    """A training pair a head cannot learn from (e.g. two partial shapes that do not overlap); `fit` skips it."""


# ----------------------------------------------------------------------------- applications


class ExtractError(GeofeatError, ValueError):
    """Bad input to ``geofeat extract``: no shapes, an unknown layout, an export target that cannot be used."""
