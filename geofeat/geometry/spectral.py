"""Laplace-Beltrami eigenpairs with a robust solver chain, cached by mesh content."""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.spatial import cKDTree

from geofeat.errors import SpectralError
from geofeat.geometry.laplacian import laplacian
from geofeat.mesh import Mesh

log = logging.getLogger(__name__)

#: Largest number of vertices for which the dense fallback solver is tried.
DENSE_MAX_VERTICES = 8000
#: Below this many vertices the dense solver is used directly (cheaper than ARPACK).
DENSE_DIRECT_VERTICES = 400
_CACHE_SIZE = 8


@dataclass(frozen=True, eq=False)
class SpectralBasis:
    """The first ``k`` eigenpairs of the generalised problem ``L phi = lambda M phi``.

    Attributes
    ----------
    evals : numpy.ndarray, shape (k,), float64
        Eigenvalues in ascending order (the first is about zero on a connected mesh).
    evecs : numpy.ndarray, shape (V, k), float64
        Eigenvectors, orthonormal for the mass: ``evecs.T @ (mass[:, None] * evecs) = I``.
    mass : numpy.ndarray, shape (V,), float64
        Lumped vertex areas (zero on unreferenced vertices).
    """

    evals: np.ndarray
    evecs: np.ndarray
    mass: np.ndarray

    @property
    def k(self) -> int:
        """Number of eigenpairs."""
        return int(self.evals.shape[0])


_basis_cache: OrderedDict[tuple, SpectralBasis] = OrderedDict()
_basis_lock = threading.Lock()


def spectral_basis(mesh: Mesh, k: int = 128, laplacian_kind: str = "robust", cache: bool = True) -> SpectralBasis:
    """Compute (or fetch from the in-memory cache) the first ``k`` Laplace-Beltrami eigenpairs.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh or point cloud.
    k : int
        Number of eigenpairs, ``1 <= k < V`` (number of vertices with positive mass).
    laplacian_kind : {"robust", "cotan"}
        Discretisation, see `geofeat.geometry.laplacian`.
    cache : bool
        Reuse a basis computed before for the same mesh content, ``k`` and Laplacian.

    Returns
    -------
    SpectralBasis
        ``evals`` (k,), ``evecs`` (V, k) and ``mass`` (V,), all float64.

    Notes
    -----
    The solve is in float64, in the standard form ``M^-1/2 L M^-1/2`` (the mass is
    diagonal) by ARPACK in shift-invert mode with a deterministic start vector. When it
    fails, the solver retries with a larger shift and more iterations, then falls back to
    a dense solver for meshes up to `DENSE_MAX_VERTICES` vertices, logging a warning
    that says what happened. Vertices without mass (unreferenced by any face) get the
    eigenvector values of their nearest vertex with mass.
    """
    if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1:
        raise SpectralError(f"k must be a positive integer number of eigenpairs; found {k!r}.")
    key = (mesh.hash, int(k), laplacian_kind)
    if cache:
        with _basis_lock:
            if key in _basis_cache:
                _basis_cache.move_to_end(key)
                return _basis_cache[key]
    lap = laplacian(mesh, kind=laplacian_kind)
    active = lap.mass > 0
    if mesh.faces is not None:
        referenced = np.zeros(mesh.n_vertices, dtype=bool)
        referenced[mesh.faces.ravel()] = True
        active &= referenced
    mass = np.where(active, lap.mass, 0.0)
    n_active = int(active.sum())
    if k >= n_active:
        raise SpectralError(
            f"k={k} eigenpairs requested for {mesh.name!r}, which has {n_active} vertices with positive mass; "
            f"k must be smaller than that. Lower k (or n_eig)."
        )
    stiffness = lap.stiffness
    if n_active < mesh.n_vertices:
        stiffness = stiffness[active][:, active]
    evals, evecs = solve_eigenpairs(stiffness, mass[active], int(k), name=mesh.name)
    if n_active < mesh.n_vertices:
        evecs = _fill_inactive(mesh.verts, active, evecs)
    evecs = np.ascontiguousarray(evecs)
    for array in (evals, evecs, mass):
        array.flags.writeable = False  # shared through the cache: nobody may change it in place
    basis = SpectralBasis(evals, evecs, mass)
    if cache:
        with _basis_lock:
            _basis_cache[key] = basis
            while len(_basis_cache) > _CACHE_SIZE:
                _basis_cache.popitem(last=False)
    return basis


def clear_basis_cache() -> None:
    """Forget every cached spectral basis."""
    with _basis_lock:
        _basis_cache.clear()


def solve_eigenpairs(stiffness: sp.spmatrix, mass: np.ndarray, k: int, name: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Smallest ``k`` eigenpairs of ``stiffness phi = lambda diag(mass) phi``.

    Parameters
    ----------
    stiffness : scipy.sparse matrix, shape (n, n)
        Symmetric positive semi-definite.
    mass : numpy.ndarray, shape (n,)
        Positive lumped mass.
    k : int
        Number of eigenpairs, ``k < n``.
    name : str
        Shape name used in log messages.

    Returns
    -------
    evals : numpy.ndarray, shape (k,), float64
    evecs : numpy.ndarray, shape (n, k), float64, mass-orthonormal
    """
    n = mass.shape[0]
    inv_sqrt_mass = 1.0 / np.sqrt(mass)
    scaling = sp.diags(inv_sqrt_mass)
    standard = sp.csc_matrix(scaling @ stiffness @ scaling)
    standard = (standard + standard.T) * 0.5
    if n <= DENSE_DIRECT_VERTICES:
        evals, vecs = _dense(standard, k)
    else:
        evals, vecs = _sparse_with_fallbacks(standard, k, name)
    order = np.argsort(evals)
    return evals[order], vecs[:, order] * inv_sqrt_mass[:, None]


def _shift_invert(standard: sp.csc_matrix, k: int, sigma: float, ncv: int, maxiter: int | None) -> tuple[np.ndarray, np.ndarray]:
    n = standard.shape[0]
    shifted = (standard - sigma * sp.identity(n, format="csc")).tocsc()
    lu = sla.splu(shifted, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
    op_inv = sla.LinearOperator((n, n), matvec=lu.solve, dtype=np.float64)
    start = np.random.default_rng(0).standard_normal(n)
    return sla.eigsh(standard, k=k, sigma=sigma, which="LM", OPinv=op_inv, v0=start, ncv=ncv, maxiter=maxiter)


def _sparse_with_fallbacks(standard: sp.csc_matrix, k: int, name: str) -> tuple[np.ndarray, np.ndarray]:
    n = standard.shape[0]
    scale = float(np.abs(standard.diagonal()).mean())
    attempts = [
        ("shift-invert, sigma=-1e-6*scale", -1e-6 * scale, min(n - 1, max(k + 32, int(1.6 * k) + 1)), None),
        (
            "shift-invert, larger shift sigma=-1e-3*scale and more iterations",
            -1e-3 * scale,
            min(n - 1, max(3 * k, k + 64)),
            50 * n,
        ),
    ]
    failures = []
    for label, sigma, ncv, maxiter in attempts:
        try:
            evals, vecs = _shift_invert(standard, k, sigma, ncv, maxiter)
        except (RuntimeError, sla.ArpackError, ValueError) as err:
            failures.append(f"{label}: {type(err).__name__}: {err}")
            log.warning("eigensolver on %r failed (%s); retrying", name, failures[-1])
            continue
        if np.isfinite(evals).all() and np.isfinite(vecs).all():
            if failures:
                log.warning("eigensolver on %r succeeded with %s", name, label)
            return evals, vecs
        failures.append(f"{label}: non-finite eigenpairs")
        log.warning("eigensolver on %r: %s; retrying", name, failures[-1])
    if n <= DENSE_MAX_VERTICES:
        log.warning("eigensolver on %r: sparse solves failed, using the dense solver on %d vertices (slow)", name, n)
        return _dense(standard, k)
    raise SpectralError(
        f"Laplacian eigenproblem of {name!r} ({n} vertices, k={k}) failed: "
        + "; ".join(failures)
        + f". The mesh is too large for the dense fallback (> {DENSE_MAX_VERTICES} vertices). "
        "Check it for duplicated or isolated parts, try laplacian='robust', or lower k."
    )


def _dense(standard: sp.spmatrix, k: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        return la.eigh(standard.toarray(), subset_by_index=[0, k - 1])
    except (la.LinAlgError, ValueError) as err:
        raise SpectralError(f"dense Laplacian eigensolver failed: {err}") from err


def _fill_inactive(verts: np.ndarray, active: np.ndarray, evecs: np.ndarray) -> np.ndarray:
    """Extend (n_active, k) eigenvectors to all V vertices by nearest active vertex."""
    active_idx = np.flatnonzero(active)
    _, nearest = cKDTree(verts[active_idx]).query(verts[~active])
    full = np.empty((len(verts), evecs.shape[1]), dtype=np.float64)
    full[active_idx] = evecs
    full[~active] = evecs[nearest]
    return full
