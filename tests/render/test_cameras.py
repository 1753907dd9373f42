import dataclasses
import math

import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.errors import RenderError
from geofeat.render import (
    Cameras,
    fibonacci_cameras,
    look_at_rotation,
    make_cameras,
    official_grid_angles,
    official_grid_cameras,
    orbit_cameras,
)
from geofeat.runtime.devices import resolve_device


def bbox(verts):
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    return (lo + hi) / 2, np.linalg.norm(hi - lo)


def pytorch3d_style_frame(position, target):
    """Our camera axes derived independently from pytorch3d's look-at (x left, y up) with up = +y."""
    forward = (target - position) / np.linalg.norm(target - position)
    left = np.cross([0.0, 1.0, 0.0], forward)
    left /= np.linalg.norm(left)
    up = np.cross(forward, left)
    return np.stack([-left, -up, forward])  # ours: x right, y down, z forward


def test_official_grid_follows_the_documented_formula(faust_mesh):
    n_views = 9
    cams = official_grid_cameras(faust_mesh, n_views, image_size=(48, 64), device="cpu")
    target, diagonal = bbox(faust_mesh.verts)
    steps = 3
    for i in range(n_views):
        e = math.radians((i % steps) * 360 / steps)  # elevation varies fastest
        a = math.radians((i // steps) * 360 / steps)
        expected = target + 0.65 * diagonal * np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])
        np.testing.assert_allclose(cams.position[i].numpy(), expected, atol=1e-12)
        np.testing.assert_allclose(cams.rotation[i].numpy(), pytorch3d_style_frame(expected, target), atol=1e-12)
    assert cams.fov_degrees == 90.0
    assert cams.image_size == (48, 64)
    assert cams.focal_length == pytest.approx(24.0)  # min(H, W) / 2 / tan(45 deg)


def test_official_grid_angles_match_linspace_layout():
    elevation, azimuth = official_grid_angles(16)
    values = torch.linspace(0, 360 - 360 / 4, 4, dtype=torch.float64)
    torch.testing.assert_close(elevation, values.repeat(4))
    torch.testing.assert_close(azimuth, torch.repeat_interleave(values, 4))


@pytest.mark.parametrize("n_views", [2, 8, 10, 0])
def test_official_grid_needs_a_perfect_square(n_views):
    with pytest.raises(RenderError, match="perfect square|positive"):
        official_grid_angles(n_views)


@pytest.mark.parametrize(("n_views", "n_distinct"), [(4, 2), (9, 9), (16, 6), (49, 49), (64, 26), (100, 50)])
def test_official_grid_repeats_positions_when_sqrt_n_is_even(n_views, n_distinct):
    cams = official_grid_cameras(bumpy(0, 1), n_views, image_size=8, device="cpu")
    distinct = torch.unique(torch.round(cams.position * 1e6), dim=0)
    assert len(distinct) == n_distinct


def test_official_grid_poles_get_the_documented_frame():
    mesh = bumpy(0, 1)
    cams = official_grid_cameras(mesh, 16, image_size=8, device="cpu")
    elevation, azimuth = official_grid_angles(16)
    target, _ = bbox(mesh.verts)
    for i in torch.nonzero((elevation == 90) | (elevation == 270)).ravel().tolist():
        rotation = cams.rotation[i].numpy()
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        forward = target - cams.position[i].numpy()
        np.testing.assert_allclose(rotation[2], forward / np.linalg.norm(forward), atol=1e-12)
        e, a = math.radians(elevation[i]), math.radians(azimuth[i])
        image_up = -math.sin(e) * np.array([math.sin(a), 0.0, math.cos(a)])
        np.testing.assert_allclose(-rotation[1], image_up, atol=1e-12)


def test_poles_are_the_limit_of_nearby_frames():
    target = np.zeros(3)
    for elevation in (90.0, -90.0):
        pole = orbit_cameras(target, 2.0, [elevation], [30.0], 8, device="cpu")
        near = orbit_cameras(target, 2.0, [elevation - np.sign(elevation) * 1e-4], [30.0], 8, device="cpu")
        np.testing.assert_allclose(pole.rotation.numpy(), near.rotation.numpy(), atol=1e-5)


def test_uniform_layout_has_no_repeated_positions(faust_mesh):
    target, diagonal = bbox(faust_mesh.verts)
    for n_views in (1, 7, 16, 50):
        cams = fibonacci_cameras(faust_mesh, n_views, image_size=8, device="cpu")
        positions = cams.position.numpy()
        np.testing.assert_allclose(np.linalg.norm(positions - target, axis=1), 0.65 * diagonal, rtol=1e-12)
        if n_views > 1:
            gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1) + np.eye(n_views) * 1e9
            # well spread: nearest neighbours are at least half the spacing of n equal caps
            assert gaps.min() > 0.5 * 0.65 * diagonal * np.sqrt(4 * np.pi / n_views) / 2
        forward = target - positions
        np.testing.assert_allclose(
            cams.rotation[:, 2].numpy(), forward / np.linalg.norm(forward, axis=1, keepdims=True), atol=1e-12
        )


def test_make_cameras_dispatches_and_rejects_unknown_layouts():
    mesh = bumpy(0, 1)
    assert len(make_cameras(mesh, 9, layout="official", image_size=8, device="cpu")) == 9
    assert len(make_cameras(mesh, 10, layout="uniform", image_size=8, device="cpu")) == 10
    with pytest.raises(RenderError, match="layout"):
        make_cameras(mesh, 9, layout="random", image_size=8, device="cpu")


def test_random_rotation_about_up_is_seeded_and_rigid():
    mesh = bumpy(0, 1)
    target, _ = bbox(mesh.verts)
    plain = official_grid_cameras(mesh, 9, image_size=8, device="cpu")
    one = official_grid_cameras(mesh, 9, image_size=8, random_rotation=True, seed=3, device="cpu")
    again = official_grid_cameras(mesh, 9, image_size=8, random_rotation=True, seed=3, device="cpu")
    other = official_grid_cameras(mesh, 9, image_size=8, random_rotation=True, seed=4, device="cpu")
    torch.testing.assert_close(one.position, again.position, rtol=0, atol=0)
    assert not torch.allclose(one.position, other.position)
    assert not torch.allclose(one.position, plain.position)
    torch.testing.assert_close(one.position[:, 1], plain.position[:, 1])  # about the vertical axis
    torch.testing.assert_close(
        (one.position - torch.as_tensor(target)).norm(dim=1), (plain.position - torch.as_tensor(target)).norm(dim=1)
    )
    # the turned rig sees the turned shape exactly as the plain rig sees the shape
    angle = math.atan2(float(one.position[0, 0] - target[0]), float(one.position[0, 2] - target[2])) - math.atan2(
        float(plain.position[0, 0] - target[0]), float(plain.position[0, 2] - target[2])
    )
    c, s = math.cos(angle), math.sin(angle)
    turn = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    turned_verts = (mesh.verts - target) @ turn.T + target
    torch.testing.assert_close(one.world_to_camera(turned_verts), plain.world_to_camera(mesh.verts))
    with pytest.raises(RenderError, match="seed"):
        official_grid_cameras(mesh, 9, image_size=8, random_rotation=True, device="cpu")


def test_unproject_inverts_project():
    mesh = bumpy(1, 2)
    cams = fibonacci_cameras(mesh, 5, image_size=(30, 50), device="cpu")
    cams = dataclasses.replace(cams, principal_point=(24.3, 16.1))
    points = np.random.default_rng(0).normal(size=(200, 3)) * 0.3
    projected = cams.project(points)
    assert projected.pixels.shape == (5, 200, 2) and projected.depth.shape == (5, 200)
    assert projected.pixels.dtype == torch.float64
    back = cams.unproject(projected.pixels, projected.depth)
    torch.testing.assert_close(back, torch.as_tensor(points).expand(5, -1, -1), rtol=0, atol=1e-12)
    # float32 in, float32 out
    back32 = cams.unproject(projected.pixels.float(), projected.depth.float())
    assert back32.dtype == torch.float32
    torch.testing.assert_close(back32.double(), back, rtol=0, atol=1e-5)


def test_pixel_convention_x_right_y_down_centres_at_half():
    cams = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], (4, 6), device="cpu")  # at +z, looking at -z
    right, up = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])  # facing -z with y up, +x is on the right
    pixels, depth = cams.project(np.stack([np.zeros(3), 0.5 * right, 0.5 * up]))
    cx, cy = 3.0, 2.0
    torch.testing.assert_close(pixels[0, 0], torch.tensor([cx, cy], dtype=torch.float64))
    assert pixels[0, 1, 0] > cx and pixels[0, 1, 1] == pytest.approx(cy)
    assert pixels[0, 2, 1] < cy and pixels[0, 2, 0] == pytest.approx(cx)
    torch.testing.assert_close(depth[0], torch.full((3,), 2.0, dtype=torch.float64))
    centres = cams.pixel_centers()
    assert centres.shape == (4, 6, 2)
    torch.testing.assert_close(centres[1, 2], torch.tensor([2.5, 1.5]))
    # the field of view spans the shorter side: a point at 45 degrees lands on the top edge
    pixels, _ = cams.project(np.array([[0.0, 2.0, 0.0]]))
    assert float(pixels[0, 0, 1]) == pytest.approx(0.0, abs=1e-12)


def test_cameras_validate_their_input():
    good = look_at_rotation(np.array([[0.0, 0.0, 2.0]]), np.zeros(3))
    with pytest.raises(RenderError, match="orthonormal"):
        Cameras(good * 2, np.zeros((1, 3)), 8, device="cpu")
    with pytest.raises(RenderError, match="det"):
        Cameras(-good, np.zeros((1, 3)), 8, device="cpu")
    with pytest.raises(RenderError, match=r"\(N, 3\)"):
        Cameras(good, np.zeros((2, 3)), 8, device="cpu")
    with pytest.raises(RenderError, match="image_size"):
        Cameras(good, np.zeros((1, 3)), (0, 8), device="cpu")
    with pytest.raises(RenderError, match="fov"):
        Cameras(good, np.zeros((1, 3)), 8, fov_degrees=180, device="cpu")
    with pytest.raises(RenderError, match="up vector"):
        look_at_rotation(np.array([[0.0, 2.0, 0.0]]), np.zeros(3))
    with pytest.raises(RenderError, match="shape"):
        Cameras(good, np.zeros((1, 3)), 8, device="cpu").project(np.zeros((4, 2)))


def test_indexing_keeps_the_view_axis_and_device_auto_resolves():
    cams = official_grid_cameras(bumpy(0, 1), 9, image_size=8, device="auto")
    assert cams.device == resolve_device("auto")
    assert cams.device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert len(cams[3]) == 1 and len(cams[-1]) == 1 and len(cams[2:5]) == 3
    torch.testing.assert_close(cams[-1].position[0], cams.position[8])
    assert cams.to("cpu").device.type == "cpu"
