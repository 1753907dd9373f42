"""Farthest-point sampling: deterministic, spread out, prefixes are samples, bad input refused."""

import numpy as np
import pytest
from shapes import bumpy

from geofeat.errors import MeshError
from geofeat.geometry.sampling import farthest_point_sampling


def test_deterministic_and_spreads_points():
    points = bumpy(0, 3).verts
    first = farthest_point_sampling(points, 60, seed=3)
    np.testing.assert_array_equal(first, farthest_point_sampling(points, 60, seed=3))
    assert first.dtype == np.int64 and len(np.unique(first)) == 60
    np.testing.assert_array_equal(farthest_point_sampling(points, 20, seed=3), first[:20])  # prefixes are samples

    def min_distance(index):
        p = points[index]
        d = np.linalg.norm(p[:, None] - p[None], axis=-1)
        return d[np.triu_indices(len(index), 1)].min()

    rng = np.random.default_rng(0)
    random_best = max(min_distance(rng.choice(len(points), 60, replace=False)) for _ in range(20))
    assert min_distance(first) > 1.5 * random_best


def test_each_sample_is_the_point_farthest_from_the_samples_before_it():
    points = bumpy(0, 3).verts
    chosen = farthest_point_sampling(points, 30, seed=np.random.default_rng(5))
    assert chosen.dtype == np.int64 and len(np.unique(chosen)) == 30
    for i in range(1, len(chosen)):
        nearest = np.min(np.linalg.norm(points[:, None] - points[chosen[:i]][None], axis=-1), axis=1)
        assert nearest[chosen[i]] == nearest.max()


def test_the_first_sample_comes_from_the_seed():
    points = np.random.default_rng(0).normal(size=(200, 3))
    firsts = {int(farthest_point_sampling(points, 1, seed=s)[0]) for s in range(20)}
    assert len(firsts) > 1
    np.testing.assert_array_equal(farthest_point_sampling(points, 50, seed=7), farthest_point_sampling(points, 50, seed=7))


def test_prefixes_are_samples_and_all_points_is_a_permutation():
    points = np.random.default_rng(1).uniform(size=(40, 2))
    every = farthest_point_sampling(points, 40, seed=3)
    assert sorted(every.tolist()) == list(range(40))
    np.testing.assert_array_equal(farthest_point_sampling(points, 12, seed=3), every[:12])


@pytest.mark.parametrize(
    ("points", "n", "message"),
    [
        (np.zeros((0, 3)), 1, "finite"),
        (np.array([[0.0, np.nan, 0.0]]), 1, "finite"),
        (np.zeros(3), 1, "finite"),
        (np.zeros((4, 3)), 0, "n_samples"),
        (np.zeros((4, 3)), 5, "n_samples"),
        (np.zeros((4, 3)), 2.0, "n_samples"),
    ],
)
def test_bad_input_is_refused_with_a_mesh_error(points, n, message):
    with pytest.raises(MeshError, match=message):
        farthest_point_sampling(points, n)
