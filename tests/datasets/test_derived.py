import numpy as np
import pytest
from scipy.spatial import cKDTree

from geofeat.datasets.derived import DerivedPartialBenchmark, SyntheticCollection, template_inverse
from geofeat.datasets.synthetic import SyntheticHumans


@pytest.fixture(scope="module")
def collection():
    return SyntheticCollection(SyntheticHumans(n_individuals=2, n_poses=3, seed=1))


def source_indices(pair_mesh, full_mesh):
    """Which vertex of the full mesh each vertex of a partial mesh is (exact coordinates)."""
    distance, index = cKDTree(full_mesh.verts).query(pair_mesh.verts)
    assert distance.max() == 0.0
    return index


@pytest.mark.parametrize("kind", ["cuts", "holes", "ray"])
def test_p2f_ground_truth_goes_through_the_template(collection, kind):
    bench = DerivedPartialBenchmark(collection, [0, 1, 2, 3, 4, 5], kind, "p2f", seed=3)
    assert len(bench) == 30
    for i in range(3):
        pair = bench[i]
        a, b = bench.pairs[i]
        assert pair.x.n_vertices == collection.mesh(b).n_vertices
        sources = source_indices(pair.y, collection.mesh(a))
        # identity template: the counterpart in B is the same template vertex
        np.testing.assert_array_equal(pair.map_yx, sources)
        np.testing.assert_array_equal(pair.map_yx_sym, collection.humans.mirror[sources])
        assert pair.protocol == "p2f" and pair.overlap_y.all()
        # the full shape overlaps exactly where the partial's vertices came from
        np.testing.assert_array_equal(np.flatnonzero(pair.overlap_x), np.unique(sources))
        assert 0 < pair.overlap_x.mean() < 1


def test_p2p_maps_and_overlaps_are_consistent(collection):
    bench = DerivedPartialBenchmark(collection, [0, 1, 2, 3], "cuts", "p2p", seed=0)
    pair = bench[1]
    a, b = bench.pairs[1]
    ys = source_indices(pair.y, collection.mesh(a))
    xs = source_indices(pair.x, collection.mesh(b))
    x_of_source = {int(s): i for i, s in enumerate(xs)}
    expected = np.array([x_of_source.get(int(s), -1) for s in ys])
    np.testing.assert_array_equal(pair.map_yx, expected)
    np.testing.assert_array_equal(pair.overlap_y, expected >= 0)
    np.testing.assert_array_equal(np.flatnonzero(pair.overlap_x), np.sort(expected[expected >= 0]))
    assert 0 < pair.overlap_y.mean() < 1


def test_pairs_are_reproducible_and_independent_of_order(collection):
    one = DerivedPartialBenchmark(collection, [0, 1, 2], "holes", "p2f", seed=5)
    two = DerivedPartialBenchmark(collection, [0, 1, 2], "holes", "p2f", seed=5)
    late = two[4]
    np.testing.assert_array_equal(one[4].y.verts, late.y.verts)
    assert one.pair_names == two.pair_names
    other = DerivedPartialBenchmark(collection, [0, 1, 2], "holes", "p2f", seed=6)
    assert other.pair_names != one.pair_names or not np.array_equal(other[0].y.verts, one[0].y.verts)


def test_template_inverse_keeps_the_first_point():
    inverse = template_inverse(np.array([2, 0, 2, 3]), 5)
    np.testing.assert_array_equal(inverse, [1, -1, 0, 3, -1])


def test_bad_kind_or_protocol(collection):
    with pytest.raises(ValueError, match="kind"):
        DerivedPartialBenchmark(collection, [0, 1], "slices")
    with pytest.raises(ValueError, match="protocol"):
        DerivedPartialBenchmark(collection, [0, 1], "cuts", "f2f")


class SparseTemplate(SyntheticCollection):
    """Synthetic shapes whose template covers only every other vertex, like a remeshed collection."""

    def template_map(self, index):
        return super().template_map(index)[::2]

    def template_map_sym(self, index):
        return super().template_map_sym(index)[::2]


@pytest.mark.parametrize("protocol", ["p2f", "p2p"])
def test_overlap_masks_are_geometric_where_the_template_has_gaps(protocol):
    sparse = SparseTemplate(SyntheticHumans(n_individuals=2, n_poses=3, seed=1))
    dense = SyntheticCollection(sparse.humans)
    sparse_pair = DerivedPartialBenchmark(sparse, [0, 1, 2, 3], "cuts", protocol, seed=0)[1]
    dense_pair = DerivedPartialBenchmark(dense, [0, 1, 2, 3], "cuts", protocol, seed=0)[1]
    assert (sparse_pair.map_yx < 0).mean() > 0.3  # half the vertices have no ground-truth counterpart
    for side in ("overlap_x", "overlap_y"):
        sparse_mask, dense_mask = getattr(sparse_pair, side), getattr(dense_pair, side)
        # nearest covered vertices fill the gaps: the masks agree with the fully covered ones
        # except along the cut boundary
        assert (sparse_mask == dense_mask).mean() > 0.95
    if protocol == "p2f":
        assert sparse_pair.overlap_y.all()
    assert 0.05 < dense_pair.overlap_x.mean() < 0.95  # a real cut, not a trivial mask
