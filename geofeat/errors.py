"""Exception types. Every error geofeat raises for bad input derives from `GeofeatError`."""

from __future__ import annotations


class GeofeatError(Exception):
    """Base class of every error geofeat raises on purpose."""


class MeshError(GeofeatError, ValueError):
    """A mesh (arrays or file) is malformed: wrong shape, dtype, values or format."""


class SpectralError(GeofeatError, RuntimeError):
    """The Laplace-Beltrami eigenproblem could not be solved, even after every fallback."""


class DescriptorError(GeofeatError, ValueError):
    """An unknown descriptor name or a bad descriptor parameter."""


class MissingDependencyError(GeofeatError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


class CacheError(GeofeatError, OSError):
    """The feature cache cannot be used (bad location, unwritable directory)."""


class DatasetError(GeofeatError, ValueError):
    """A benchmark dataset cannot be used: folder layout, file contents or loader options are wrong."""


class MetricError(GeofeatError, ValueError):
    """Inputs to a metric have the wrong shape, dtype or values."""


class FunctionalMapError(GeofeatError, ValueError):
    """Bad input to a functional-map routine (shapes, sizes, indices)."""


class RenderError(GeofeatError, ValueError):
    """Bad input to the rendering layer (cameras, image size, mesh tensors, settings)."""


class BackboneError(GeofeatError, ValueError):
    """A DINO backbone cannot be loaded or used: missing or malformed weights, bad options or images."""


class DeviceError(GeofeatError, ValueError):
    """An unknown torch device, or CUDA requested where there is none."""


class TrainingError(GeofeatError, ValueError):
    """Bad input to a training routine (loss tensors of the wrong shape, dtype or values, bad options)."""


class DiffusionNetError(GeofeatError, ValueError):
    """Bad input to DiffusionNet: options, feature tensors or operators that do not fit together."""
