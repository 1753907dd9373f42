import logging

import numpy as np
import pytest
import scipy.linalg as la
from shapes import bumpy

from geofeat.errors import SpectralError
from geofeat.geometry import lanczos, laplacian, spectral


def _spd(n, seed=0, spread=1e4):
    """A dense symmetric positive definite matrix with eigenvalues from 1 to ``spread``, shape (n, n)."""
    rng = np.random.default_rng(seed)
    basis, _ = np.linalg.qr(rng.standard_normal((n, n)))
    values = np.geomspace(1.0, spread, n)
    return (basis * values) @ basis.T


def test_largest_eigenpairs_of_a_symmetric_matrix():
    matrix = _spd(300)
    theta, vectors = lanczos.largest_eigenpairs(lambda x: matrix @ x, 300, 20, max_steps=200)
    values, reference = la.eigh(matrix)
    np.testing.assert_allclose(theta, values[::-1][:20], rtol=1e-10)
    np.testing.assert_allclose(vectors.T @ vectors, np.eye(20), atol=1e-12)
    residual = matrix @ vectors - vectors * theta
    assert np.linalg.norm(residual, axis=0).max() < 1e-9 * theta.max()


def test_repeated_eigenvalues_are_found_with_their_multiplicity():
    """Three distinct eigenvalues: the Krylov space of a start vector is exhausted after three
    steps; rounding then gives a new direction, orthogonalised against the basis, and the
    other copies of the largest eigenvalue are found."""
    values = np.repeat([1.0, 2.0, 3.0], 20)
    theta, vectors = lanczos.largest_eigenpairs(lambda x: values * x, 60, 5, max_steps=40)
    np.testing.assert_allclose(theta, 3.0, rtol=1e-12)
    np.testing.assert_allclose(vectors.T @ vectors, np.eye(5), atol=1e-12)
    assert np.abs(vectors[:40]).max() < 1e-12  # all in the eigenspace of 3


def test_no_convergence_within_the_steps_is_an_error():
    matrix = _spd(300, spread=10.0)  # clustered: slow convergence
    with pytest.raises(SpectralError, match="did not converge within 25 steps"):
        lanczos.largest_eigenpairs(lambda x: matrix @ x, 300, 20, max_steps=25)


@pytest.mark.parametrize(("k", "max_steps", "n"), [(0, 10, 20), (10, 10, 20), (5, 30, 20)])
def test_bad_sizes_are_refused(k, max_steps, n):
    with pytest.raises(SpectralError, match="0 < k < max_steps <= n"):
        lanczos.largest_eigenpairs(lambda x: x, n, k, max_steps=max_steps)


def test_vectors_far_from_orthonormal_are_refused():
    vectors = np.linalg.qr(np.random.default_rng(0).standard_normal((50, 4)))[0]
    np.testing.assert_allclose(lanczos._orthonormalise(vectors), vectors, atol=1e-14)
    vectors[:, 1] += 1e-6 * vectors[:, 0]
    with pytest.raises(SpectralError, match="orthonormal only to 1.0e-06"):
        lanczos._orthonormalise(vectors)


def test_partial_reorthogonalisation_skips_most_steps(monkeypatch):
    """The basis is read by a reorthogonalisation at a fraction of the steps, not at each,
    and each covers every earlier vector."""
    matrix = _spd(400, seed=1)
    blocks, steps = [], []
    real = lanczos._reorthogonalise

    def spy(block, residual):
        blocks.append((len(block), len(steps)))
        return real(block, residual)

    def apply(x):
        steps.append(1)
        return matrix @ x

    monkeypatch.setattr(lanczos, "_reorthogonalise", spy)
    theta, vectors = lanczos.largest_eigenpairs(apply, 400, 30, max_steps=300)
    np.testing.assert_allclose(theta, la.eigvalsh(matrix)[::-1][:30], rtol=1e-10)
    np.testing.assert_allclose(vectors.T @ vectors, np.eye(30), atol=1e-12)
    assert 0 < len(blocks) < 0.5 * len(steps)
    assert all(size == step for size, step in blocks)  # against every Lanczos vector so far


def test_a_missed_mode_hands_over_to_arpack(monkeypatch, caplog):
    """The count of eigenvalues (Sylvester's inertia) catches a Lanczos answer that skipped a mode."""
    mesh = bumpy(3, 3)
    lap = laplacian(mesh, "cotan")
    expected, _ = spectral.solve_eigenpairs(lap.stiffness, lap.mass, 12, progress=False)
    real = spectral.largest_eigenpairs

    def skipping(apply, n, k, max_steps):
        theta, vectors = real(apply, n, k + 1, max_steps=max_steps)
        keep = np.r_[0:4, 5 : k + 1]  # the fifth largest dropped, the (k+1)-th in its place
        return theta[keep], vectors[:, keep]

    monkeypatch.setattr(spectral, "largest_eigenpairs", skipping)
    monkeypatch.setattr(spectral, "LANCZOS_FROM_VERTICES", 0)
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        evals, _ = spectral.solve_eigenpairs(lap.stiffness, lap.mass, 12, progress=False)
    assert "13 eigenvalues lie below the largest of the 12 found" in caplog.text
    assert "succeeded with shift-invert, sigma=-1e-6*scale" in caplog.text
    np.testing.assert_allclose(np.sort(evals), expected, rtol=1e-8, atol=1e-10)
