"""The reference RAY partial shapes (geofeat.render.raycast): open3d's pinhole rays, first hits, trimesh's split.

Values marked "official" were produced by the official code (vikiehm/geo-lora ``utils/ray_caster.py``
with open3d 0.20.0 and trimesh 4.5.0); open3d is not needed to run these tests.
"""

from __future__ import annotations

import numpy as np
import pytest

import geofeat
from geofeat import Mesh
from geofeat.errors import MeshError, RenderError
from geofeat.render.raycast import (
    first_hits,
    official_components,
    official_filled_holes,
    official_ray_eye,
    pinhole_camera,
    pinhole_rays,
    ray_partial_reference,
)


def grid(n: int, z: float = 0.0, half: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid of squares (two triangles each) in the plane ``z``, counter-clockwise seen from +z."""
    ticks = np.linspace(-half, half, n + 1)
    xs, ys = np.meshgrid(ticks, ticks, indexing="xy")
    verts = np.stack((xs.ravel(), ys.ravel(), np.full(xs.size, z)), axis=1)
    faces = []
    for row in range(n):
        for col in range(n):
            a = row * (n + 1) + col
            b, c, d = a + 1, a + n + 2, a + n + 1
            faces += [(a, b, c), (a, c, d)]
    return verts, np.array(faces, dtype=np.int64)


# ---------------------------------------------------------------------------------------- rays


def test_rays_go_through_pixel_centres_of_a_camera_looking_down_an_axis():
    # eye on +z looking at the origin: right = up x forward = -x, rows grow along +y (row 0 at the bottom)
    directions = pinhole_rays(pinhole_camera((0.0, 0.0, 2.0), image_size=300))
    col, row = np.meshgrid(np.arange(300), np.arange(300), indexing="xy")
    expected = np.stack((-(col + 0.5 - 150) / 150, (row + 0.5 - 150) / 150, -np.ones((300, 300))), axis=-1)
    np.testing.assert_allclose(directions, expected, atol=1e-12)


def test_rays_equal_open3d_create_rays_pinhole():
    # official: o3d.t.geometry.RaycastingScene.create_rays_pinhole(fov_deg=90, center=0, eye=(0, 0, 2), up=+y, 4, 3)
    official = np.array(
        [
            [[0.75, -0.5, -1.0], [0.25, -0.5, -1.0], [-0.25, -0.5, -1.0], [-0.75, -0.5, -1.0]],
            [[0.75, 0.0, -1.0], [0.25, 0.0, -1.0], [-0.25, 0.0, -1.0], [-0.75, 0.0, -1.0]],
            [[0.75, 0.5, -1.0], [0.25, 0.5, -1.0], [-0.25, 0.5, -1.0], [-0.75, 0.5, -1.0]],
        ]
    )  # a 3 x 4 grid: the focal length comes from the width
    np.testing.assert_allclose(pinhole_rays(pinhole_camera((0.0, 0.0, 2.0), image_size=(3, 4))), official, atol=1e-7)
    # official: fov_deg=60, center=(0.1, 0.2, 0.3), eye=(1, 2, -3), width 5, height 7 (float32 there)
    directions = pinhole_rays(pinhole_camera((1.0, 2.0, -3.0), center=(0.1, 0.2, 0.3), image_size=(7, 5), fov_degrees=60.0))
    np.testing.assert_allclose(directions[0, 0], [-0.5935583710670471, -1.078800082206726, 0.4209657311439514], atol=1e-6)
    np.testing.assert_allclose(directions[6, 4], [0.12786805629730225, 0.14741945266723633, 1.2865654230117798], atol=1e-6)
    np.testing.assert_allclose(directions[3, 2], [-0.23284512758255005, -0.4656903147697449, 0.853765606880188], atol=1e-6)


def test_camera_looking_along_up_is_refused():
    with pytest.raises(RenderError, match="up vector"):
        pinhole_camera((0.0, 3.0, 0.0))


# ---------------------------------------------------------------------------------------- hits


def test_square_facing_the_camera_is_hit_on_all_its_faces_from_either_side():
    verts, faces = grid(4, z=0.0)
    for eye in ((0.0, 0.0, 1.0), (0.0, 0.0, -1.0)):  # front and back side
        hits = first_hits(verts, faces, pinhole_camera(eye, image_size=64))
        assert np.array_equal(hits.hit_faces(), np.arange(len(faces)))
        np.testing.assert_allclose(hits.depth[hits.face >= 0], 1.0, rtol=1e-6)
        # the square spans [-0.5, 0.5]: at depth 1 with a 90 degree view, the middle half of the rays
        assert np.all(hits.face[16:48, 16:48] >= 0) and np.all(hits.face[:15] < 0) and np.all(hits.face[:, 49:] < 0)


def test_square_behind_another_is_hidden():
    front, front_faces = grid(2, z=0.2, half=0.5)
    back, back_faces = grid(2, z=-0.2, half=0.3)
    verts = np.concatenate((back, front))
    faces = np.concatenate((back_faces, front_faces + len(back)))  # back faces come first (lower indices)
    hits = first_hits(verts, faces, pinhole_camera((0.0, 0.0, 1.0), image_size=64))
    assert np.array_equal(hits.hit_faces(), np.arange(len(back_faces), len(faces)))
    # seen from behind, the small square hides part of the large one, which shows around it
    hits = first_hits(verts, faces, pinhole_camera((0.0, 0.0, -1.0), image_size=300))
    assert np.array_equal(hits.hit_faces(), np.arange(len(faces)))


def test_faces_crossing_the_camera_plane_are_hit_in_front_of_the_camera():
    # a floor at y = -0.5 from z = -100 to z = 10, camera at z = 1 looking at -z: both floor triangles
    # have corners behind the camera, which the rasterizer does not draw
    verts = np.array([[-100.0, -0.5, -100.0], [100.0, -0.5, -100.0], [100.0, -0.5, 10.0], [-100.0, -0.5, 10.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    camera = pinhole_camera((0.0, 0.0, 1.0), image_size=32)
    hits = first_hits(verts, faces, camera)
    assert np.all(hits.face[:16] >= 0) and np.all(hits.face[16:] < 0)  # rows below the horizon see the floor
    directions = pinhole_rays(camera)
    np.testing.assert_allclose(hits.depth[:16], 0.5 / -directions[:16, :, 1])


# ---------------------------------------------------------------------------------------- trimesh's split


def test_components_join_faces_through_edges_of_exactly_two_faces():
    faces = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [5, 6, 2]])  # 0-1-2 chain by edges, face 3 touches at a vertex
    assert official_components(faces).tolist() == [0, 0, 0, 1]
    fin = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [4, 1, 5]])  # edge (0, 1) has three faces: it joins none
    assert official_components(fin).tolist() == [0, 1, 2, 2]


def test_holes_of_three_and_four_edges_are_filled_like_trimesh():
    verts, faces = grid(4)  # faces 10 and 11: the square of rows 1-2, columns 1-2 of the vertices (inside)
    single = np.delete(faces, 10, axis=0)  # one missing triangle: filled with the same oriented triangle
    filled = official_filled_holes(verts, single)
    assert [np.roll(filled[0], k).tolist() for k in range(3)].count(faces[10].tolist()) == 1 and len(filled) == 1
    quad = np.delete(faces, [10, 11], axis=0)  # one missing square: two triangles over its four corners
    filled = official_filled_holes(verts, quad)
    assert len(filled) == 2 and sorted(set(filled.ravel())) == sorted(set(faces[[10, 11]].ravel()))
    normals = np.cross(verts[filled[:, 1]] - verts[filled[:, 0]], verts[filled[:, 2]] - verts[filled[:, 0]])
    assert np.all(normals[:, 2] > 0)  # same orientation as the grid
    larger = np.delete(faces, [10, 11, 12, 13], axis=0)  # a hole of six edges stays open
    assert len(official_filled_holes(verts, larger)) == 0


# ---------------------------------------------------------------------------------------- the generator


def test_official_ray_eye_replays_the_legacy_stream():
    np.random.seed(0)
    first = official_ray_eye()
    official_ray_eye()
    third = official_ray_eye()
    after = np.random.rand()
    # official: numpy.random.seed(0); cam_generator("low", n_cam_pos=1)[0, :, 0], draws 0 and 2
    assert first.tolist() == [-0.2863206670534971, -0.9040826608793917, 0.3172617498458951]
    assert third.tolist() == [0.027399760390236828, 0.0572569873480131, -0.997983411951515]
    replay = np.random.RandomState(0)
    replay.rand(21)  # seven numbers per draw
    assert after == replay.rand()
    assert np.array_equal(official_ray_eye(np.random.RandomState(0)), first)


@pytest.fixture(scope="module")
def faust_080(faust_dir) -> Mesh:
    mesh = geofeat.load_mesh(faust_dir / "off" / "tr_reg_080.off")
    return Mesh(mesh.verts.astype(np.float32), mesh.faces, name="tr_reg_080")


@pytest.mark.parametrize(
    ("eye", "official"),
    [
        ([-0.2863206670534971, -0.9040826608793917, 0.3172617498458951], (73, 100, 983)),
        ([0.027399760390236828, 0.0572569873480131, -0.997983411951515], (1126, 1740, 2195)),
    ],
)
def test_reference_partial_matches_the_official_draws(faust_080, eye, official):
    partial = ray_partial_reference(faust_080, eye)
    n_vertices, n_faces, n_hit = official  # official: vertices, faces (with filled holes), hit triangles
    assert (partial.mesh.n_vertices, len(partial.mesh.faces), partial.info["hit_faces"].size) == (n_vertices, n_faces, n_hit)
    assert partial.kind == "ray" and partial.info["scale"] == 1.0
    source = partial.info["source_vertices"]
    np.testing.assert_array_equal(partial.mesh.verts, faust_080.verts[source])
    np.testing.assert_array_equal(partial.vertex_map, source)  # ground truth: no repeated positions here
    assert not partial.exact
    kept = partial.face_map >= 0
    np.testing.assert_array_equal(source[partial.mesh.faces[kept]], faust_080.faces[partial.face_map[kept]])
    assert np.isin(partial.face_map[kept], partial.info["hit_faces"]).all()
    assert (~kept).sum() == partial.info["n_filled"] > 0


def test_ground_truth_is_the_lowest_vertex_at_the_same_position():
    verts, faces = grid(3)
    duplicate = np.concatenate((verts[[5]], verts))  # vertex 0 repeats the position of vertex 6 (old 5)
    mesh = Mesh(duplicate, faces + 1, name="square")
    partial = ray_partial_reference(mesh, (0.0, 0.0, 1.0))
    assert partial.info["source_vertices"].tolist() == list(range(1, 17))
    expected = partial.info["source_vertices"].copy()
    expected[expected == 6] = 0
    np.testing.assert_array_equal(partial.vertex_map, expected)


def test_large_mesh_is_cast_at_scale_0_8_and_keeps_its_positions():
    verts, faces = grid(2, z=-0.1, half=0.5)
    big = Mesh(verts * np.array([3.0, 0.25, 1.0]), faces, name="wide")  # diagonal 3.03: cast at 0.8
    partial = ray_partial_reference(big, (0.0, 0.0, 1.0))
    assert partial.info["scale"] == 0.8
    # positions unscaled, rounded to float32 as the official training does
    np.testing.assert_array_equal(partial.mesh.verts, big.verts.astype(np.float32)[partial.info["source_vertices"]])


def test_no_hit_raises():
    verts, faces = grid(2, z=5.0)  # behind the camera at z = 1 looking at the origin
    with pytest.raises(MeshError, match="no ray"):
        ray_partial_reference(Mesh(verts, faces, name="behind"), (0.0, 0.0, 1.0))
