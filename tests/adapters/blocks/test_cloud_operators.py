"""DiffusionNet's operators on point clouds: the reference constructions' neighbours, normals and gradients."""

import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat.adapters.blocks.operators import (
    cloud_neighbors,
    neighborhood_normals,
    surface_operators,
)
from geofeat.errors import MeshError


@pytest.fixture(scope="module")
def cloud() -> geofeat.Mesh:
    return geofeat.Mesh(bumpy(2, 3).verts, name="bumpy2-cloud")


def test_neighbours_leave_out_the_point_itself(cloud):
    neighbors = cloud_neighbors(cloud)
    assert neighbors.shape == (cloud.n_vertices, 30)
    assert not (neighbors == np.arange(cloud.n_vertices)[:, None]).any()
    distances = np.linalg.norm(cloud.verts[neighbors] - cloud.verts[:, None], axis=2)
    assert (np.diff(distances, axis=1) >= 0).all()  # nearest first


def test_neighbours_of_many_coincident_copies_drop_exactly_one(cloud):
    verts = np.vstack([cloud.verts, np.repeat(cloud.verts[:1], 40, axis=0)])
    neighbors = cloud_neighbors(geofeat.Mesh(verts))
    assert neighbors.shape == (len(verts), 30)
    assert not (neighbors == np.arange(len(verts))[:, None]).any()
    with pytest.raises(MeshError, match="has 2 points; at least 3"):
        cloud_neighbors(geofeat.Mesh(cloud.verts[:2]))


def test_neighbourhood_normals_are_the_plane_through_the_point():
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 8), np.linspace(0, 1, 8)), axis=-1).reshape(-1, 2)
    plane = geofeat.Mesh(np.column_stack([grid, 0.3 * grid[:, 0] - 0.2 * grid[:, 1]]))
    normals = neighborhood_normals(plane.verts, cloud_neighbors(plane))
    expected = np.array([-0.3, 0.2, 1.0]) / np.linalg.norm([-0.3, 0.2, 1.0])
    np.testing.assert_allclose(np.abs(normals @ expected), 1.0, atol=1e-9)


@pytest.mark.parametrize("construction", ["diffusionnet", "ulrssm"])
def test_reference_constructions_on_a_cloud(cloud, construction):
    ops = surface_operators(cloud, 16, laplacian_kind="robust", construction=construction, cache=False)
    frames = ops.frames.double().numpy()
    np.testing.assert_allclose(np.einsum("vij,vkj->vik", frames, frames), np.tile(np.eye(3), (cloud.n_vertices, 1, 1)), atol=1e-5)
    normals = neighborhood_normals(cloud.verts, cloud_neighbors(cloud))
    np.testing.assert_allclose(frames[:, 2], normals, atol=1e-6)  # the SVD's sign, unoriented
    direction = np.array([0.4, -1.0, 0.7])
    values = cloud.verts @ direction
    computed = np.stack(
        (ops.grad_x.to_dense().double().numpy() @ values, ops.grad_y.to_dense().double().numpy() @ values), axis=1
    )
    expected = frames[:, :2] @ direction
    assert np.linalg.norm(computed - expected, axis=1).max() < 0.1 * np.linalg.norm(direction)


def test_a_cloud_has_no_cotangent_laplacian(cloud):
    with pytest.raises(MeshError, match="point cloud: only kind='robust'"):
        surface_operators(cloud, 8, laplacian_kind="cotan", construction="diffusionnet", cache=False)
