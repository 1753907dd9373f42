import logging

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from shapes import bumpy, sphere

import geofeat
from geofeat import Mesh
from geofeat.descriptors.shot import SHOT, SHOT_RECIPES, shot_descriptors
from geofeat.errors import DescriptorError, GeofeatError, MeshError


def test_registered_with_dsmk_defaults(faust_mesh):
    feats = geofeat.compute(faust_mesh, "shot", cache=False)
    assert feats.shape == (faust_mesh.n_vertices, 192)
    assert feats.dtype == np.float32 and np.isfinite(feats).all()
    np.testing.assert_allclose(np.linalg.norm(feats, axis=1), 1.0, atol=1e-5)
    dsmk = SHOT(recipe="dsmk").get_params()
    assert dsmk == SHOT().get_params() == SHOT(radius=0.3, n_bins=5).get_params()  # one cache entry
    assert dsmk.items() >= SHOT_RECIPES["dsmk"].items()
    assert SHOT(recipe="dsmk", radius=0.4).get_params() == {**dsmk, "radius": 0.4}


def test_length_follows_bins_and_volumes():
    mesh = bumpy(subdivisions=3)
    feats = geofeat.compute(mesh, "shot", cache=False, radius=0.6, n_bins=7, double_volumes_sectors=False)
    assert feats.shape == (mesh.n_vertices, 16 * 8)


def test_cached_like_the_others(isolated_cache):
    mesh = bumpy(subdivisions=2)
    first = geofeat.compute(mesh, "shot", radius=0.8)
    second = geofeat.compute(mesh, "shot", radius=0.8)
    np.testing.assert_array_equal(first, second)


@pytest.mark.parametrize(
    ("params", "match"),
    [
        ({"radius": 0.0}, "radius"),
        ({"radius": -1.0}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"n_bins": 0}, "n_bins"),
        ({"use_interpolation": 1}, "use_interpolation"),
        ({"radius_unit": "percent"}, "radius_unit"),
        ({"cloud_normals": "guess"}, "cloud_normals"),
    ],
)
def test_bad_parameters(params, match):
    with pytest.raises(DescriptorError, match=match):
        SHOT(**params)


def test_unknown_recipe():
    with pytest.raises(DescriptorError, match="recipe"):
        SHOT(recipe="nope")


def test_rigid_motion_invariant():
    mesh = bumpy(subdivisions=3)
    moved = Mesh(Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).apply(np.array(mesh.verts)) + [0.5, -2.0, 1.0], mesh.faces)
    a, rep = shot_descriptors(mesh.verts, SHOT().normals(mesh), 0.7)
    b = geofeat.compute(moved, "shot", cache=False, radius=0.7)
    keep = ~rep["sign_tie"]
    np.testing.assert_allclose(a[keep], b[keep], atol=1e-5)


def test_relative_radius():
    mesh = bumpy(subdivisions=3)
    big = Mesh(mesh.verts * 3.0, mesh.faces)
    for unit, scale in (("sqrt_area", np.sqrt(big.area())), ("diameter", big.bbox_diagonal())):
        descriptor = SHOT(radius=0.15, radius_unit=unit)
        assert descriptor.absolute_radius(big) == pytest.approx(0.15 * scale)
        relative = geofeat.compute(big, descriptor, cache=False)
        absolute = geofeat.compute(big, "shot", cache=False, radius=descriptor.absolute_radius(big))
        np.testing.assert_array_equal(relative, absolute)


def test_chunks_give_the_same_features():
    mesh = bumpy(subdivisions=3)
    normals = SHOT().normals(mesh)
    whole, _ = shot_descriptors(mesh.verts, normals, 0.5)
    chunked, _ = shot_descriptors(mesh.verts, normals, 0.5, chunk_size=7)
    np.testing.assert_allclose(whole, chunked, atol=1e-12)


def test_point_cloud_normals_estimated_or_zero(caplog):
    mesh = sphere(subdivisions=3)
    cloud = Mesh(mesh.verts)
    with caplog.at_level(logging.INFO, logger="geofeat.descriptors.shot"):
        estimated = geofeat.compute(cloud, "shot", cache=False, radius=0.5)
    assert "normals are estimated" in caplog.text
    on_mesh = geofeat.compute(mesh, "shot", cache=False, radius=0.5)
    # estimated normals point outward like the faces: the same histograms up to the estimate's error
    assert np.abs(estimated - on_mesh).max() < 0.1
    zero = geofeat.compute(cloud, "shot", cache=False, radius=0.5, cloud_normals="zero")
    per_bin = np.abs(zero).reshape(len(zero), 32, 6).sum(axis=(0, 1))
    assert per_bin[[2, 3]].sum() > 0 and per_bin[[0, 1, 4, 5]].sum() == 0  # cos = 0: the middle bins
    with pytest.raises(DescriptorError, match="point cloud"):
        SHOT(radius_unit="sqrt_area").absolute_radius(cloud)


def test_too_few_neighbours_zero_rows_with_warning(caplog):
    mesh = bumpy(subdivisions=3)
    edge = np.linalg.norm(mesh.verts[mesh.faces[:, 0]] - mesh.verts[mesh.faces[:, 1]], axis=1)
    radius = float(np.median(edge)) * 1.2
    with caplog.at_level(logging.WARNING, logger="geofeat.descriptors.shot"):
        feats = geofeat.compute(mesh, "shot", cache=False, radius=radius)
    zero = ~feats.any(axis=1)
    assert zero.any() and not zero.all()
    assert "fewer than 5 neighbours" in caplog.text
    assert np.isfinite(feats).all()


def test_radius_too_small_for_every_vertex():
    with pytest.raises(DescriptorError, match="raise the radius"):
        geofeat.compute(bumpy(subdivisions=2), "shot", cache=False, radius=1e-4)


def test_min_neighbors_above_five():
    mesh = bumpy(subdivisions=3)
    counts = cKDTree(mesh.verts).query_ball_point(mesh.verts, 0.3, return_length=True) - 1
    limit = int(np.median(counts))
    feats = geofeat.compute(mesh, "shot", cache=False, radius=0.3, min_neighbors=limit)
    zero = ~feats.any(axis=1)
    assert zero.any()
    assert (counts[zero] < limit).all()


def test_duplicate_points_defined_with_warning(caplog):
    mesh = bumpy(subdivisions=2)
    verts = np.concatenate([mesh.verts, mesh.verts[:10]])
    cloud = Mesh(verts)
    with caplog.at_level(logging.WARNING, logger="geofeat.descriptors.shot"):
        feats = geofeat.compute(cloud, "shot", cache=False, radius=0.8)
    assert "duplicate" in caplog.text
    assert np.isfinite(feats).all() and feats.any(axis=1).all()


def test_all_neighbours_too_close_gives_zero_row(caplog):
    # a tight cluster (all within 1e-3) next to a regular grid: the reference gives NaN rows there
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 12), np.linspace(0, 1, 12), [0.0]), -1).reshape(-1, 3)
    cluster = np.array([5.0, 5.0, 5.0]) + np.random.default_rng(0).normal(scale=1e-4, size=(8, 3))
    with caplog.at_level(logging.WARNING, logger="geofeat.descriptors.shot"):
        feats = geofeat.compute(Mesh(np.concatenate([grid, cluster])), "shot", cache=False, radius=0.3)
    assert not feats[-8:].any()
    assert np.isfinite(feats).all()
    assert "closer than 1e-3" in caplog.text


def test_tiny_mesh_refused():
    mesh = bumpy(subdivisions=2)
    tiny = Mesh(mesh.verts * 1e-4, mesh.faces)  # every neighbour within 1e-3: nothing binned anywhere
    with pytest.raises(DescriptorError, match="scale it up"):
        geofeat.compute(tiny, "shot", cache=False, radius=0.3, radius_unit="diameter")


def test_flat_patch_is_finite():
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 15), np.linspace(0, 1, 15), [0.0]), -1).reshape(-1, 3)
    feats = geofeat.compute(Mesh(grid), "shot", cache=False, radius=0.3)
    assert np.isfinite(feats).all() and feats.any(axis=1).all()


def test_nan_vertices_refused():
    verts = sphere(subdivisions=1).verts.copy()
    verts[3] = np.nan
    with pytest.raises(MeshError):
        geofeat.compute(Mesh(verts), "shot", cache=False)
    assert issubclass(MeshError, GeofeatError)


def test_some_vertices_only():
    mesh = bumpy(subdivisions=3)
    normals = SHOT().normals(mesh)
    whole, report = shot_descriptors(mesh.verts, normals, 0.5)
    picked = np.array([7, 3, 100, 641])
    some, some_report = shot_descriptors(mesh.verts, normals, 0.5, queries=picked)
    np.testing.assert_allclose(some, whole[picked], atol=1e-12)
    np.testing.assert_array_equal(some_report["sign_tie"], report["sign_tie"][picked])


def test_a_head_takes_shot_by_name():
    from geofeat.adapters.heads import make_head
    from geofeat.datasets.records import ShapePair
    from geofeat.geometry import make_partial

    mesh = bumpy(0, 3)
    partial = make_partial(mesh, "cuts", seed=0)
    pair = ShapePair(x=mesh, y=partial.mesh, map_yx=np.asarray(partial.vertex_map, dtype=np.int64), protocol="p2f")
    head = make_head("nn", descriptor="shot", descriptor_params={"radius": 0.3})
    assert head.features(mesh).shape == (mesh.n_vertices, 192)
    match = head.match(pair)
    assert np.mean(match.map_yx == pair.map_yx) > 0.5  # nearest SHOT rows find most of the cut-out vertices


@pytest.mark.parametrize("far", [None, 1e9])
def test_neighbours_are_those_within_the_radius(far):
    # a far point makes the shape span more than 2**20 radii: the grid's cells grow past the radius
    points = np.random.default_rng(1).uniform(-1, 1, size=(2000, 3))
    if far is not None:
        points = np.concatenate([points, [[far, 0.0, 0.0]]])
    radius = 0.2
    _, report = shot_descriptors(points, np.zeros_like(points), radius, return_frames=True)
    expected = cKDTree(points).query_ball_point(points, radius, return_length=True) - 1  # the vertex itself excluded
    np.testing.assert_array_equal(report["frames"].n_neighbors, expected)


def test_arrays_that_do_not_fit_are_refused():
    points = np.random.default_rng(0).uniform(-1, 1, size=(50, 3))
    with pytest.raises(DescriptorError, match="queries"):
        shot_descriptors(points, np.zeros_like(points), 0.5, queries=np.array([0, 50]))
    with pytest.raises(DescriptorError, match="normals"):
        shot_descriptors(points, np.zeros((49, 3)), 0.5)
    with pytest.raises(DescriptorError, match="flip_axes"):
        shot_descriptors(points, np.zeros_like(points), 0.5, flip_axes=np.zeros(3))
