"""The geodesic matrices of the training shapes, handed out as torch tensors: `TorchGeodesicStore`.

A full shape's all-pairs geodesic matrix (edge Dijkstra, divided by ``sqrt(area)``) is
computed once and stored as a float16 ``.npy`` file keyed by the mesh content hash (the
geometry layer's `geofeat.geometry.geodesic_store.GeodesicStore`, checksum-verified); steps
read it back. float16 keeps about three significant digits, plenty for the loss weights
``0.5 + d``, and halves the disk use (a 5,000-vertex shape takes 50 MB, a 12,000-vertex one
288 MB).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from geofeat.errors import MeshError, TrainingError
from geofeat.geometry import geodesic_store
from geofeat.mesh import Mesh

__all__ = ["TorchGeodesicStore"]


class TorchGeodesicStore(geodesic_store.GeodesicStore):
    """The geometry layer's `geofeat.geometry.geodesic_store.GeodesicStore` handing out torch tensors, as training uses it.

    What it adds: matrices handed out as float32 torch tensors on a device, float16 entries
    (the loss weights need about three digits), connected shapes only, and `TrainingError`
    (not `MeshError`) for a mesh in several pieces.

    Parameters
    ----------
    folder : str or os.PathLike, optional
        Default ``<geofeat cache>/geodesics``.
    """

    def __init__(self, folder: str | os.PathLike | None = None):
        super().__init__(folder, dtype="float16", connected=True)

    def ensure(self, mesh: Mesh) -> Path:
        """Compute and store the matrix unless present (`TrainingError` for a mesh in several pieces)."""
        try:
            return super().ensure(mesh)
        except MeshError as exc:
            raise TrainingError(str(exc)) from exc

    def load(self, mesh: Mesh, device: str | torch.device = "cpu") -> torch.Tensor:
        """The (V, V) float32 matrix of ``mesh`` on ``device``; computed when missing, recomputed when the file is damaged."""
        return self.load_stored(mesh).to(device).float()

    def load_stored(self, mesh: Mesh) -> torch.Tensor:
        """The matrix of ``mesh`` as stored: (V, V) float16 on the CPU, a copy (`load` widens it to float32)."""
        try:
            dist = super().load(mesh, widen=False)
        except MeshError as exc:
            raise TrainingError(str(exc)) from exc
        return torch.from_numpy(np.array(dist))
