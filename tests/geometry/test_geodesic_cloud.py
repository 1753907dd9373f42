"""Geodesics on point clouds: the heat method on points against known distances, and bad clouds."""

import logging

import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry.geodesic import area_normalisation, distances_from, geodesic_matrix
from geofeat.geometry.geodesic_cloud import MIN_HEAT_POINTS, cloud_area, cloud_layout
from geofeat.geometry.geodesic_memory import GeodesicEntries, evaluation_distances
from geofeat.geometry.geodesic_store import GeodesicStore


def sphere_cloud(n: int, seed: int = 0) -> Mesh:
    """``n`` seeded points uniform on the unit sphere."""
    points = np.random.default_rng(seed).normal(size=(n, 3))
    return Mesh(points / np.linalg.norm(points, axis=1, keepdims=True), name=f"sphere_cloud{n}")


def relative_errors(found: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """|found - reference| / reference where the reference is not 0 (the sources themselves)."""
    away = reference > 1e-9
    return np.abs(found - reference)[away] / reference[away]


def test_a_faust_r_shape_as_a_cloud_agrees_with_the_mesh_geodesics(faust_dir):
    mesh = geofeat.load_mesh(faust_dir / "off" / "tr_reg_080.off")
    cloud = Mesh(mesh.verts, name="tr_reg_080_points")
    sources = np.random.default_rng(0).choice(mesh.n_vertices, 40, replace=False)
    on_points = distances_from(cloud, sources)  # the heat method on points: the default on a cloud
    against_heat = relative_errors(on_points, distances_from(mesh, sources, "heat"))
    against_dijkstra = relative_errors(on_points, distances_from(mesh, sources, "dijkstra"))
    # typical points agree within about a percent; the mean is pulled up by shortcuts where two
    # body parts come close (the 30 nearest points of a hand reach the thigh)
    assert np.median(against_heat) < 0.03 and against_heat.mean() < 0.12
    assert np.median(against_dijkstra) < 0.08 and against_dijkstra.mean() < 0.15
    assert abs(cloud_area(cloud) / mesh.area() - 1) < 0.08


def test_on_a_sphere_and_on_a_plane_the_distances_are_the_known_ones():
    cloud = sphere_cloud(1500)
    sources = [0, 7, 300]
    exact = np.arccos(np.clip(cloud.verts[sources] @ cloud.verts.T, -1, 1))
    assert relative_errors(distances_from(cloud, sources, "heat"), exact).mean() < 0.05
    assert abs(cloud_area(cloud) / (4 * np.pi) - 1) < 0.01
    flat = Mesh(np.c_[np.random.default_rng(1).random((900, 2)), np.zeros(900)], name="flat")  # a flat cloud is a surface
    straight = np.linalg.norm(flat.verts[sources][:, None] - flat.verts[None], axis=2)
    assert relative_errors(distances_from(flat, sources), straight).mean() < 0.05


def test_all_pairs_on_a_cloud_are_symmetric_normalised_cached_and_agree_with_single_sources():
    cloud = sphere_cloud(300, seed=2)
    dist = geodesic_matrix(cloud)
    assert dist.dtype == np.float32 and dist.shape == (300, 300) and not dist.flags.writeable
    np.testing.assert_array_equal(dist, dist.T)
    assert (np.diag(dist) == 0).all() and np.isfinite(dist).all()
    assert geodesic_matrix(cloud) is dist  # cached by content
    raw = geodesic_matrix(cloud, "heat", normalize=False)
    np.testing.assert_allclose(dist, raw * area_normalisation(cloud), rtol=1e-5)
    rows = distances_from(cloud, [5, 9, 5])  # one heat solve each: the matrix is their symmetrised form
    np.testing.assert_array_equal(rows[0], rows[2])
    np.testing.assert_allclose(rows[:2], raw[[5, 9]], rtol=0.1, atol=0.02)
    with pytest.raises(MeshError, match="no edges to run Dijkstra on; use method='heat'|it has no edges"):
        distances_from(cloud, [0], "dijkstra")


def test_the_store_and_the_streamed_entries_give_the_matrix_of_a_cloud(tmp_path):
    cloud = sphere_cloud(200, seed=3)
    store = GeodesicStore(tmp_path / "geodesics")
    stored = store.load(cloud)
    np.testing.assert_array_equal(stored, geodesic_matrix(cloud, cache=False))
    assert store.path(cloud) is not None and store.get(cloud) is not None
    entries = evaluation_distances(cloud, limit=1)  # far below one matrix: only the entries read
    assert isinstance(entries, GeodesicEntries)
    rows, cols = np.array([0, 3, 150, 199]), np.array([7, 3, 20, 0])
    entries[rows, cols]
    entries.worst_case(np.array([4]))
    entries.compute()
    np.testing.assert_allclose(entries[rows, cols], stored[rows, cols], rtol=1e-6)
    np.testing.assert_allclose(entries.worst_case(np.array([4])), [stored[4].max()], rtol=1e-6)


def test_duplicate_points_share_their_distances(caplog):
    base = sphere_cloud(200, seed=4)
    cloud = Mesh(np.r_[base.verts, base.verts[[3, 3, 10]]], name="with_duplicates")
    with caplog.at_level(logging.WARNING):
        dist = geodesic_matrix(cloud, normalize=False)
    assert "3 point(s) repeat another point" in caplog.text
    layout = cloud_layout(cloud)
    assert layout.n_duplicates == 3 and layout.points.shape == (200, 3)
    np.testing.assert_array_equal(dist[200], dist[3])
    assert dist[3, 200] == dist[200, 201] == 0 and dist[202, 10] == 0
    np.testing.assert_allclose(dist[:200, :200], geodesic_matrix(base, normalize=False), rtol=1e-6)


def test_an_isolated_point_is_a_piece_of_its_own(caplog):
    base = sphere_cloud(250, seed=5)
    cloud = Mesh(np.r_[base.verts, [[10.0, 10.0, 10.0]]], name="with_outlier")
    with caplog.at_level(logging.WARNING):
        dist = geodesic_matrix(cloud, normalize=False)
    assert "1 point(s) in 1 piece(s)" in caplog.text and "outliers" in caplog.text
    assert np.isinf(dist[250, :250]).all() and np.isinf(dist[:250, 250]).all() and dist[250, 250] == 0
    np.testing.assert_allclose(dist[:250, :250], geodesic_matrix(base, normalize=False), rtol=1e-6)
    assert cloud_area(cloud) == pytest.approx(cloud_area(base))  # the outlier adds no area


def test_two_clouds_far_apart_are_infinitely_far_from_each_other():
    base = sphere_cloud(120, seed=6)
    cloud = Mesh(np.r_[base.verts, base.verts + 20.0], name="two_spheres")
    dist = geodesic_matrix(cloud, normalize=False)
    assert np.isinf(dist[:120, 120:]).all() and np.isfinite(dist[:120, :120]).all()
    np.testing.assert_allclose(dist[:120, :120], dist[120:, 120:], rtol=1e-6)  # the same sphere, moved


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (sphere_cloud(MIN_HEAT_POINTS - 1).verts, f"needs at least {MIN_HEAT_POINTS}"),
        (np.repeat(sphere_cloud(1).verts, 500, axis=0), "1 distinct point"),
        (np.c_[np.linspace(0, 1, 200), np.zeros(200), np.zeros(200)], "lie on a line"),
        (
            np.repeat(100.0 * np.random.default_rng(0).normal(size=(10, 3)), 5, axis=0)
            + np.random.default_rng(1).random((50, 3)),
            "falls apart",
        ),
    ],
    ids=["too-small", "one-point-repeated", "a-line", "scattered"],
)
def test_clouds_the_heat_method_cannot_use_raise_a_clear_error(points, message):
    cloud = Mesh(points, name="bad")
    with pytest.raises(MeshError, match=message):
        geodesic_matrix(cloud)
    with pytest.raises(geofeat.GeofeatError):
        cloud_area(cloud)


def test_a_mesh_keeps_its_own_methods_and_errors():
    mesh = bumpy(0, 1)
    with pytest.raises(MeshError, match="triangle mesh"):
        cloud_layout(mesh)
    np.testing.assert_array_equal(geodesic_matrix(mesh), geodesic_matrix(mesh, "dijkstra"))
