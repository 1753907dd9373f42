import numpy as np
import pytest
from shapes import bumpy

from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry.surface_points import SurfacePoints


def test_positions_and_nearest_corners():
    mesh = bumpy(0, 1)
    face = np.array([0, 5, 5])
    bary = np.array([[1.0, 0.0, 0.0], [0.2, 0.3, 0.5], [0.4, 0.4, 0.2]])
    points = SurfacePoints(mesh, face, bary)
    corners = mesh.verts[mesh.faces[face]]
    np.testing.assert_allclose(points.positions(), np.einsum("pk,pkd->pd", bary, corners), atol=1e-12)
    # the corner with the largest weight; the first of two equal ones
    assert points.nearest_corner.tolist() == [mesh.faces[0, 0], mesh.faces[5, 2], mesh.faces[5, 0]]
    assert len(points) == 3 and not points.nearest_corner.flags.writeable and not points.bary.flags.writeable


@pytest.mark.parametrize(
    ("face", "bary", "message"),
    [
        ([0, 1], [[1.0, 0.0, 0.0]], "shape"),
        ([10_000], [[1.0, 0.0, 0.0]], "face indices must lie"),
        ([0], [[0.5, 0.6, 0.0]], "sum to 1"),
        ([0], [[1.5, -0.5, 0.0]], "non-negative"),
        ([0.0], [[1.0, 0.0, 0.0]], "integer"),
    ],
)
def test_bad_surface_points_are_refused(face, bary, message):
    with pytest.raises(MeshError, match=message):
        SurfacePoints(bumpy(0, 1), np.array(face), np.array(bary))


def test_a_point_cloud_has_no_surface_points():
    with pytest.raises(MeshError, match="point cloud"):
        SurfacePoints(Mesh(np.eye(3)), np.array([0]), np.array([[1.0, 0.0, 0.0]]))
