import time

import numpy as np

from geofeat.datasets import synthetic
from geofeat.datasets.synthetic import Proportions, SyntheticHumans, posed_shape, template


def test_template_is_one_closed_mirror_symmetric_component():
    mesh, mirror = template()
    assert 3000 < mesh.n_vertices < 8000
    assert mesh.report() == [] and mesh.n_components() == 1
    np.testing.assert_array_equal(mirror[mirror], np.arange(mesh.n_vertices))  # an involution
    np.testing.assert_array_equal(mesh.verts[mirror] * [-1, 1, 1], mesh.verts)
    edges = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)  # watertight
    assert mesh.verts[:, 2].max() > 0.1  # nose and toes point to +z


def test_collection_is_fast_deterministic_and_shares_connectivity():
    start = time.perf_counter()
    humans = SyntheticHumans(n_individuals=3, n_poses=3, seed=7)
    shapes = [humans.shape(i) for i in range(len(humans))]
    assert time.perf_counter() - start < 10.0
    assert [s.name for s in shapes] == humans.names and len(set(humans.names)) == 9
    for shape in shapes:
        np.testing.assert_array_equal(shape.faces, shapes[0].faces)
        assert np.isfinite(shape.verts).all()
    again = SyntheticHumans(n_individuals=3, n_poses=3, seed=7).shape(4)
    np.testing.assert_array_equal(again.verts, shapes[4].verts)
    other = SyntheticHumans(n_individuals=3, n_poses=3, seed=8).shape(4)
    assert not np.allclose(other.verts, shapes[4].verts)
    # Poses move vertices far more than the rest-pose jitter does.
    moved = np.linalg.norm(shapes[1].verts - shapes[0].verts, axis=1).max()
    assert moved > 0.1


def test_symmetric_individual_in_rest_pose_is_mirror_symmetric():
    proportions = Proportions.random(np.random.default_rng(3))
    identity = np.repeat(np.eye(3)[None], len(synthetic.SKELETON), axis=0)
    shape = posed_shape(proportions, identity, "rest")
    mirror = SyntheticHumans().mirror
    np.testing.assert_allclose(shape.verts[mirror] * [-1, 1, 1], shape.verts, atol=1e-12)


def test_random_poses_mirror_left_and_right_ranges():
    rng = np.random.default_rng(0)
    pose = synthetic.random_pose(rng)
    assert pose.shape == (len(synthetic.SKELETON), 3, 3)
    np.testing.assert_allclose(pose @ pose.transpose(0, 2, 1), np.repeat(np.eye(3)[None], len(pose), 0), atol=1e-12)
    assert np.allclose(pose[[b.name for b in synthetic.SKELETON].index("nose")], np.eye(3))


def test_segment_distance_is_the_norm_of_the_offset_to_the_closest_point():
    points = np.random.default_rng(0).uniform(-1, 2, size=(5000, 3))
    head, tail = np.array([0.1, 0.2, -0.3]), np.array([0.9, 1.1, 0.4])
    distance, t = synthetic._segment_distance(points, head, tail)
    axis = tail - head
    plain_t = np.clip((points - head) @ axis / (axis @ axis), 0.0, 1.0)
    np.testing.assert_array_equal(t, plain_t)
    assert 0 < (t == 0).sum() and 0 < (t == 1).sum() and 0 < ((t > 0) & (t < 1)).sum()  # both ends and the middle
    plain = np.linalg.norm(points - (head + plain_t[:, None] * axis), axis=1)
    np.testing.assert_allclose(distance, plain, rtol=1e-15, atol=0)
