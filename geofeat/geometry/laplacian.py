"""Laplace-Beltrami discretisations: stiffness matrix and lumped mass."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from geofeat.errors import MeshError
from geofeat.mesh import Mesh

LAPLACIANS = ("robust", "cotan")


class Laplacian(NamedTuple):
    """A weak Laplacian.

    Attributes
    ----------
    stiffness : scipy.sparse.csr_matrix, shape (V, V), float64
        Symmetric positive semi-definite stiffness matrix (rows sum to zero).
    mass : numpy.ndarray, shape (V,), float64
        Lumped (diagonal) mass, the area attached to each vertex.
    """

    stiffness: sp.csr_matrix
    mass: np.ndarray


def laplacian(mesh: Mesh, kind: str = "robust", mollify_factor: float = 1e-5, n_neighbors: int = 30) -> Laplacian:
    """Build the Laplacian of a mesh or point cloud.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh, or point cloud (``faces=None``; needs ``kind="robust"``).
    kind : {"robust", "cotan"}
        ``"robust"``: the tufted intrinsic-Delaunay Laplacian of Sharp and Crane (2020),
        package robust-laplacian; sound on non-manifold and degenerate meshes and on point
        clouds. ``"cotan"``: the classic cotangent Laplacian with lumped mass (one third of
        the adjacent triangle areas), as in pyFM; degenerate faces are ignored.
    mollify_factor : float
        Intrinsic mollification of the robust Laplacian (relative to mean edge length).
    n_neighbors : int
        Neighbourhood size of the robust point-cloud Laplacian.

    Returns
    -------
    Laplacian
        ``stiffness`` (V, V) csr float64 and ``mass`` (V,) float64.

    Raises
    ------
    MeshError
        An unknown ``kind``; a point cloud of ``n_neighbors`` points or fewer, or one the
        robust Laplacian cannot triangulate (coincident or collinear points).
    """
    if kind not in LAPLACIANS:
        raise MeshError(f"unknown Laplacian kind {kind!r}; expected one of {LAPLACIANS}.")
    if mesh.faces is None:
        if kind != "robust":
            raise MeshError(f"{mesh.name!r} is a point cloud: only kind='robust' works without faces (got {kind!r}).")
        if mesh.n_vertices <= n_neighbors:
            raise MeshError(
                f"point cloud {mesh.name or '<unnamed>'!r} has {mesh.n_vertices} points; the robust point-cloud Laplacian "
                f"builds each point's {n_neighbors} nearest neighbours, so it needs at least {n_neighbors + 1} points. "
                "Sample the surface more densely, or pass the mesh with its faces."
            )
        import robust_laplacian

        try:
            stiffness, mass = robust_laplacian.point_cloud_laplacian(
                mesh.verts, mollify_factor=mollify_factor, n_neighbors=n_neighbors
            )
        except RuntimeError as err:
            raise MeshError(
                f"the robust Laplacian failed on point cloud {mesh.name or '<unnamed>'!r} ({err}); expected points sampling "
                "a surface. Coincident points or points on a line or curve have no surface to triangulate: remove "
                "duplicates and check the input."
            ) from err
    elif kind == "robust":
        import robust_laplacian

        try:
            stiffness, mass = robust_laplacian.mesh_laplacian(mesh.verts, mesh.faces, mollify_factor=mollify_factor)
        except RuntimeError as err:
            raise MeshError(
                f"the robust Laplacian failed on mesh {mesh.name or '<unnamed>'!r} ({err}); see Mesh.report() for its "
                "problems, or try laplacian='cotan'."
            ) from err
    else:
        stiffness, mass = _cotan_laplacian(mesh.verts, mesh.faces)
    mass = np.asarray(sp.csr_matrix(mass).diagonal() if sp.issparse(mass) else mass, dtype=np.float64)
    return Laplacian(sp.csr_matrix(stiffness, dtype=np.float64), mass)


def _cotan_laplacian(verts: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray]:
    """Cotangent stiffness (V, V) and lumped mass (V,), skipping zero-area faces."""
    n = len(verts)
    tri = verts[faces]  # (F, 3, 3)
    double_area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    keep = double_area > 1e-300
    faces, tri, double_area = faces[keep], tri[keep], double_area[keep]
    row_parts, col_parts, weight_parts = [], [], []
    for corner in range(3):
        i, j = (corner + 1) % 3, (corner + 2) % 3
        u = tri[:, i] - tri[:, corner]
        v = tri[:, j] - tri[:, corner]
        cot = np.einsum("fd,fd->f", u, v) / double_area
        row_parts.append(faces[:, i])
        col_parts.append(faces[:, j])
        weight_parts.append(0.5 * cot)
    rows, cols, weights = np.concatenate(row_parts), np.concatenate(col_parts), np.concatenate(weight_parts)
    off = sp.coo_matrix((-weights, (rows, cols)), shape=(n, n))
    off = off + off.T
    stiffness = off - sp.diags(np.asarray(off.sum(axis=1)).ravel())
    mass = np.bincount(faces.ravel(), weights=np.repeat(double_area / 6.0, 3), minlength=n)
    return sp.csr_matrix(stiffness), mass
