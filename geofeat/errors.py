"""Exception types of the core. Every error geofeat raises for bad input derives from `GeofeatError`.

The core's own errors are defined here: `GeofeatError`, `MeshError` (meshes, files),
`DescriptorError` (bad parameters; the default of `geofeat.checks`), `MissingDependencyError`
(optional dependencies, `geofeat.registry`), `DeviceError` (`geofeat.devices`) and `StoreError`
(stores of computed arrays on disk, `geofeat.files.EntryFolder`). Every other
error type is defined beside the layer that raises it and is re-exported here (imported on
first use, so this module never imports a layer above the core):

========================  ==========================================
``SpectralError``         `geofeat.geometry.errors`
``CacheError``            `geofeat.cache`
``DatasetError``          `geofeat.datasets.errors`
``MetricError``           `geofeat.metrics`
``RenderError``           `geofeat.render.errors`
``BackboneError``         `geofeat.backbones.errors`
``TrainingError``         `geofeat.train.errors`
``FunctionalMapError``    `geofeat.adapters.errors`
``DiffusionNetError``     `geofeat.adapters.errors`
========================  ==========================================
"""

from __future__ import annotations

import importlib
from typing import Any

#: Error types defined in the layer that raises them: name -> module.
MOVED = {
    "SpectralError": "geofeat.geometry.errors",
    "CacheError": "geofeat.cache",
    "DatasetError": "geofeat.datasets.errors",
    "MetricError": "geofeat.metrics",
    "RenderError": "geofeat.render.errors",
    "BackboneError": "geofeat.backbones.errors",
    "TrainingError": "geofeat.train.errors",
    "FunctionalMapError": "geofeat.adapters.errors",
    "DiffusionNetError": "geofeat.adapters.errors",
}


def __getattr__(name: str) -> Any:
    """``geofeat.errors.X`` for the error types defined in the layers (`MOVED`)."""
    if name in MOVED:
        return getattr(importlib.import_module(MOVED[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *MOVED])


class GeofeatError(Exception):
    """Base class of every error geofeat raises on purpose."""


class MeshError(GeofeatError, ValueError):
    """A mesh (arrays or file) is malformed: wrong shape, dtype, values or format."""


class DescriptorError(GeofeatError, ValueError):
    """An unknown descriptor name or a bad descriptor parameter."""


class MissingDependencyError(GeofeatError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


class DeviceError(GeofeatError, ValueError):
    """An unknown torch device, or CUDA requested where there is none."""


class StoreError(GeofeatError, OSError):
    """A store of computed arrays on disk (`geofeat.files.EntryFolder`) cannot be read, written or cleared."""
