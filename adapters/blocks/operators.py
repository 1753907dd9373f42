"""Per-shape operators of DiffusionNet: mass, Laplace-Beltrami eigenpairs and tangent-plane gradients.

The gradient operator follows the construction that Sharp et al. (2022, "DiffusionNet:
Discretization Agnostic Learning on Surfaces", section 3.3) describe for meshes and point
clouds: each vertex gets a normal and a tangent basis ``(X, Y)``; the gradient of a scalar
function at a vertex is the least-squares fit of the function differences along the edges
to its neighbours (the mesh edges, or the ``k`` nearest points of a point cloud), with the
edge vectors expressed in that basis. It is stored as two real sparse matrices, the ``X``
and ``Y`` components, i.e. the real and imaginary parts of a complex gradient.

Eigenpairs and mass come from `geofeat.geometry.spectral.spectral_basis` (the same cache, so
they are never recomputed for a shape already seen). Everything is computed in float64 and
handed out as float32 torch tensors. torch is imported where the tensors are made, so that a
head's settings can be checked against `CONSTRUCTIONS` without loading it.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from geofeat.errors import MeshError
from geofeat.geometry.normals import N_NEIGHBORS_CLOUD, vertex_normals
from geofeat.geometry.spectral import spectral_basis
from geofeat.mesh import Mesh
from geofeat.runtime.devices import resolve_device
from geofeat.storage.lru import LRUCache
from geofeat.topology import unique_edges

if TYPE_CHECKING:
    import torch

#: Tikhonov regularisation of the per-vertex least-squares gradient fit, relative to the mean
#: squared tangent edge length at the vertex (keeps nearly collinear neighbourhoods solvable).
GRADIENT_REGULARIZATION = 1e-5
#: Absolute Tikhonov regularisation of the gradient fit in the DiffusionNet reference code
#: (``construction="diffusionnet"``), in squared length units of the (unit-area) shape.
REFERENCE_GRADIENT_REGULARIZATION = 1e-5
#: Operator constructions: ours, and the two variants of the DiffusionNet reference code the
#: released models were trained with, which differ only in the epsilon added to a vector's
#: length when face normals and tangent axes are normalised: the original DiffusionNet code
#: (also in DPFM) uses 1e-6, ULRSSM's copy (also in DeepShapeMatchingKit, EchoMatch) 1e-12.
#: On a unit-area mesh of 5,000 vertices a face normal's raw length (twice its area) is
#: about 1e-5 to 1e-4, so 1e-6 makes small faces weigh noticeably less.
NORMALIZE_EPS = {"diffusionnet": 1e-6, "ulrssm": 1e-12}
CONSTRUCTIONS = ("geofeat", *NORMALIZE_EPS)
#: A normal candidate axis is rejected for the tangent X axis when ``|n . axis|`` reaches this.
_AXIS_ALIGNMENT_LIMIT = 0.9
_CACHE_SIZE = 8


@dataclass(frozen=True, eq=False)
class SurfaceOperators:
    """Everything DiffusionNet needs about one shape, as float32 torch tensors on one device.

    Attributes
    ----------
    mass : torch.Tensor, shape (V,), float32
        Lumped vertex areas.
    evals : torch.Tensor, shape (k,), float32
        Laplace-Beltrami eigenvalues, ascending, clipped at zero.
    evecs : torch.Tensor, shape (V, k), float32
        Eigenvectors, orthonormal for the mass.
    grad_x, grad_y : torch.Tensor, sparse COO, shape (V, V), float32
        ``grad_x @ f`` and ``grad_y @ f`` are the components of the tangent gradient of a
        per-vertex function ``f`` along ``frames[:, 0]`` and ``frames[:, 1]``.
    frames : torch.Tensor, shape (V, 3, 3), float32
        Per-vertex orthonormal frames; rows are the tangent axes ``X``, ``Y`` and the normal.
    faces : torch.Tensor, shape (F, 3), int64, or None
        Triangles (None for a point cloud).
    edges : torch.Tensor, shape (E, 2), int64, or None
        Undirected mesh edges, each once with the smaller index first (None for a point cloud).

    Notes
    -----
    Instances returned by `surface_operators` are shared through its cache: never change
    their tensors in place.
    """

    mass: torch.Tensor
    evals: torch.Tensor
    evecs: torch.Tensor
    grad_x: torch.Tensor
    grad_y: torch.Tensor
    frames: torch.Tensor
    faces: torch.Tensor | None = None
    edges: torch.Tensor | None = None

    @property
    def n_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.mass.shape[0])

    @property
    def k(self) -> int:
        """Number of eigenpairs."""
        return int(self.evals.shape[0])

    @property
    def device(self) -> torch.device:
        """Device holding the tensors."""
        return self.mass.device

    @cached_property
    def gradient_transposes(self) -> tuple[torch.Tensor, torch.Tensor]:
        """``grad_x.T`` and ``grad_y.T``, coalesced sparse COO (V, V), on the device of the record.

        Made once per record, on first use, from ``grad_x`` and ``grad_y`` themselves (a record
        made by ``dataclasses.replace`` or `to` makes its own). The backward pass of
        `geofeat.adapters.blocks.diffusion_net.tangent_gradients` multiplies by them; torch's own
        backward would transpose and coalesce again at every step, which on CUDA sorts the
        entries and waits for the device.
        """
        return self.grad_x.t().coalesce(), self.grad_y.t().coalesce()

    def to(self, device: str | torch.device) -> SurfaceOperators:
        """The same operators on another device.

        Parameters
        ----------
        device : str or torch.device
            Target device (``"auto"``: CUDA when available).

        Returns
        -------
        SurfaceOperators
            A new record (``self`` when the tensors are already there).
        """
        target = resolve_device(device)
        if _same_device(self.device, target):
            return self
        moved = {f.name: None if getattr(self, f.name) is None else getattr(self, f.name).to(target) for f in fields(self)}
        return replace(self, **moved)


def _same_device(a: torch.device, b: torch.device) -> bool:
    if a.type != b.type:
        return False
    if a.type != "cuda":
        return True
    import torch

    current = torch.cuda.current_device()
    return (a.index if a.index is not None else current) == (b.index if b.index is not None else current)


_operator_cache: LRUCache[tuple, SurfaceOperators] = LRUCache(lambda: _CACHE_SIZE)


def surface_operators(
    mesh: Mesh, k: int = 128, laplacian_kind: str = "robust", cache: bool = True, construction: str = "geofeat"
) -> SurfaceOperators:
    """Build (or fetch from the in-memory cache) the DiffusionNet operators of a shape.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh, or point cloud (``faces=None``).
    k : int
        Number of Laplace-Beltrami eigenpairs, ``1 <= k < V``.
    laplacian_kind : {"robust", "cotan"}
        Discretisation of the Laplacian, see `geofeat.geometry.laplacian`.
    cache : bool
        Reuse the operators built before for the same mesh content, ``k``, Laplacian and
        construction (a small LRU cache in memory).
    construction : {"geofeat", "diffusionnet", "ulrssm"}
        ``"geofeat"``: vertex normals weighted by face area and a gradient fit regularised
        relative to the local edge lengths (scale-free). ``"diffusionnet"`` (the original
        DiffusionNet code, as in DPFM) and ``"ulrssm"`` (ULRSSM's and
        DeepShapeMatchingKit's copy): the choices the released models were trained with:
        normals = normalised sum of the normalised normals of the adjacent faces, and an
        absolute regularisation `REFERENCE_GRADIENT_REGULARIZATION` (so the operators
        depend on the scale of the shape: use them on unit-area shapes, as the references
        do); the two differ in `NORMALIZE_EPS`. Use ``laplacian_kind="cotan"`` with them
        on meshes. On a point cloud (``laplacian_kind="robust"``, the point-cloud
        Laplacian, as the reference code builds it) their normals are those of
        `neighborhood_normals`, as in the reference code; ``"geofeat"`` orients them away
        from the centroid (`geofeat.geometry.normals.vertex_normals`).

    Returns
    -------
    SurfaceOperators
        Float32 CPU tensors: mass (V,), evals (k,), evecs (V, k), sparse grad_x and
        grad_y (V, V), frames (V, 3, 3), faces (F, 3) and edges (E, 2).

    Raises
    ------
    geofeat.SpectralError
        Bad ``k`` or a failed eigensolve.
    geofeat.MeshError
        Unknown Laplacian kind or construction, or a point cloud with ``kind="cotan"``.
    """
    if construction not in CONSTRUCTIONS:
        raise MeshError(f"unknown operator construction {construction!r}; expected one of {CONSTRUCTIONS}.")
    key = (mesh.hash, int(k) if isinstance(k, (int, np.integer)) else k, laplacian_kind, construction)
    if cache and (ops := _operator_cache.get(key)) is not None:
        return ops
    basis = spectral_basis(mesh, k, laplacian_kind=laplacian_kind)
    frames, (grad_x, grad_y) = _frames_and_gradients(mesh, construction)
    edges = None if mesh.faces is None else unique_edges(mesh.faces)
    ops = SurfaceOperators(
        mass=_dense32(basis.mass),
        evals=_dense32(np.clip(basis.evals, 0.0, None)),
        evecs=_dense32(basis.evecs),
        grad_x=_sparse32(grad_x),
        grad_y=_sparse32(grad_y),
        frames=_dense32(frames),
        faces=None if mesh.faces is None else _int64(mesh.faces),
        edges=None if edges is None else _int64(edges),
    )
    if cache:
        _operator_cache.put(key, ops)
    return ops


def clear_operator_cache() -> None:
    """Forget every cached `SurfaceOperators` (the spectral-basis cache is left alone)."""
    _operator_cache.clear()


def _dense32(array: np.ndarray) -> torch.Tensor:
    import torch

    return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def _int64(array: np.ndarray) -> torch.Tensor:
    import torch

    return torch.from_numpy(np.array(array, dtype=np.int64))


def _sparse32(matrix: sp.spmatrix) -> torch.Tensor:
    import torch

    coo = sp.coo_matrix(matrix)
    indices = torch.from_numpy(np.vstack((coo.row, coo.col)).astype(np.int64))
    values = torch.from_numpy(coo.data.astype(np.float32))
    return torch.sparse_coo_tensor(indices, values, coo.shape, check_invariants=True).coalesce()


# ----------------------------------------------------------------------------- geometry (float64)


def tangent_frames(normals: np.ndarray, normalize_eps: float = 0.0) -> np.ndarray:
    """An orthonormal tangent basis at every vertex.

    Parameters
    ----------
    normals : numpy.ndarray, shape (V, 3)
        Unit normals.
    normalize_eps : float
        The projected axis ``a`` becomes ``a / (|a| + normalize_eps)`` (the DiffusionNet
        reference code adds 1e-6 or 1e-12; 0 makes it exactly unit).

    Returns
    -------
    numpy.ndarray, shape (V, 3, 3), float64
        ``frames[i] = [X_i, Y_i, n_i]`` (rows): ``X_i`` is the x axis (the y axis where the
        normal is nearly parallel to x) projected onto the tangent plane and normalised,
        ``Y_i = n_i x X_i``, so ``(X, Y, n)`` is right-handed.
    """
    normals = np.asarray(normals, dtype=np.float64)
    axis = np.zeros_like(normals)
    near_x = np.abs(normals[:, 0]) >= _AXIS_ALIGNMENT_LIMIT
    axis[~near_x, 0] = 1.0
    axis[near_x, 1] = 1.0
    basis_x = axis - normals * np.einsum("vd,vd->v", axis, normals)[:, None]
    basis_x /= np.linalg.norm(basis_x, axis=1, keepdims=True) + normalize_eps
    basis_y = np.cross(normals, basis_x)
    return np.stack((basis_x, basis_y, normals), axis=1)


def gradient_matrices(
    mesh: Mesh, frames: np.ndarray, absolute_regularization: float | None = None
) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    """Least-squares tangent gradient operators.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh (neighbours: the vertices sharing an edge) or point cloud
        (neighbours: the `N_NEIGHBORS_CLOUD` nearest points).
    frames : numpy.ndarray, shape (V, 3, 3)
        Per-vertex frames from `tangent_frames`.
    absolute_regularization : float, optional
        Use this ``r_i`` at every vertex (the DiffusionNet reference code uses 1e-5)
        instead of the scale-free default below.

    Returns
    -------
    grad_x, grad_y : scipy.sparse.csr_matrix, shape (V, V), float64
        For a per-vertex function ``f``, ``(grad_x @ f)[i], (grad_y @ f)[i]`` is the vector
        ``g`` of the tangent plane of vertex ``i`` (in its ``X, Y`` axes) minimising
        ``sum_j (e_ij . g - (f_j - f_i))^2 + r_i |g|^2`` over the neighbours ``j``, with
        ``e_ij`` the edge vector ``p_j - p_i`` projected onto the ``X, Y`` axes and ``r_i``
        `GRADIENT_REGULARIZATION` times the mean of ``|e_ij|^2``. Exact for functions that
        are linear in the tangent plane (up to the regularisation). Rows of vertices without
        neighbours are zero.
    """
    verts = mesh.verts
    n = len(verts)
    tails, tips = _directed_neighbors(mesh)
    edge_vecs = verts[tips] - verts[tails]
    tangent = np.stack(
        (
            np.einsum("ed,ed->e", edge_vecs, frames[tails, 0]),
            np.einsum("ed,ed->e", edge_vecs, frames[tails, 1]),
        ),
        axis=1,
    )  # (E, 2)
    # per-vertex normal equations [[a, b], [b, c]] of the 2x2 least-squares problem
    a = np.bincount(tails, weights=tangent[:, 0] ** 2, minlength=n)
    b = np.bincount(tails, weights=tangent[:, 0] * tangent[:, 1], minlength=n)
    c = np.bincount(tails, weights=tangent[:, 1] ** 2, minlength=n)
    count = np.bincount(tails, minlength=n)
    if absolute_regularization is None:
        reg = GRADIENT_REGULARIZATION * (a + c) / np.maximum(count, 1)
    else:
        reg = np.full(n, float(absolute_regularization))
    a, c = a + reg, c + reg
    det = a * c - b * b
    inv_det = np.divide(1.0, det, out=np.zeros(n), where=det > 0)
    # coefficient of (f_j - f_i) in the fitted gradient at i: inverse normal matrix times e_ij
    coef_x = inv_det[tails] * (c[tails] * tangent[:, 0] - b[tails] * tangent[:, 1])
    coef_y = inv_det[tails] * (a[tails] * tangent[:, 1] - b[tails] * tangent[:, 0])
    rows = np.concatenate((tails, tails))
    cols = np.concatenate((tips, tails))
    grad_x = sp.csr_matrix((np.concatenate((coef_x, -coef_x)), (rows, cols)), shape=(n, n))
    grad_y = sp.csr_matrix((np.concatenate((coef_y, -coef_y)), (rows, cols)), shape=(n, n))
    return grad_x, grad_y


def _frames_and_gradients(mesh: Mesh, construction: str) -> tuple[np.ndarray, tuple[sp.csr_matrix, sp.csr_matrix]]:
    """Tangent frames (V, 3, 3) and the gradient matrices of ``construction`` (see `surface_operators`)."""
    eps = NORMALIZE_EPS.get(construction)
    if eps is None:
        frames = tangent_frames(vertex_normals(mesh))
        return frames, gradient_matrices(mesh, frames)
    if mesh.faces is None:
        normals = neighborhood_normals(mesh.verts, cloud_neighbors(mesh))
    else:
        normals = vertex_normals(mesh, face_weights="unit", normalize_eps=eps)
    frames = tangent_frames(normals, normalize_eps=eps)
    return frames, gradient_matrices(mesh, frames, REFERENCE_GRADIENT_REGULARIZATION)


def cloud_neighbors(mesh: Mesh, n_neighbors: int = N_NEIGHBORS_CLOUD) -> np.ndarray:
    """The nearest other points of every point of a cloud, nearest first.

    Parameters
    ----------
    mesh : Mesh
        Point cloud (faces are ignored) of at least 3 points.
    n_neighbors : int
        How many (fewer when the cloud has no more other points).

    Returns
    -------
    numpy.ndarray, shape (V, min(n_neighbors, V - 1)), int64
        Row ``i``: the ``n_neighbors + 1`` nearest points of point ``i`` without ``i``
        itself, or without the farthest of them where ``i`` is not among them (more
        coincident copies of it than neighbours), as the DiffusionNet reference code does.

    Raises
    ------
    MeshError
        Fewer than 3 points.
    """
    n = mesh.n_vertices
    n_query = min(n_neighbors + 1, n)
    if n_query < 3:
        raise MeshError(f"point cloud {mesh.name!r} has {n} points; at least 3 are needed for tangent gradients.")
    _, neighbors = cKDTree(mesh.verts).query(mesh.verts, k=n_query)
    keep = neighbors != np.arange(n)[:, None]
    keep[keep.all(axis=1), -1] = False
    return neighbors[keep].reshape(n, n_query - 1)


def neighborhood_normals(verts: np.ndarray, neighbors: np.ndarray) -> np.ndarray:
    """Normals of a point cloud as the DiffusionNet reference code computes them.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
    neighbors : numpy.ndarray of int, shape (V, K)
        Neighbours of every point (`cloud_neighbors`).

    Returns
    -------
    numpy.ndarray, shape (V, 3), float64
        The right singular vector of the smallest singular value of the offsets from each
        point to its neighbours (not centred on their mean): the normal of the plane
        through the point closest to its neighbours. Its sign is the one the SVD returns
        (numpy's LAPACK), like the reference's, so it is not oriented.
    """
    offsets = verts[neighbors] - verts[:, None, :]
    normals = np.linalg.svd(offsets, full_matrices=False)[2][:, 2, :]
    return normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _directed_neighbors(mesh: Mesh) -> tuple[np.ndarray, np.ndarray]:
    """(tail, tip) index arrays of every directed neighbour pair, no self pairs."""
    if mesh.faces is not None:
        edges = unique_edges(mesh.faces)
        return np.concatenate((edges[:, 0], edges[:, 1])), np.concatenate((edges[:, 1], edges[:, 0]))
    neighbors = cloud_neighbors(mesh)
    return np.repeat(np.arange(mesh.n_vertices), neighbors.shape[1]), neighbors.ravel()
