"""Evaluating pairs with point clouds: a scan matched to a mesh, a cloud made from a mesh, a bare cloud."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import bumpy

from geofeat import Mesh
from geofeat.datasets import Match, ShapePair
from geofeat.datasets.depth_camera import DepthCamera, scan_mesh
from geofeat.errors import MetricError
from geofeat.evaluation.protocol import evaluate_dataset, evaluate_pair, evaluation_target
from geofeat.evaluation.report import plot_pairs
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.geometry.surface_points import SurfacePoints


def all_true(n: int) -> np.ndarray:
    return np.ones(n, dtype=bool)


def mirror_of(mesh: Mesh) -> np.ndarray:
    """The vertex nearest to each vertex's reflection in the x = mean plane (a stand-in mirror map)."""
    reflected = mesh.verts * [-1, 1, 1] + [2 * mesh.verts[:, 0].mean(), 0, 0]
    return np.linalg.norm(reflected[:, None] - mesh.verts[None], axis=2).argmin(axis=1)


def vertices_as_surface_points(mesh: Mesh) -> SurfacePoints:
    """Each vertex of ``mesh`` as a surface point: a face it is a corner of, with weight 1 on it."""
    face_of, corner_of = np.zeros(mesh.n_vertices, dtype=np.int64), np.zeros(mesh.n_vertices, dtype=np.int64)
    for corner in range(3):
        face_of[mesh.faces[:, corner]] = np.arange(len(mesh.faces))
        corner_of[mesh.faces[:, corner]] = corner
    return SurfacePoints(mesh, face_of, np.eye(3)[corner_of])


def test_a_scan_matched_to_its_full_mesh_is_measured_on_the_mesh():
    mesh = bumpy(0, 3)
    scan = scan_mesh(mesh, DepthCamera(image_size=48), seed=1)
    truth = scan.surface.nearest_corner
    pair = ShapePair(x=mesh, y=scan.cloud, map_yx=truth, map_yx_sym=mirror_of(mesh)[truth], y_surface=scan.surface)
    assert evaluate_pair(pair, Match(truth, all_true(len(truth)))).geodesic_error == 0.0
    guess = np.random.default_rng(0).integers(0, mesh.n_vertices, len(truth))
    record = evaluate_pair(pair, Match(guess, all_true(len(truth))))
    np.testing.assert_allclose(record.errors, geodesic_matrix(mesh)[truth, guess].astype(np.float64))
    assert record.chirality_accuracy is not None


def test_a_cloud_made_from_a_mesh_is_measured_with_the_geodesics_of_that_mesh():
    mesh = bumpy(1, 3)
    as_mesh = ShapePair(
        x=mesh, y=mesh.renamed("y"), map_yx=np.arange(mesh.n_vertices), map_yx_sym=mirror_of(mesh), protocol="f2f"
    )
    cloud = Mesh(mesh.verts, name="x_points")
    as_cloud = ShapePair(
        x=cloud,
        y=mesh.renamed("y"),
        map_yx=as_mesh.map_yx,
        map_yx_sym=as_mesh.map_yx_sym,
        protocol="f2f",
        x_surface=vertices_as_surface_points(mesh),
        corr_x=np.arange(0, mesh.n_vertices, 3),
        corr_y=np.arange(0, mesh.n_vertices, 3),
    )
    assert evaluation_target(as_cloud) is mesh and evaluation_target(as_mesh) is mesh
    guess = Match(np.random.default_rng(2).integers(0, mesh.n_vertices, mesh.n_vertices), all_true(mesh.n_vertices))
    on_mesh, on_cloud = evaluate_pair(as_mesh, guess), evaluate_pair(as_cloud, guess)
    np.testing.assert_array_equal(on_cloud.errors, on_mesh.errors)
    assert on_cloud.chirality_accuracy == on_mesh.chirality_accuracy
    template = evaluate_pair(as_cloud, guess, protocol="template")
    np.testing.assert_array_equal(template.errors, on_mesh.errors[::3])
    with pytest.raises(MetricError, match="one surface point per point of x"):
        evaluate_pair(
            ShapePair(x=Mesh(mesh.verts[:-1]), y=mesh, map_yx=np.arange(mesh.n_vertices) % 10, x_surface=as_cloud.x_surface),
            guess,
        )
    with pytest.raises(MetricError, match="indices of the points of x"):
        evaluate_pair(as_cloud, Match(np.full(mesh.n_vertices, mesh.n_vertices), all_true(mesh.n_vertices)))


def test_a_bare_cloud_is_measured_with_the_heat_method_on_its_points(tmp_path):
    cloud = Mesh(bumpy(2, 3).verts, name="points")
    n = cloud.n_vertices
    pair = ShapePair(x=cloud, y=cloud.renamed("points_y"), map_yx=np.arange(n), map_yx_sym=mirror_of(cloud), protocol="f2f")
    guess = Match(np.random.default_rng(3).integers(0, n, n), all_true(n))
    record = evaluate_pair(pair, guess)
    np.testing.assert_allclose(record.errors, geodesic_matrix(cloud)[np.arange(n), guess.map_yx].astype(np.float64))
    assert evaluate_pair(pair, Match(pair.map_yx_sym, all_true(n))).chirality_accuracy == 0.0
    # through the store, and through streamed entries below a tiny memory bound: the same records
    store = GeodesicStore(tmp_path / "geodesics")
    stored, _ = evaluate_dataset([pair], lambda i, p: guess, store=store, progress=False)
    streamed, _ = evaluate_dataset([pair], lambda i, p: guess, memory=1, progress=False)
    assert store.path(cloud) is not None
    np.testing.assert_allclose(stored[0].errors, record.errors, rtol=1e-6)
    np.testing.assert_allclose(streamed[0].errors, record.errors, rtol=1e-6)


def test_pictures_draw_point_clouds(tmp_path):
    mesh = bumpy(0, 3)
    scan = scan_mesh(mesh, DepthCamera(image_size=48), seed=2)
    pair = ShapePair(x=mesh, y=scan.cloud, map_yx=scan.surface.nearest_corner, protocol="p2f")
    plot_pairs([(pair, pair.map_yx, "truth", 0.0)], tmp_path / "pairs.png")
    assert (tmp_path / "pairs.png").read_bytes()[:4] == b"\x89PNG"
