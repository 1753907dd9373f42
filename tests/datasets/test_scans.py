import numpy as np
import pytest

from geofeat.datasets import dataset_names, load_dataset
from geofeat.datasets.base import read_indices
from geofeat.datasets.depth_camera import DepthCamera
from geofeat.datasets.derived import SyntheticCollection, template_inverse
from geofeat.datasets.scans import ScanBenchmark
from geofeat.datasets.synthetic import SyntheticHumans
from geofeat.errors import DatasetError

SMALL = DepthCamera(image_size=64)


@pytest.fixture(scope="module")
def collection():
    return SyntheticCollection(SyntheticHumans(n_individuals=2, n_poses=3, seed=1))


def test_ground_truth_goes_from_the_scanned_surface_point_through_the_template(collection):
    bench = ScanBenchmark(collection, [0, 1, 2, 3, 4, 5], seed=3, camera=SMALL)
    assert len(bench) == 30 and len(set(bench.pairs)) == 30
    for i in range(3):
        pair = bench[i]
        a, b = bench.pairs[i]
        assert pair.name == bench.pair_names[i] and pair.protocol == "p2f"
        assert pair.y.is_point_cloud and pair.x.hash == collection.mesh(b).hash
        surface = pair.y_surface
        assert surface is not None and surface.mesh.hash == collection.mesh(a).hash and len(surface) == pair.y.n_vertices
        # identity template: the counterpart is the nearest corner of the face the ray hit
        np.testing.assert_array_equal(pair.map_yx, surface.nearest_corner)
        np.testing.assert_array_equal(pair.map_yx_sym, collection.humans.mirror[surface.nearest_corner])
        assert pair.overlap_y.all()
        seen = np.unique(collection.mesh(a).faces[bench.scan(i).seen_faces()])  # the scan is a function of the seed
        np.testing.assert_array_equal(np.flatnonzero(pair.overlap_x), seen)
        assert 0.2 < pair.overlap_x.mean() < 0.8


def test_a_pair_depends_on_its_seed_and_index_only(collection):
    first = ScanBenchmark(collection, [0, 1, 2, 3], seed=5, camera=SMALL)
    again = ScanBenchmark(collection, [0, 1, 2, 3], seed=5, camera=SMALL)
    np.testing.assert_array_equal(first[4].y.verts, again[4].y.verts)
    np.testing.assert_array_equal(first[4].map_yx, again[4].map_yx)
    other = ScanBenchmark(collection, [0, 1, 2, 3], seed=6, camera=SMALL)
    assert first.pairs != other.pairs or not np.array_equal(first[0].y.verts, other[0].y.verts)


def test_the_scan_benchmarks_are_registered_with_their_camera_options():
    assert {"faust_r_scans", "scape_r_scans", "synthetic_scans"} <= set(dataset_names())
    pairs = load_dataset("synthetic_scans", split="test", image_size=48, depth_noise=0.0)
    assert len(pairs) == 90 and pairs.camera == DepthCamera(image_size=48, depth_noise=0.0)
    with pytest.raises(DatasetError, match="unknown option.*the depth camera takes: image_size"):
        load_dataset("synthetic_scans", resolution=48)
    with pytest.raises(DatasetError, match="depth_noise"):
        load_dataset("synthetic_scans", depth_noise=-1.0)


def test_faust_r_scans_map_each_point_through_the_faust_r_template(faust_dir):
    pairs = load_dataset("faust_r_scans", faust_dir.parent, split="test")
    assert len(pairs) == 380 and pairs.pair_names[0] == pairs[0].name
    pair = pairs[0]
    a, b = (name.split("_scan")[0] for name in pair.name.split("->"))
    vts_a = read_indices(faust_dir / "corres" / f"{a}.vts") - 1
    vts_b = read_indices(faust_dir / "corres" / f"{b}.vts") - 1
    point = template_inverse(vts_a, pair.y_surface.mesh.n_vertices)[pair.y_surface.nearest_corner]
    np.testing.assert_array_equal(pair.map_yx, np.where(point >= 0, vts_b[np.maximum(point, 0)], -1))
    assert 1_500 < pair.y.n_vertices < 6_000 and 0.6 < (pair.map_yx >= 0).mean() < 0.95
    assert 0.2 < pair.overlap_x.mean() < 0.8


def test_scans_and_cuts_pair_the_same_shapes_in_the_same_order():
    scans = load_dataset("synthetic_scans", split="test", image_size=48)
    cuts = load_dataset("synthetic_cuts", split="test")
    assert len(scans) == len(cuts) > 1
    assert scans.pairs == cuts.pairs
