"""Points on the surface of a triangle mesh, each given by a face and barycentric coordinates: `SurfacePoints`.

A point cloud made from a mesh (a depth scan, a surface sample) keeps, for each point, the
surface point it came from. Ground truth and evaluation read the mesh through it: a point
stands for the corner of its face with the largest barycentric weight
(`SurfacePoints.nearest_corner`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from geofeat.errors import MeshError
from geofeat.mesh import Mesh, require_faces

__all__ = ["BARY_TOLERANCE", "SurfacePoints"]

#: How far barycentric coordinates may stray below 0 or their sum from 1 (float32 rounding of a rasterizer).
BARY_TOLERANCE = 1e-4


@dataclass(frozen=True, eq=False)
class SurfacePoints:
    """P points on a triangle mesh: a face and barycentric coordinates each.

    Parameters
    ----------
    mesh : Mesh
        The triangle mesh the points lie on (F faces, V vertices).
    face : array_like of int, shape (P,)
        Face index of each point, in ``[0, F)``.
    bary : array_like of float, shape (P, 3)
        Barycentric coordinates of each point in its face, weights of the face's corners in
        ``mesh.faces`` order: non-negative and summing to 1 (within `BARY_TOLERANCE`).
        Stored as float64.

    Raises
    ------
    MeshError
        A point cloud for ``mesh``, or arrays of the wrong shape or values.
    """

    mesh: Mesh
    face: np.ndarray
    bary: np.ndarray

    def __post_init__(self) -> None:
        faces = require_faces(self.mesh, "surface points")
        face = np.asarray(self.face)
        bary = np.asarray(self.bary, dtype=np.float64)
        if face.ndim != 1 or (face.size and face.dtype.kind not in "iu"):
            raise MeshError(f"surface points: face must be a 1-D integer array, shape (P,); found {face.dtype} {face.shape}.")
        if bary.shape != (face.size, 3):
            raise MeshError(f"surface points: bary must have shape (P, 3) = ({face.size}, 3); found {bary.shape}.")
        if face.size and (face.min() < 0 or face.max() >= len(faces)):
            raise MeshError(
                f"surface points: face indices must lie in [0, {len(faces) - 1}] ({self.mesh.name!r} has {len(faces)} faces); "
                f"found [{face.min()}, {face.max()}]."
            )
        if not np.isfinite(bary).all() or (bary < -BARY_TOLERANCE).any() or (np.abs(bary.sum(axis=1) - 1) > BARY_TOLERANCE).any():
            raise MeshError("surface points: barycentric coordinates must be finite, non-negative and sum to 1 in every row.")
        face = face.astype(np.int64)
        for array in (face, bary):
            array.flags.writeable = False
        object.__setattr__(self, "face", face)
        object.__setattr__(self, "bary", bary)

    def __len__(self) -> int:
        return int(self.face.size)

    def positions(self) -> np.ndarray:
        """The points, shape (P, 3) float64: ``v0 + b1 (v1 - v0) + b2 (v2 - v0)`` of each face."""
        corners = self.mesh.verts[require_faces(self.mesh, "surface points")[self.face]]  # (P, 3, 3)
        origin = corners[:, 0]
        return origin + self.bary[:, 1:2] * (corners[:, 1] - origin) + self.bary[:, 2:3] * (corners[:, 2] - origin)

    @cached_property
    def nearest_corner(self) -> np.ndarray:
        """The vertex of each point's face with the largest barycentric weight (the first corner on ties), shape (P,) int64, read-only."""
        faces = require_faces(self.mesh, "surface points")
        corner = np.argmax(self.bary, axis=1)
        vertex = faces[self.face, corner]
        vertex.flags.writeable = False
        return vertex
