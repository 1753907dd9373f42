"""Laplace-Beltrami eigenpairs with a robust solver chain, cached by mesh content."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg as la
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from geofeat.checks import check_integer
from geofeat.errors import SpectralError
from geofeat.geometry.geodesic_memory import available_memory
from geofeat.geometry.lanczos import largest_eigenpairs
from geofeat.geometry.laplacian import laplacian
from geofeat.mesh import Mesh
from geofeat.runtime.progress import progress_bar
from geofeat.storage.lru import LRUCache
from geofeat.storage.sizes import format_size

log = logging.getLogger(__name__)

#: Largest number of vertices for which the dense fallback solver is tried.
DENSE_MAX_VERTICES = 8000
#: Below this many vertices the dense solver is used directly (cheaper than ARPACK).
DENSE_DIRECT_VERTICES = 400
#: Requests of more than this fraction of the spectrum go to the dense solver directly
#: (ARPACK would need a subspace of about the whole space, and fail or crawl).
SPARSE_MAX_FRACTION = 0.25
#: Bound on ARPACK's restarts in the first sparse attempt (twice that in the second).
SPARSE_MAXITER = 300
#: An eigenvalue times the total area below this counts as zero (non-zero modes of a
#: surface are of order one and above on this scale; rounding noise is about 1e-10).
ZERO_EIGENVALUE_TOL = 1e-6
#: Work bound of one sparse attempt: at most this many linear solves per Lanczos vector
#: (``ncv``); an attempt that has not converged by then is abandoned as failed. A converging
#: solve takes about 1.3 ``ncv`` (323 solves for k=128 on 5,000 and on 200,000 vertices).
#: Counted, not timed, so the outcome never depends on the machine or its load.
SPARSE_SOLVES_PER_VECTOR = 5
#: A sparse solve that runs longer than this shows a progress bar (linear solves done).
PROGRESS_AFTER_SECONDS = 5.0
#: Meshes from this many vertices try Lanczos with partial reorthogonalisation before ARPACK.
#: Medians of 5 solves (k=128; 40 on the smallest), same process, AMD EPYC 2 cores: on 642
#: vertices 22 ms against ARPACK's 15-90 ms; Lanczos faster on 2,562 (124-126 against
#: 142-146 ms), 5,000 (153-156 against 214-332 ms), 9,237 (218-226 against 477-506 ms) and
#: 20,001 vertices (545-605 against 1,222-1,393 ms).
LANCZOS_FROM_VERTICES = 2_000
#: Bound on the steps of the Lanczos attempt (partial reorthogonalisation,
#: `lanczos_steps`): ``LANCZOS_STEPS_PER_EIGENPAIR * k + 64``. It converges in about ``2.4 k``
#: (312 steps for k=128 on 20,000 vertices); its basis grows to that many vectors.
LANCZOS_STEPS_PER_EIGENPAIR = 3
#: The eigenvalues of the Lanczos attempt are counted below their largest times ``1 + COUNT_MARGIN``;
#: a count other than ``k`` (a mode missed, or eigenvalues this close straddling ``k``) hands over to ARPACK.
COUNT_MARGIN = 1e-8
#: Lanczos vectors beyond ``k`` in ARPACK's attempt (`first_subspace`): ``k + max(SUBSPACE_EXTRA, k // 4)``.
#: The linear solves barely depend on it (about 320 for k=128 from 5,000 to 200,000 vertices
#: with 160 or 257 vectors), while ARPACK's orthogonalisation and memory grow with its square.
SUBSPACE_EXTRA = 32
#: Sparse factorisation of the shifted Laplacian: "auto" (CHOLMOD where scikit-sparse is
#: installed, SuperLU otherwise) or "superlu".
FACTORIZATION = "auto"
#: Bytes per vertex of the sparse factorisation and the solver's other work arrays, on top
#: of the Lanczos vectors and the eigenvectors (measured: about 100 on meshes of 20,000 to
#: 200,000 vertices; this leaves room for more fill on other meshes).
FACTOR_BYTES_PER_VERTEX = 400
#: Meshes with at least this many vertices log the memory the eigensolve will take.
LOG_MEMORY_FROM_VERTICES = 100_000
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
    n_zero : int
        How many of the eigenvalues are zero (constant modes): the number of connected
        components of the solved vertices, or more where an eigenvalue times the total
        area is below `ZERO_EIGENVALUE_TOL` (scale-free), at most ``k``. Eigenvalues of
        zero modes are rounding noise (about 1e-10); use this count, not their values.
    """

    evals: np.ndarray
    evecs: np.ndarray
    mass: np.ndarray
    n_zero: int = 0

    @property
    def k(self) -> int:
        """Number of eigenpairs."""
        return int(self.evals.shape[0])


_basis_cache: LRUCache[tuple, SpectralBasis] = LRUCache(lambda: _CACHE_SIZE)


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
    The solve is in float64 and scale-free (see `solve_eigenpairs`): scaling a mesh by
    ``s`` divides the eigenvalues by ``s^2`` and the eigenvectors by ``s``, exactly up to
    rounding. Vertices without mass (unreferenced by any face, or only by faces of zero
    area) get the eigenvector values of their nearest vertex with mass.
    """
    k = check_integer(k, "k", low=1, error=SpectralError, expected="a positive integer number of eigenpairs")
    key = (mesh.hash, int(k), laplacian_kind)
    if cache and (basis := _basis_cache.get(key)) is not None:
        return basis
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
    n_components = connected_components(abs(stiffness) + sp.identity(n_active), directed=False)[0]
    by_value = int(np.count_nonzero(np.abs(evals) * mass.sum() < ZERO_EIGENVALUE_TOL))
    basis = SpectralBasis(evals, evecs, mass, n_zero=min(int(k), max(int(n_components), by_value)))
    if cache:
        _basis_cache.put(key, basis)
    return basis


def clear_basis_cache() -> None:
    """Forget every cached spectral basis."""
    _basis_cache.clear()


def mass_normalize(features: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """Scale every channel to unit mass-weighted L2 norm (channels of norm zero are left as they are).

    Parameters
    ----------
    features : numpy.ndarray, shape (V, C)
    mass : numpy.ndarray, shape (V,)
        Vertex areas (`SpectralBasis.mass`).

    Returns
    -------
    numpy.ndarray, shape (V, C)
        ``features[:, c] / sqrt(sum_i mass_i features[i, c]^2)``.
    """
    norms = np.sqrt(mass @ np.square(features))
    return features / np.where(norms > 0, norms, 1.0)


def solve_eigenpairs(
    stiffness: sp.spmatrix, mass: np.ndarray, k: int, name: str = "", progress: bool = True
) -> tuple[np.ndarray, np.ndarray]:
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
        Shape name used in log messages and the progress bar.
    progress : bool
        Show a progress bar (linear solves done) when a sparse solve runs for more than
        `PROGRESS_AFTER_SECONDS`.

    Returns
    -------
    evals : numpy.ndarray, shape (k,), float64
    evecs : numpy.ndarray, shape (n, k), float64, mass-orthonormal

    Notes
    -----
    The problem is solved scale-free: the mass is divided by its total (the shape's area),
    which makes the spectrum of a cotangent or robust Laplacian independent of the size
    of the shape, and the eigenpairs are scaled back at the end. Small meshes and requests
    of more than `SPARSE_MAX_FRACTION` of the spectrum go to the dense solver directly.
    Otherwise the shifted problem is factorised (`_factorize`: CHOLMOD where scikit-sparse
    is installed, SuperLU otherwise) and solved in shift-invert mode by a sequence of
    attempts. From `LANCZOS_FROM_VERTICES` vertices the first is Lanczos with partial
    reorthogonalisation (`geofeat.geometry.lanczos`), whose eigenvalue count is then
    confirmed by Sylvester's law of inertia (a factorisation shifted just above the largest
    eigenvalue found has exactly ``k`` negative pivots). Then ARPACK with
    ``k + max(32, k // 4)`` Lanczos vectors; ARPACK with a larger shift and subspace; then
    the dense solver for meshes up to `DENSE_MAX_VERTICES` vertices. Every attempt has a
    deterministic start vector and a bounded number of linear solves. Before a sparse solve
    the memory it needs (`eigensolve_memory`) is compared with the memory available, and a
    solve that would not fit raises `SpectralError` instead of starting.
    """
    n = mass.shape[0]
    total = float(mass.sum())
    if not (np.isfinite(total) and total > 0 and (mass > 0).all()):
        raise SpectralError(f"{name!r}: the mass must be finite and positive at every solved vertex (total {total!r}).")
    unit_mass = mass / total
    stiffness = sp.csc_matrix(stiffness, dtype=np.float64)
    stiffness = ((stiffness + stiffness.T) * 0.5).tocsc()
    if n <= DENSE_DIRECT_VERTICES or k > SPARSE_MAX_FRACTION * n:
        if n > DENSE_MAX_VERTICES:
            raise SpectralError(
                f"{name!r}: k={k} eigenpairs of {n} vertices is more than {SPARSE_MAX_FRACTION:.0%} of the spectrum, "
                f"which needs the dense solver, and the mesh is larger than its limit ({DENSE_MAX_VERTICES} vertices). "
                "Lower k, or decimate the mesh."
            )
        evals, evecs = _dense(stiffness, unit_mass, k)
    else:
        _check_memory(n, k, name)
        evals, evecs = _sparse_with_fallbacks(stiffness, unit_mass, k, name, progress)
    order = np.argsort(evals)
    return evals[order] / total, evecs[:, order] / np.sqrt(total)


def first_subspace(n: int, k: int) -> int:
    """Lanczos vectors of the first sparse attempt for ``k`` of ``n`` eigenpairs."""
    return min(n - 1, max(k + max(SUBSPACE_EXTRA, k // 4), 20))


def lanczos_steps(n: int, k: int) -> int:
    """Bound on the steps (and basis vectors) of the Lanczos attempt for ``k`` of ``n`` eigenpairs."""
    return min(n, LANCZOS_STEPS_PER_EIGENPAIR * k + 64)


def eigensolve_memory(n: int, k: int) -> int:
    """Estimated peak bytes of the sparse eigensolve of ``n`` vertices and ``k`` eigenpairs.

    The Lanczos basis (from `LANCZOS_FROM_VERTICES` vertices `lanczos_steps` vectors, an
    upper bound: it stops growing when the solve converges, at about ``2.4 k``; ARPACK's
    `first_subspace` below), twice the ``(n, k)`` eigenvectors and `FACTOR_BYTES_PER_VERTEX`
    for the factorisation: about 1.2 GB for 200,000 vertices and 6.0 GB for 1,000,000 at
    ``k = 128``.
    """
    basis = lanczos_steps(n, k) + 1 if n >= LANCZOS_FROM_VERTICES else first_subspace(n, k)
    return 8 * n * (basis + 2 * k) + FACTOR_BYTES_PER_VERTEX * n


def _check_memory(n: int, k: int, name: str) -> None:
    """Raise `SpectralError` before a solve that would not fit in the memory available now."""
    need = eigensolve_memory(n, k)
    available = available_memory()
    if n >= LOG_MEMORY_FROM_VERTICES:
        room = "unknown" if available is None else format_size(available)
        log.info("eigenpairs of %r (%d vertices, k=%d) will take about %s (available: %s)", name, n, k, format_size(need), room)
    if available is not None and need > available:
        raise SpectralError(
            f"{name!r}: {k} eigenpairs of {n} vertices need about {format_size(need)} of memory, and "
            f"{format_size(available)} is available. Decimate the mesh, lower k (or n_eig), or free memory."
        )


class _OutOfBudget(Exception):
    """A sparse attempt used up its linear solves (`SPARSE_SOLVES_PER_VECTOR`) without converging."""


def _shift_invert(
    stiffness: sp.csc_matrix, mass: np.ndarray, k: int, sigma: float, method: str, steps: int, maxiter: int, bar
) -> tuple[np.ndarray, np.ndarray]:
    """Shift-invert on the standard form of the problem, counting the linear solves on ``bar``.

    The lumped mass is diagonal, so ``L phi = lambda M phi`` is ``A psi = lambda psi`` with
    ``A = M^-1/2 L M^-1/2`` and ``phi = M^-1/2 psi``: no mass products, about 15% less time
    than the generalised form for the same eigenpairs up to rounding, also on meshes with
    nearly degenerate faces (the mass sums to one here, so the scaling does not depend on
    the size of the shape). ``method`` is "lanczos" (`largest_eigenpairs`, at most
    ``steps`` solves, its count of eigenvalues checked by `_count_below`) or "arpack"
    (``steps`` Lanczos vectors, at most ``maxiter`` restarts).
    """
    n = stiffness.shape[0]
    inv_sqrt_mass = 1.0 / np.sqrt(mass)
    scaling = sp.diags(inv_sqrt_mass)
    standard = (scaling @ stiffness @ scaling).tocsc()
    identity = sp.identity(n, format="csc")
    factor = _factorize((standard - sigma * identity).tocsc())

    budget = SPARSE_SOLVES_PER_VECTOR * steps
    done = 0

    def solve(x: np.ndarray) -> np.ndarray:
        nonlocal done
        if done >= budget:
            raise _OutOfBudget(f"no convergence within {budget} linear solves")
        done += 1
        bar.update(1)
        return factor(x)

    if method == "lanczos":
        theta, vecs = largest_eigenpairs(solve, n, k, max_steps=steps)
        evals = sigma + 1.0 / theta
        limit = float(evals.max()) * (1.0 + COUNT_MARGIN)
        below = _count_below((standard - limit * identity).tocsc())
        if below != k:
            raise SpectralError(
                f"{below} eigenvalues lie below the largest of the {k} found, {limit:.6g} (a mode missed, or a "
                "cluster of nearly equal eigenvalues straddling k)"
            )
        return evals, vecs * inv_sqrt_mass[:, None]
    op_inv = sla.LinearOperator((n, n), matvec=solve, dtype=np.float64)
    start = np.random.default_rng(0).standard_normal(n)
    evals, vecs = sla.eigsh(standard, k=k, sigma=sigma, which="LM", OPinv=op_inv, v0=start, ncv=steps, maxiter=maxiter)
    return evals, vecs * inv_sqrt_mass[:, None]


def cholmod_available() -> bool:
    """Whether the sparse Cholesky factorisation of SuiteSparse (``scikit-sparse``) can be imported."""
    try:
        import sksparse.cholmod  # noqa: F401
    except ImportError:
        return False
    return True


def _factorize(shifted: sp.csc_matrix):
    """A solver for ``shifted x = b`` (symmetric positive definite), as a function of ``b``.

    CHOLMOD's simplicial LDL' with the AMD ordering where scikit-sparse is installed (its
    solves take about half the time of SuperLU's on these matrices: 0.43 against 0.93 ms on
    20,000 vertices); SuperLU in symmetric mode otherwise, or where CHOLMOD finds the matrix
    not positive definite in floating point. Both solve to rounding.
    """
    factor = _cholmod_ldl(shifted)
    return factor.solve_A if factor is not None else _superlu_ldu(shifted).solve


def _count_below(shifted: sp.csc_matrix) -> int:
    """How many eigenvalues of the symmetric ``shifted`` are negative: its negative LDL' pivots (Sylvester's law of inertia).

    CHOLMOD's simplicial LDL' where scikit-sparse is installed, SuperLU without pivoting
    (whose ``U`` has the pivots on its diagonal) otherwise.
    """
    factor = _cholmod_ldl(shifted)
    pivots = factor.D() if factor is not None else _superlu_ldu(shifted).U.diagonal()
    return int(np.count_nonzero(pivots < 0))


def _cholmod_ldl(shifted: sp.csc_matrix):
    """CHOLMOD's simplicial LDL' (AMD ordering) of symmetric ``shifted``, or None.

    None where `FACTORIZATION` is "superlu", scikit-sparse is not installed, or CHOLMOD
    cannot factorise the matrix.
    """
    if FACTORIZATION != "auto" or not cholmod_available():
        return None
    from sksparse.cholmod import CholmodError, cholesky

    try:
        return cholesky(shifted, mode="simplicial", ordering_method="amd")
    except CholmodError as err:
        log.debug("CHOLMOD could not factorise the shifted Laplacian (%s); using SuperLU", err)
        return None


def _superlu_ldu(shifted: sp.csc_matrix) -> sla.SuperLU:
    """SuperLU of symmetric ``shifted`` in symmetric mode without pivoting: ``U``'s diagonal holds the LDL' pivots."""
    return sla.splu(shifted, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def _sparse_with_fallbacks(
    stiffness: sp.csc_matrix, mass: np.ndarray, k: int, name: str, progress: bool
) -> tuple[np.ndarray, np.ndarray]:
    n = stiffness.shape[0]
    scale = float(stiffness.diagonal().sum())  # sum of diag(L) / sum(mass), the mass summing to one
    lanczos = [("Lanczos, sigma=-1e-6*scale", -1e-6 * scale, "lanczos", lanczos_steps(n, k), 0)]
    attempts = (lanczos if n >= LANCZOS_FROM_VERTICES else []) + [
        ("shift-invert, sigma=-1e-6*scale", -1e-6 * scale, "arpack", first_subspace(n, k), SPARSE_MAXITER),
        (
            "shift-invert, larger shift sigma=-1e-3*scale and subspace",
            -1e-3 * scale,
            "arpack",
            min(n - 1, 3 * k + 32),
            2 * SPARSE_MAXITER,
        ),
    ]
    failures = []
    for label, sigma, method, steps, maxiter in attempts:
        with progress_bar(
            desc=f"eigenpairs of {name or 'mesh'} (k={k}, {n} vertices)",
            unit="solve",
            delay=PROGRESS_AFTER_SECONDS,
            show=progress,
            leave=False,
        ) as bar:
            try:
                evals, vecs = _shift_invert(stiffness, mass, k, sigma, method, steps, maxiter, bar)
            except (SpectralError, RuntimeError, sla.ArpackError, ValueError, _OutOfBudget) as err:
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
        return _dense(stiffness, mass, k)
    raise SpectralError(
        f"Laplacian eigenproblem of {name!r} ({n} vertices, k={k}) failed: "
        + "; ".join(failures)
        + f". The mesh is too large for the dense fallback (> {DENSE_MAX_VERTICES} vertices). "
        "What to try: repair the mesh (remove duplicated vertices, degenerate faces and isolated parts), use "
        "laplacian='robust' (sound on non-manifold and degenerate meshes), or lower k."
    )


def _dense(stiffness: sp.spmatrix, mass: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The first ``k`` eigenpairs of the generalised problem by LAPACK (``O(n^3)``, for small ``n``)."""
    try:
        return la.eigh(stiffness.toarray(), np.diag(mass), subset_by_index=[0, k - 1])
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
