"""Laplace-Beltrami discretisations: stiffness matrix and lumped mass."""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from geofeat.errors import MeshError
from geofeat.mesh import Mesh

log = logging.getLogger(__name__)

LAPLACIANS = ("robust", "cotan")
#: A point of a cloud links to those of its ``n_neighbors`` nearest points closer than this many
#: times its local spacing (the median nearest-neighbour distance of those points);
#: `isolated_points` are the groups of at most ``n_neighbors`` points that these links
#: leave apart from the rest. Uniform random samples of a surface stay below 5.
ISOLATION_SPACING_FACTOR = 10.0


class Laplacian(NamedTuple):
    """A weak Laplacian.

    Attributes
    ----------
    stiffness : scipy.sparse.csr_matrix, shape (V, V), float64
        Symmetric positive semi-definite stiffness matrix (rows sum to zero).
    mass : numpy.ndarray, shape (V,), float64
        Lumped (diagonal) mass, the area attached to each vertex (zero at the points of a
        point cloud left out of the Laplacian, see `laplacian`).
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

    Notes
    -----
    On a point cloud two kinds of points are left out of the Laplacian (zero rows, columns
    and mass, as unreferenced vertices of a mesh; `geofeat.geometry.spectral.spectral_basis`
    gives them the eigenvector values of their nearest point with mass), with a logged
    warning: every copy of a position but the first (coincident points, which the robust
    Laplacian would tie by enormous weights), and isolated points (`isolated_points`).

    Raises
    ------
    MeshError
        An unknown ``kind``; a point cloud of ``n_neighbors`` distinct, not isolated points
        or fewer, or one the robust Laplacian cannot triangulate (points on a line or curve).
    """
    if kind not in LAPLACIANS:
        raise MeshError(f"unknown Laplacian kind {kind!r}; expected one of {LAPLACIANS}.")
    if mesh.faces is None:
        if kind != "robust":
            raise MeshError(f"{mesh.name!r} is a point cloud: only kind='robust' works without faces (got {kind!r}).")
        stiffness, mass = _point_cloud_laplacian(mesh, mollify_factor, n_neighbors)
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


def _point_cloud_laplacian(mesh: Mesh, mollify_factor: float, n_neighbors: int) -> tuple[sp.csr_matrix, np.ndarray]:
    """The robust point-cloud Laplacian on the distinct, not isolated points; the others get zero rows and mass."""
    name = mesh.name or "<unnamed>"
    distinct = _first_copies(mesh.verts)
    isolated = np.zeros(mesh.n_vertices, dtype=bool)
    if distinct.sum() > n_neighbors:
        isolated[distinct] = isolated_points(mesh.verts[distinct], n_neighbors)
    solved = np.flatnonzero(distinct & ~isolated)
    if len(solved) <= n_neighbors:
        detail = "" if len(solved) == mesh.n_vertices else f", of which {len(solved)} distinct and not isolated"
        raise MeshError(
            f"point cloud {name!r} has {mesh.n_vertices} points{detail}; the robust point-cloud Laplacian builds each point's {n_neighbors} nearest "
            f"neighbours, so it needs at least {n_neighbors + 1} points. Sample the surface more densely, or pass the mesh with its faces."
        )
    _warn_left_out(name, mesh.n_vertices - int(distinct.sum()), int(isolated.sum()), n_neighbors)
    import robust_laplacian

    try:
        stiffness, mass = robust_laplacian.point_cloud_laplacian(
            mesh.verts[solved], mollify_factor=mollify_factor, n_neighbors=n_neighbors
        )
    except RuntimeError as err:
        raise MeshError(
            f"the robust Laplacian failed on point cloud {name!r} ({err}); expected points sampling a surface. Points "
            "on a line or curve have no surface to triangulate: check the input."
        ) from err
    mass = np.asarray(sp.csr_matrix(mass).diagonal() if sp.issparse(mass) else mass, dtype=np.float64)
    if len(solved) == mesh.n_vertices:
        return sp.csr_matrix(stiffness), mass
    spread = sp.csr_matrix((np.ones(len(solved)), (solved, np.arange(len(solved)))), shape=(mesh.n_vertices, len(solved)))
    full_mass = np.zeros(mesh.n_vertices)
    full_mass[solved] = mass
    return sp.csr_matrix(spread @ stiffness @ spread.T), full_mass


def _first_copies(verts: np.ndarray) -> np.ndarray:
    """(V,) bool: True at the first occurrence of every distinct position."""
    _, first = np.unique(verts, axis=0, return_index=True)
    mask = np.zeros(len(verts), dtype=bool)
    mask[first] = True
    return mask


def isolated_points(points: np.ndarray, n_neighbors: int = 30) -> np.ndarray:
    """The points of a cloud that lie apart from the surface the others sample.

    Parameters
    ----------
    points : numpy.ndarray, shape (V, 3)
        Distinct points, ``V > n_neighbors``.
    n_neighbors : int
        Neighbourhood size of the point-cloud Laplacian.

    Returns
    -------
    numpy.ndarray, shape (V,), bool
        True for the points of the groups of at most ``n_neighbors`` points that no point
        outside the group links to, where a point links to those of its ``n_neighbors``
        nearest points closer than `ISOLATION_SPACING_FACTOR` times its local spacing (the
        median distance of those points to their own nearest neighbour). Such a group is
        too small for neighbourhoods of its own, so the Laplacian would tie it to distant
        points by weak weights: a spurious low-frequency mode on it.
    """
    dists, neighbors = cKDTree(points).query(points, k=n_neighbors + 1)  # column 0: the point itself
    spacing = dists[:, 1]
    local = np.median(spacing[neighbors[:, 1:]], axis=1)
    linked = dists[:, 1:] <= ISOLATION_SPACING_FACTOR * local[:, None]
    rows = np.repeat(np.arange(len(points)), n_neighbors)[linked.ravel()]
    graph = sp.csr_matrix((np.ones(len(rows)), (rows, neighbors[:, 1:].ravel()[linked.ravel()])), shape=(len(points),) * 2)
    _, labels = connected_components(graph, directed=False)
    return np.bincount(labels)[labels] <= n_neighbors


def _warn_left_out(name: str, n_copies: int, n_isolated: int, n_neighbors: int) -> None:
    if n_copies:
        log.warning(
            "point cloud %r: %d point(s) repeat the position of an earlier one; the Laplacian is built on the first copy, "
            "the others get zero mass and its eigenvector values",
            name,
            n_copies,
        )
    if n_isolated:
        log.warning(
            "point cloud %r: %d isolated point(s), in groups of at most %d far from the surface the other points sample; "
            "they get zero mass and the eigenvector values of their nearest point with mass (remove outliers to "
            "silence this)",
            name,
            n_isolated,
            n_neighbors,
        )


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
