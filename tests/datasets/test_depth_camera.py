import numpy as np
import pytest
import torch
from shapes import bumpy, sphere

import geofeat
from geofeat.datasets.depth_camera import DepthCamera, scan_mesh
from geofeat.errors import MeshError, RenderError
from geofeat.render.camera_layouts import look_at_rotation
from geofeat.render.cameras import Cameras

EXACT = DepthCamera(image_size=64, depth_noise=0.0, dropout_start_degrees=None)


def camera_of(scan, settings: DepthCamera) -> Cameras:
    rotation = look_at_rotation(scan.eye[None], scan.target)
    return Cameras(rotation, scan.eye[None], settings.image_size, settings.fov_degrees, device="cpu")


def test_without_noise_every_point_is_its_surface_point_seen_at_its_pixel_centre():
    mesh = bumpy(1, 3)
    scan = scan_mesh(mesh, EXACT, seed=4)
    assert scan.cloud.is_point_cloud and scan.cloud.name == "bumpy1_scan" and scan.surface.mesh is mesh
    np.testing.assert_allclose(scan.cloud.verts, scan.surface.positions(), atol=1e-12)
    projected = camera_of(scan, EXACT).project(torch.as_tensor(np.array(scan.cloud.verts))).pixels[0].numpy()
    np.testing.assert_allclose(projected, scan.pixels[:, ::-1] + 0.5, atol=1e-3)  # (x, y) = (column, row) + 0.5
    assert len(np.unique(scan.pixels, axis=0)) == scan.cloud.n_vertices  # one point per pixel, in image order
    assert (np.diff(scan.pixels[:, 0] * 64 + scan.pixels[:, 1]) > 0).all()
    # every point is on a face the camera sees, and nearer than the far side of the shape
    assert scan.seen_faces()[scan.surface.face].mean() > 0.95


def test_noise_moves_points_along_their_rays_only():
    mesh = sphere(3)
    settings = DepthCamera(image_size=48, depth_noise=0.01, dropout_start_degrees=None)
    scan = scan_mesh(mesh, settings, seed=0)
    moved = scan.cloud.verts - scan.surface.positions()
    rays = scan.surface.positions() - scan.eye
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    np.testing.assert_allclose(np.cross(moved, rays), 0.0, atol=1e-12)
    assert np.std(np.einsum("pi,pi->p", moved, rays)) == pytest.approx(0.01 * mesh.bbox_diagonal(), rel=0.15)


def test_grazing_dropout_removes_points_where_the_surface_turns_away():
    mesh = sphere(4)
    exact = scan_mesh(mesh, DepthCamera(image_size=64, depth_noise=0.0, dropout_start_degrees=None), seed=1)
    dropped = scan_mesh(mesh, DepthCamera(image_size=64, depth_noise=0.0, dropout_start_degrees=30.0), seed=1)

    def incidence(scan):  # angle between each point's ray and its face's normal, degrees
        corners = mesh.verts[mesh.faces[scan.surface.face]]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        rays = scan.surface.positions() - scan.eye
        cosine = np.abs(np.einsum("pi,pi->p", normals, rays)) / np.linalg.norm(normals, axis=1) / np.linalg.norm(rays, axis=1)
        return np.degrees(np.arccos(np.clip(cosine, 0, 1)))

    kept = {tuple(pixel) for pixel in dropped.pixels.tolist()}
    assert kept < {tuple(pixel) for pixel in exact.pixels.tolist()}  # the same rays, fewer points
    assert all(tuple(pixel) in kept for pixel in exact.pixels[incidence(exact) < 30].tolist())  # always kept up to the start
    assert (incidence(dropped) > 60).mean() < 0.7 * (incidence(exact) > 60).mean()


def test_a_scan_is_reproducible_from_its_seed_and_changes_with_it():
    mesh = bumpy(2, 3)
    first, again, other = scan_mesh(mesh, seed=7), scan_mesh(mesh, seed=7), scan_mesh(mesh, seed=8)
    np.testing.assert_array_equal(first.cloud.verts, again.cloud.verts)
    np.testing.assert_array_equal(first.surface.face, again.surface.face)
    assert not np.array_equal(first.eye, other.eye)


def test_the_default_camera_scans_a_faust_r_body_into_a_few_thousand_points(faust_dir):
    mesh = geofeat.load_mesh(faust_dir / "off" / "tr_reg_080.off")
    sizes = [scan_mesh(mesh, seed=seed).cloud.n_vertices for seed in range(3)]
    assert all(1_500 < n < 6_000 for n in sizes), sizes


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"image_size": 0}, "image_size"),
        ({"fov_degrees": 180}, "fov_degrees"),
        ({"elevation_degrees": (-10, 85)}, "elevation_degrees"),
        ({"distance_factor": 0.5}, "distance_factor"),
        ({"depth_noise": -1}, "depth_noise"),
        ({"dropout_start_degrees": 90}, "dropout_start_degrees"),
    ],
)
def test_bad_camera_settings_are_refused(settings, message):
    with pytest.raises(RenderError, match=message):
        DepthCamera(**settings)


def test_settings_round_trip_through_json(tmp_path):
    settings = DepthCamera(image_size=(120, 160), elevation_degrees=(0, 45), dropout_start_degrees=None)
    assert DepthCamera.load(settings.save(tmp_path / "camera.json")) == settings


def test_what_cannot_be_scanned_raises_a_clear_error():
    with pytest.raises(MeshError, match="point cloud"):
        scan_mesh(geofeat.Mesh(np.eye(3)))
    with pytest.raises(MeshError, match="fewer than 100"):
        scan_mesh(sphere(2), DepthCamera(image_size=8))
