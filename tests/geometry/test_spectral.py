import logging
import time

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from shapes import bumpy, sphere

from geofeat import Mesh
from geofeat.errors import SpectralError
from geofeat.geometry import laplacian, spectral, spectral_basis
from geofeat.geometry.spectral import mass_normalize


def test_unit_sphere_spectrum_is_l_l_plus_1():
    """Eigenvalues of the unit sphere are l(l+1) with multiplicity 2l+1: 0, 2 (x3), 6 (x5)."""
    basis = spectral_basis(sphere(4), k=9, laplacian_kind="cotan", cache=False)
    expected = np.array([0, 2, 2, 2, 6, 6, 6, 6, 6], dtype=float)
    np.testing.assert_allclose(basis.evals, expected, atol=0.02)


@pytest.mark.parametrize("kind", ["robust", "cotan"])
def test_basis_is_mass_orthonormal_and_solves_the_problem(kind):
    mesh = bumpy(0, 3)
    basis = spectral_basis(mesh, k=30, laplacian_kind=kind, cache=False)
    lap = laplacian(mesh, kind)
    gram = basis.evecs.T @ (basis.mass[:, None] * basis.evecs)
    np.testing.assert_allclose(gram, np.eye(30), atol=1e-9)
    residual = lap.stiffness @ basis.evecs - basis.mass[:, None] * basis.evecs * basis.evals
    assert np.abs(residual).max() < 1e-8 * basis.evals.max()
    assert np.all(np.diff(basis.evals) >= 0) and abs(basis.evals[0]) < 1e-8


def test_cotan_spectrum_matches_pyfm_on_faust(faust_mesh):
    from pyFM.mesh import TriMesh

    reference = TriMesh(faust_mesh.verts, faust_mesh.faces).process(k=50)
    basis = spectral_basis(faust_mesh, k=50, laplacian_kind="cotan", cache=False)
    np.testing.assert_allclose(basis.evals[1:], reference.eigenvalues[1:], rtol=1e-8)


def test_robust_and_cotan_agree_on_a_clean_mesh(faust_mesh):
    robust = spectral_basis(faust_mesh, k=20, laplacian_kind="robust", cache=False)
    cotan = spectral_basis(faust_mesh, k=20, laplacian_kind="cotan", cache=False)
    np.testing.assert_allclose(robust.evals[1:], cotan.evals[1:], rtol=1e-3)


@pytest.mark.numerically_sensitive
def test_results_are_reproducible_to_the_bit():
    mesh = bumpy(2, 4)
    a = spectral_basis(mesh, k=40, cache=False)
    b = spectral_basis(mesh, k=40, cache=False)
    assert np.array_equal(a.evals, b.evals) and np.array_equal(a.evecs, b.evecs)


def test_in_memory_cache_by_content():
    mesh = bumpy(3, 3)
    first = spectral_basis(mesh, k=10)
    same_content = Mesh(mesh.verts.copy(), mesh.faces.copy(), name="copy")
    assert spectral_basis(same_content, k=10) is first
    assert spectral_basis(mesh, k=11) is not first
    spectral.clear_basis_cache()
    assert spectral_basis(mesh, k=10) is not first
    with pytest.raises(ValueError):
        first.evecs[0, 0] = 1.0  # cached arrays are read-only


def _without_lanczos(monkeypatch):
    """Make the Lanczos attempt fail, so that ARPACK's attempts run."""

    def failing_lanczos(*args, **kwargs):
        raise SpectralError("Lanczos failure (simulated)")

    monkeypatch.setattr(spectral, "largest_eigenpairs", failing_lanczos)


def test_fallback_chain_retries_then_uses_dense_solver(monkeypatch, caplog):
    mesh = bumpy(4, 3)
    reference = spectral_basis(mesh, k=12, cache=False)
    monkeypatch.setattr(spectral, "LANCZOS_FROM_VERTICES", 0)  # the whole chain: Lanczos, ARPACK twice, dense
    _without_lanczos(monkeypatch)
    calls = []

    def failing_eigsh(*args, **kwargs):
        calls.append(kwargs["sigma"])
        raise sla.ArpackNoConvergence("no convergence (simulated)", np.zeros(0), np.zeros((0, 0)))

    monkeypatch.setattr(spectral.sla, "eigsh", failing_eigsh)
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        basis = spectral_basis(mesh, k=12, cache=False)
    assert len(calls) == 2 and calls[1] < calls[0] < 0  # second try: a larger shift
    assert "Lanczos failure (simulated)" in caplog.text and "retrying" in caplog.text and "dense solver" in caplog.text
    np.testing.assert_allclose(basis.evals, reference.evals, atol=1e-8 * reference.evals.max())


def test_second_attempt_success_is_reported(monkeypatch, caplog):
    mesh = bumpy(5, 3)
    _without_lanczos(monkeypatch)
    real = spectral.sla.eigsh
    state = {"n": 0}

    def flaky(*args, **kwargs):
        state["n"] += 1
        if state["n"] == 1:
            raise RuntimeError("Factor is exactly singular (simulated)")
        return real(*args, **kwargs)

    monkeypatch.setattr(spectral.sla, "eigsh", flaky)
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        spectral_basis(mesh, k=8, cache=False)
    assert "succeeded with shift-invert, larger shift" in caplog.text


def test_large_mesh_without_dense_fallback_raises(monkeypatch):
    mesh = bumpy(6, 3)
    _without_lanczos(monkeypatch)

    def failing_eigsh(*args, **kwargs):
        raise RuntimeError("simulated failure")

    monkeypatch.setattr(spectral.sla, "eigsh", failing_eigsh)
    monkeypatch.setattr(spectral, "DENSE_MAX_VERTICES", 100)
    with pytest.raises(SpectralError, match="simulated failure"):
        spectral_basis(mesh, k=8, cache=False)


def test_bad_k():
    mesh = sphere(1)
    with pytest.raises(SpectralError, match="smaller than"):
        spectral_basis(mesh, k=mesh.n_vertices)
    with pytest.raises(SpectralError, match="positive integer"):
        spectral_basis(mesh, k=0)


def test_point_cloud_basis():
    cloud = Mesh(sphere(3).verts)
    basis = spectral_basis(cloud, k=9)
    assert basis.evecs.shape == (cloud.n_vertices, 9)
    ratios = basis.evals[1:] / basis.evals[1]
    np.testing.assert_allclose(ratios[:3], 1.0, atol=0.05)  # the 3-fold first eigenspace of a sphere
    with pytest.raises(Exception, match="point cloud"):
        laplacian(cloud, "cotan")


def test_unreferenced_vertex_gets_nearest_values():
    base = bumpy(7, 2)
    verts = np.vstack([base.verts, base.verts[:1] * 1.01])
    mesh = Mesh(verts, base.faces)
    basis = spectral_basis(mesh, k=10, cache=False)
    assert basis.mass[-1] == 0
    np.testing.assert_array_equal(basis.evecs[-1], basis.evecs[0])


@pytest.mark.parametrize("scale", [1e-12, 1e-11, 1e6])
def test_spectrum_is_scale_free(faust_mesh, scale):
    """Scaling by s divides eigenvalues by s^2 and eigenvectors by s (WKS was wrong from index 86 at 1e-12)."""
    ref = spectral_basis(faust_mesh, k=128, cache=False)
    scaled = spectral_basis(Mesh(faust_mesh.verts * scale, faust_mesh.faces), k=128, cache=False)
    np.testing.assert_allclose(scaled.evals[1:] * scale**2, ref.evals[1:], rtol=1e-7)
    inner = np.abs(np.einsum("vk,v,vk->k", scaled.evecs * scale, ref.mass, ref.evecs))
    np.testing.assert_allclose(inner[:100], 1.0, atol=1e-6)  # the last ones may mix within near-multiple eigenvalues


def test_zero_modes_come_from_the_components():
    """A mesh with as many components as eigenpairs has only zero modes, whatever the rounding noise says."""
    pieces = [sphere(1).verts + 5.0 * i for i in range(6)]
    faces = np.vstack([sphere(1).faces + i * len(pieces[0]) for i in range(6)])
    mesh = Mesh(np.vstack(pieces), faces)
    basis = spectral_basis(mesh, k=6, cache=False)
    assert basis.n_zero == 6
    assert spectral_basis(mesh, k=9, cache=False).n_zero == 6
    assert spectral_basis(sphere(3), k=9, cache=False).n_zero == 1


def test_large_fraction_of_the_spectrum_goes_dense_directly(monkeypatch):
    mesh = bumpy(1, 3)
    k = mesh.n_vertices // 2

    def no_sparse(*args, **kwargs):
        raise AssertionError("ARPACK must not be tried for half of the spectrum")

    monkeypatch.setattr(spectral.sla, "eigsh", no_sparse)
    basis = spectral_basis(mesh, k=k, cache=False)
    assert basis.k == k and np.all(np.diff(basis.evals) >= 0)


def test_every_sparse_attempt_is_bounded(monkeypatch):
    seen = []
    real = sla.eigsh

    def spy(*args, **kwargs):
        seen.append(kwargs.get("maxiter"))
        return real(*args, **kwargs)

    monkeypatch.setattr(spectral.sla, "eigsh", spy)
    monkeypatch.setattr(spectral, "LANCZOS_FROM_VERTICES", 0)
    spectral_basis(bumpy(4, 4), k=20, cache=False)
    assert not seen  # the Lanczos attempt answered
    steps = []
    real_lanczos = spectral.largest_eigenpairs

    def lanczos_spy(*args, **kwargs):
        steps.append(kwargs["max_steps"])
        return real_lanczos(*args, **kwargs)

    monkeypatch.setattr(spectral, "largest_eigenpairs", lanczos_spy)
    spectral_basis(bumpy(4, 4), k=20, cache=False)
    assert steps == [spectral.lanczos_steps(bumpy(4, 4).n_vertices, 20)] and steps[0] <= 3 * 20 + 64
    _without_lanczos(monkeypatch)
    spectral_basis(bumpy(4, 4), k=20, cache=False)
    assert seen and all(isinstance(m, int) and 0 < m <= 1000 for m in seen)


@pytest.mark.numerically_sensitive
def test_tiny_masses_of_degenerate_faces_do_not_break_the_solve(faust_mesh):
    """Zero-area faces give vertices tiny masses; the solve on unit total mass stays sound."""
    verts = faust_mesh.verts.copy()
    faces = faust_mesh.faces.copy()
    a, b, c = faces[0]
    verts[c] = verts[a] + 1e-9 * (verts[b] - verts[a])  # flatten one triangle almost to a segment
    mesh = Mesh(verts, faces)
    basis = spectral_basis(mesh, k=64, cache=False)
    ref = spectral_basis(faust_mesh, k=64, cache=False)
    np.testing.assert_allclose(basis.evals[1:20], ref.evals[1:20], rtol=1e-2)


def test_a_sparse_attempt_past_its_work_bound_is_abandoned(monkeypatch, caplog):
    monkeypatch.setattr(spectral, "SPARSE_SOLVES_PER_VECTOR", 0)
    mesh = bumpy(5, 3)
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        basis = spectral_basis(mesh, k=10, cache=False)  # both sparse attempts run out; the dense solver answers
    assert "no convergence within 0 linear solves" in caplog.text and "dense solver" in caplog.text
    assert basis.k == 10 and np.all(np.diff(basis.evals) >= 0)
    monkeypatch.setattr(spectral, "DENSE_MAX_VERTICES", 100)
    with pytest.raises(SpectralError, match="no convergence within 0 linear solves.*laplacian='robust'"):
        spectral_basis(mesh, k=10, cache=False)


def test_the_work_bound_does_not_depend_on_time(monkeypatch):
    """A slow machine gets the same eigenpairs: the bound counts linear solves, it never reads a clock."""
    mesh = bumpy(5, 3)
    ref = spectral_basis(mesh, k=10, cache=False)
    ticks = iter(range(0, 10**9, 3600))  # every clock reading an hour after the last one
    monkeypatch.setattr(time, "monotonic", lambda: float(next(ticks)))
    monkeypatch.setattr(time, "perf_counter", lambda: float(next(ticks)))
    slow = spectral_basis(mesh, k=10, cache=False)
    assert np.array_equal(slow.evals, ref.evals) and np.array_equal(slow.evecs, ref.evecs)


@pytest.mark.parametrize("squash", [1e-2, 1e-4, 1e-6])
def test_sparse_solve_is_accurate_near_degenerate_faces(squash):
    """The sparse solve (standard form M^-1/2 L M^-1/2) where tiny faces give tiny masses.

    Residuals and mass-orthonormality at rounding level; where LAPACK's dense solve of the
    generalised problem is itself accurate (the mildest squash), the same eigenpairs.
    """
    mesh = bumpy(0, 3)
    verts = mesh.verts.copy()
    ring = np.unique(mesh.faces[(mesh.faces == 0).any(axis=1)])
    verts[ring] = verts[0] + squash * (verts[ring] - verts[0])  # tiny faces and masses around vertex 0
    lap = laplacian(Mesh(verts, mesh.faces), kind="cotan")
    assert mesh.n_vertices > spectral.DENSE_DIRECT_VERTICES  # the sparse path
    evals, evecs = spectral.solve_eigenpairs(lap.stiffness, lap.mass, 40, progress=False)
    stiffness = sp.csc_matrix(lap.stiffness)
    residuals = stiffness @ evecs - lap.mass[:, None] * evecs * evals[None, :]
    scale = abs(stiffness).sum(axis=1).max() * np.linalg.norm(evecs, axis=0)
    assert (np.linalg.norm(residuals, axis=0) / scale).max() < 1e-12
    np.testing.assert_allclose(evecs.T @ (lap.mass[:, None] * evecs), np.eye(40), atol=1e-12)
    if squash == 1e-2:
        ref_evals, ref_evecs = spectral._dense(stiffness, lap.mass, 40)
        np.testing.assert_allclose(evals, ref_evals, atol=1e-9 * ref_evals.max())
        # sign- and rotation-free: squared eigenvectors summed over the first 25 (sphere-like l <= 4 modes, apart from l = 5)
        np.testing.assert_allclose((evecs[:, :25] ** 2).sum(1), (ref_evecs[:, :25] ** 2).sum(1), rtol=1e-6)


def test_mass_normalize_gives_unit_mass_norm_and_keeps_zero_channels():
    mass = np.array([1.0, 2.0, 0.5])
    features = np.array([[1.0, 0.0, 3.0], [2.0, 0.0, -1.0], [0.0, 0.0, 4.0]])
    out = mass_normalize(features, mass)
    np.testing.assert_allclose(mass @ np.square(out[:, [0, 2]]), [1.0, 1.0])
    np.testing.assert_array_equal(out[:, 1], 0.0)
    np.testing.assert_allclose(out[:, 0] / out[0, 0], features[:, 0])  # a scaling per channel


def _eigsh_reference(stiffness, mass, k):
    """scipy's ``eigsh`` on the generalised problem with its default tolerance."""
    stiffness = sp.csc_matrix(stiffness)
    return sla.eigsh(stiffness, k=k, M=sp.diags(mass), sigma=-1e-6 * stiffness.diagonal().sum(), which="LM")


def _largest_eigenspace_sine(evecs, reference, evals, mass, gap=1e-3):
    """Largest sine between the mass-orthonormal eigenspaces of eigenvalues closer than ``gap`` (relative)."""
    bounds = [0] + [i for i in range(1, len(evals)) if evals[i] - evals[i - 1] > gap * abs(evals[i])] + [len(evals)]
    worst = 0.0
    for start, stop in zip(bounds[:-2], bounds[1:-1], strict=True):  # the last space may go on past k
        overlap = reference[:, start:stop].T @ (mass[:, None] * evecs[:, start:stop])
        smallest = min(1.0, float(np.linalg.svd(overlap, compute_uv=False).min()))
        worst = max(worst, float(np.sqrt(1.0 - smallest**2)))
    return worst


@pytest.mark.parametrize(("factorization", "lanczos_from"), [("auto", 0), ("superlu", 0), ("auto", 10**9)])
def test_sparse_solve_gives_the_eigenpairs_of_scipy_eigsh(faust_mesh, monkeypatch, factorization, lanczos_from):
    """Lanczos (tried from `LANCZOS_FROM_VERTICES` on) and ARPACK, with either factorisation."""
    monkeypatch.setattr(spectral, "FACTORIZATION", factorization)
    monkeypatch.setattr(spectral, "LANCZOS_FROM_VERTICES", lanczos_from)
    lap = laplacian(faust_mesh, kind="robust")
    k = 96
    evals, evecs = spectral.solve_eigenpairs(lap.stiffness, lap.mass, k)
    ref_evals, ref_evecs = _eigsh_reference(lap.stiffness, lap.mass, k)
    np.testing.assert_allclose(evals[1:], ref_evals[1:], rtol=1e-8)
    assert _largest_eigenspace_sine(evecs, ref_evecs, ref_evals, lap.mass) < 1e-6


def test_cholmod_factorisation_solves_like_superlu():
    pytest.importorskip("sksparse.cholmod", reason="scikit-sparse (CHOLMOD) is an optional speed-up")
    mesh = bumpy(seed=0)
    lap = laplacian(mesh, kind="cotan")
    shifted = sp.csc_matrix(lap.stiffness + 1e-3 * sp.diags(lap.mass))
    rhs = np.random.default_rng(0).standard_normal(mesh.n_vertices)
    expected = sla.spsolve(shifted, rhs)
    np.testing.assert_allclose(spectral._factorize(shifted)(rhs), expected, rtol=1e-8, atol=1e-10 * np.abs(expected).max())


def test_first_subspace_is_k_plus_a_margin_below_n():
    assert spectral.first_subspace(100_000, 128) == 160
    assert spectral.first_subspace(100_000, 400) == 500
    assert spectral.first_subspace(100_000, 3) == 35
    assert spectral.first_subspace(50, 40) == 49


def test_a_solve_that_would_not_fit_in_memory_is_refused_before_it_starts(faust_mesh, monkeypatch):
    monkeypatch.setattr(spectral, "available_memory", lambda: 10_000_000)
    monkeypatch.setattr(spectral, "_sparse_with_fallbacks", lambda *args: pytest.fail("the solve started"))
    with pytest.raises(SpectralError, match="need about .* of memory, and 10.0 MB is available"):
        spectral_basis(faust_mesh, k=128, cache=False)


def test_memory_estimate_grows_with_vertices_and_eigenpairs():
    small, large = spectral.eigensolve_memory(20_000, 128), spectral.eigensolve_memory(200_000, 128)
    assert large == pytest.approx(10 * small, rel=1e-6)
    assert spectral.eigensolve_memory(20_000, 256) > small
    assert 5e9 < spectral.eigensolve_memory(1_000_000, 128) < 7e9
