"""Vertex normals: face weights, point clouds, vertices without a face, one result for a Mesh and for arrays."""

import numpy as np
import pytest
from shapes import sphere

from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry.normals import vertex_normals

#: A vertex (0) shared by a big face in the plane z = 0 and a small face in the plane x = 0.
VERTS = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.1], [0, 0.1, 0.0]], dtype=float)
FACES = np.array([[0, 1, 2], [0, 4, 3]])


def test_sphere_normals_point_outwards_and_are_unit():
    mesh = sphere(2)
    normals = vertex_normals(mesh)
    assert normals.shape == (mesh.n_vertices, 3) and normals.dtype == np.float64
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0)
    radial = mesh.verts / np.linalg.norm(mesh.verts, axis=1, keepdims=True)
    assert (np.einsum("vd,vd->v", normals, radial) > 0.99).all()
    np.testing.assert_array_equal(vertex_normals(mesh.verts, mesh.faces), normals)


def test_area_weights_let_the_big_face_dominate_and_unit_weights_do_not():
    big, small = np.array([0, 0, 1.0]), np.array([0.01, 0, 0])  # the cross products: twice each face's area
    np.testing.assert_allclose(vertex_normals(VERTS, FACES)[0], (big + small) / np.linalg.norm(big + small))
    unit = vertex_normals(VERTS, FACES, face_weights="unit")[0]
    np.testing.assert_allclose(unit, np.array([1.0, 0, 1.0]) / np.sqrt(2))


def test_vertices_without_a_face_get_the_neighbourhood_normal_or_zero():
    mesh = sphere(2)
    extra = np.vstack([mesh.verts, 1.001 * mesh.verts[:1]])  # a point just outside the sphere, in no face
    normals = vertex_normals(extra, mesh.faces)
    radial = extra[-1] / np.linalg.norm(extra[-1])
    assert normals[-1] @ radial > 0.95
    assert not vertex_normals(extra, mesh.faces, fallback=False)[-1].any()
    cloud = vertex_normals(Mesh(mesh.verts, None))
    assert (np.einsum("vd,vd->v", cloud, mesh.verts / np.linalg.norm(mesh.verts, axis=1, keepdims=True)) > 0.95).all()


def test_bad_input_is_refused():
    with pytest.raises(MeshError, match="face_weights"):
        vertex_normals(VERTS, FACES, face_weights="angle")
    with pytest.raises(MeshError, match="not a Mesh and faces"):
        vertex_normals(sphere(1), FACES)
    with pytest.raises(MeshError, match=r"\(V, 3\)"):
        vertex_normals(VERTS[:, :2], FACES)
