"""Vertex normals of meshes and point clouds: the one implementation behind shading and DiffusionNet's operators.

>>> normals = vertex_normals(mesh)                                  # (V, 3) float64, unit  # doctest: +SKIP
>>> normals = vertex_normals(verts, faces, face_weights="unit")     # the DiffusionNet code's weights  # doctest: +SKIP
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from geofeat.errors import MeshError
from geofeat.mesh import Mesh

__all__ = ["FACE_WEIGHTS", "N_NEIGHBORS_CLOUD", "vertex_normals"]

#: How the normals of the faces around a vertex are summed: by area, or each normalised.
FACE_WEIGHTS = ("area", "unit")
#: Neighbours of each point used for the normal of a point (as in DiffusionNet).
N_NEIGHBORS_CLOUD = 30


def vertex_normals(
    verts: Mesh | np.ndarray,
    faces: np.ndarray | None = None,
    face_weights: str = "area",
    normalize_eps: float = 1e-12,
    fallback: bool = True,
) -> np.ndarray:
    """Unit normal at every vertex.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        A `Mesh` (then ``faces`` must be None), or vertex positions.
    faces : array_like of int, shape (F, 3), optional
        Triangles; None for a point cloud.
    face_weights : {"area", "unit"}
        Sum the adjacent face normals weighted by face area (as pytorch3d's
        ``Meshes.verts_normals_packed``), or normalised (the DiffusionNet reference code;
        degenerate faces then add nothing).
    normalize_eps : float
        With ``face_weights="unit"``: a face normal ``n`` counts as ``n / (|n| + normalize_eps)``.
    fallback : bool
        What a vertex without a usable face normal gets (a point of a point cloud, a vertex
        in no face, or one whose face normals cancel): True, the direction of least
        variance of its `N_NEIGHBORS_CLOUD` nearest points, oriented away from the centroid
        of the shape; False, a zero normal (the renderer: such a vertex shades no pixel).

    Returns
    -------
    numpy.ndarray, shape (V, 3), float64
        On a mesh, the normalised sum of the adjacent face normals (oriented like the
        faces, right-handed), weighted as ``face_weights`` says; elsewhere as ``fallback``
        says.

    Raises
    ------
    MeshError
        A Mesh given with faces, arrays of the wrong shape, or an unknown ``face_weights``.
    """
    if isinstance(verts, Mesh):
        if faces is not None:
            raise MeshError("vertex_normals: pass either a Mesh or verts and faces, not a Mesh and faces.")
        faces, verts = verts.faces, verts.verts
    verts = np.asarray(verts, dtype=np.float64)
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise MeshError(f"vertex_normals: verts must have shape (V, 3); found {verts.shape}.")
    if face_weights not in FACE_WEIGHTS:
        raise MeshError(f"face_weights must be 'area' or 'unit'; found {face_weights!r}.")
    normals = np.zeros_like(verts)
    if faces is not None:
        faces = np.asarray(faces, dtype=np.int64)
        if faces.ndim != 2 or faces.shape[1] != 3:
            raise MeshError(f"vertex_normals: faces must have shape (F, 3); found {faces.shape}.")
        tri = verts[faces]
        face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
        if face_weights == "unit":
            face_normals = face_normals / (np.linalg.norm(face_normals, axis=1, keepdims=True) + normalize_eps)
        for corner in range(3):
            np.add.at(normals, faces[:, corner], face_normals)
    lengths = np.linalg.norm(normals, axis=1)
    scale = max(_bbox_diagonal(verts), 1e-300)
    missing = lengths <= (1e-12 if face_weights == "unit" else 1e-12 * scale**2)
    if missing.any():
        normals[missing] = _cloud_normals(verts, np.flatnonzero(missing)) if fallback else 0.0
        lengths[missing] = 1.0
    return normals / lengths[:, None]


def _bbox_diagonal(verts: np.ndarray) -> float:
    """Length of the bounding-box diagonal (0 without vertices)."""
    if len(verts) == 0:
        return 0.0
    return float(np.linalg.norm(verts.max(axis=0) - verts.min(axis=0)))


def _cloud_normals(verts: np.ndarray, which: np.ndarray) -> np.ndarray:
    """Least-variance direction of the neighbourhood of ``verts[which]``, (n, 3) unit."""
    n_query = min(N_NEIGHBORS_CLOUD + 1, len(verts))
    if n_query < 3:
        normals = np.zeros((len(which), 3))
        normals[:, 2] = 1.0
        return normals
    _, neighbors = cKDTree(verts).query(verts[which], k=n_query)
    local = verts[neighbors] - verts[which][:, None, :]
    local -= local.mean(axis=1, keepdims=True)
    normals = np.linalg.svd(local, full_matrices=False)[2][:, 2, :]
    outward = np.einsum("nd,nd->n", normals, verts[which] - verts.mean(axis=0))
    return np.where(outward[:, None] < 0, -normals, normals)
