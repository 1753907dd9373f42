"""The point-cloud Laplacian with coincident and isolated points, and clouds too small for it."""

import logging

import numpy as np
import pytest
from shapes import bumpy

from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry import laplacian, spectral_basis
from geofeat.geometry.laplacian import isolated_points


@pytest.fixture(scope="module")
def points() -> np.ndarray:
    return bumpy(1, 2).verts  # 162 points of a smooth closed surface


def _same_basis(cloud: Mesh, clean: Mesh, k: int = 8) -> tuple:
    basis, reference = spectral_basis(cloud, k, cache=False), spectral_basis(clean, k, cache=False)
    np.testing.assert_allclose(basis.evals, reference.evals, rtol=1e-6, atol=1e-9)
    n = clean.n_vertices
    projector = basis.evecs[:n].T @ (reference.mass[:, None] * reference.evecs)
    np.testing.assert_allclose(np.abs(projector), np.eye(k), atol=1e-6)  # the same eigenvectors, up to sign
    return basis, reference


def test_coincident_points_are_solved_once(points, caplog):
    copies = np.array([0, 5, 5, 40])
    cloud = Mesh(np.vstack([points, points[copies]]), name="with-copies")
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        lap = laplacian(cloud)
    assert "4 point(s) repeat the position of an earlier one" in caplog.text
    n = len(points)
    np.testing.assert_array_equal(lap.mass[n:], 0.0)
    assert lap.stiffness[n:].nnz == 0 and lap.stiffness[:, n:].nnz == 0
    np.testing.assert_allclose(lap.mass[:n], laplacian(Mesh(points)).mass, rtol=1e-12)
    basis, _ = _same_basis(cloud, Mesh(points))
    np.testing.assert_array_equal(basis.evecs[n:], basis.evecs[copies])


def test_isolated_points_get_no_mass_and_nearest_values(points, caplog):
    far = np.array([[10.0, 10.0, 10.0], [10.0, 10.0, 10.05], [10.0, 10.05, 10.0], [-8.0, 0.0, 0.0]])
    cloud = Mesh(np.vstack([points, far]), name="with-outliers")
    n = len(points)
    np.testing.assert_array_equal(np.flatnonzero(isolated_points(cloud.verts)), np.arange(n, n + 4))
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        basis, _ = _same_basis(cloud, Mesh(points))
    assert "4 isolated point(s)" in caplog.text
    np.testing.assert_array_equal(basis.mass[n:], 0.0)
    nearest = np.argmin(np.linalg.norm(points[None] - far[:, None], axis=2), axis=1)
    np.testing.assert_array_equal(basis.evecs[n:], basis.evecs[nearest])


def test_a_clean_cloud_has_no_isolated_points(points):
    assert not isolated_points(points).any()
    assert not isolated_points(np.random.default_rng(0).standard_normal((200, 3))).any()


def test_too_few_distinct_points_is_refused(points):
    with pytest.raises(MeshError, match="has 60 points, of which 30 distinct and not isolated; .* at least 31 points"):
        laplacian(Mesh(np.vstack([points[:30], points[:30]])))
    with pytest.raises(MeshError, match="has 30 points; .* at least 31 points"):
        laplacian(Mesh(points[:30]))
