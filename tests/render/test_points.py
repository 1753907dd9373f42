"""The point renderer: discs z-buffered per pixel, on hand-made clouds, against the mesh rasterizer and on every device."""

import numpy as np
import pytest
import torch
from shapes import sphere

import geofeat
from geofeat.errors import RenderError
from geofeat.render import (
    Cameras,
    SplatSettings,
    make_cameras,
    rasterize,
    rasterize_points,
    render_points_phong,
    splat_points,
)
from geofeat.render.points import local_spacing, splat_radii

SIZE = 9  # pixels; the camera's focal length is SIZE / 2, its axis through the centre of pixel (4, 4)


def axis_camera(size: int = SIZE) -> Cameras:
    """One camera at the origin looking down +z (image x = world x, image y = world y), 90 degree field of view."""
    return Cameras(np.eye(3)[None], np.zeros((1, 3)), image_size=size, device="cpu")


def test_the_nearer_point_wins_whatever_its_index():
    camera = axis_camera()
    far, near = [0.0, 0.0, 3.0], [0.0, 0.0, 2.0]
    radii = np.array([1.5, 0.5])  # on screen: far 4.5 * 1.5 / 3 = 2.25 px, near 4.5 * 0.5 / 2 = 1.125 px
    for order in ([far, near], [near, far]):
        fragments = rasterize_points(np.array(order), camera, radii=radii if order[0] is far else radii[::-1].copy())
        near_index = order.index(near)
        assert fragments.pix_to_point[0, 4, 4] == near_index and fragments.depth[0, 4, 4] == 2.0
        assert fragments.pix_to_point[0, 4, 6] == 1 - near_index and fragments.depth[0, 4, 6] == 3.0  # 2 px off: far only
        assert fragments.pix_to_point[0, 0, 0] == -1 and fragments.depth[0, 0, 0] == float("inf")


def test_a_disc_covers_exactly_the_pixel_centres_within_its_screen_radius():
    camera = axis_camera(size=15)
    point = np.array([[0.31, -0.17, 2.5]])
    fragments = rasterize_points(point, camera, SplatSettings(radius=0.9))
    f = camera.focal_length
    x, y = f * point[0, 0] / point[0, 2] + 7.5, f * point[0, 1] / point[0, 2] + 7.5
    rows, cols = np.mgrid[0:15, 0:15] + 0.5
    expected = (cols - x) ** 2 + (rows - y) ** 2 <= (f * 0.9 / 2.5) ** 2
    assert expected.sum() > 20
    np.testing.assert_array_equal(fragments.pix_to_point[0].numpy() == 0, expected)


def test_a_point_behind_the_camera_is_not_drawn():
    camera = axis_camera()
    behind = rasterize_points(np.array([[0.0, 0.0, -2.0], [0.1, 0.0, -1.0]]), camera, SplatSettings(radius=1.0))
    assert bool((behind.pix_to_point == -1).all()) and bool(torch.isinf(behind.depth).all())
    both = rasterize_points(np.array([[0.0, 0.0, -0.5], [0.0, 0.0, 4.0]]), camera, SplatSettings(radius=1.0))
    drawn = both.pix_to_point[both.pix_to_point >= 0]
    assert drawn.numel() > 0 and bool((drawn == 1).all())


def test_equal_depths_go_to_the_lower_index():
    camera = axis_camera()
    fragments = rasterize_points(np.array([[0.0, 0.0, 5.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.0]]), camera, SplatSettings(radius=0.5))
    assert fragments.pix_to_point[0, 4, 4] == 1


def random_cloud(n: int = 300, seed: int = 0) -> geofeat.Mesh:
    return geofeat.Mesh(np.random.default_rng(seed).normal(size=(n, 3)) * [1.0, 0.6, 0.3], None, name="blob")


def test_chunking_does_not_change_the_result():
    cloud = random_cloud()
    cameras = make_cameras(cloud, 4, layout="official", image_size=24, device="cpu")
    whole = rasterize_points(cloud, cameras)
    chunked = rasterize_points(cloud, cameras, SplatSettings(max_candidates=5, views_per_batch=1))
    assert bool((whole.pix_to_point >= 0).float().mean() > 0.1)
    assert torch.equal(whole.pix_to_point, chunked.pix_to_point)
    assert torch.equal(whole.depth, chunked.depth)


def test_splat_points_lie_on_the_pixel_rays_and_on_their_discs():
    cloud = random_cloud()
    cameras = make_cameras(cloud, 4, layout="uniform", image_size=24, device="cpu")
    fragments = rasterize_points(cloud, cameras)
    pixels = torch.nonzero(fragments.pix_to_point >= 0)
    points = splat_points(cloud, cameras, fragments.pix_to_point, pixels)  # (M, 3) float64
    owners = fragments.pix_to_point[pixels[:, 0], pixels[:, 1], pixels[:, 2]].numpy()
    for view in range(len(cameras)):
        mine = (pixels[:, 0] == view).numpy()
        projected = cameras[view].project(points[mine])
        centres = pixels[mine][:, [2, 1]].double() + 0.5
        torch.testing.assert_close(projected.pixels[0], centres, rtol=0, atol=1e-9)
        own_depth = cameras[view].world_to_camera(cloud.verts[owners[mine]])[0, :, 2]
        torch.testing.assert_close(projected.depth[0], own_depth, rtol=1e-12, atol=0)
    offset = np.linalg.norm(points.numpy() - cloud.verts[owners], axis=1)
    assert (offset <= splat_radii(cloud)[owners] * (1 + 1e-9)).all()


def test_radii_follow_the_local_spacing_within_the_clamp():
    rng = np.random.default_rng(1)
    dense = rng.uniform(size=(400, 3)) * [1.0, 1.0, 0.01]
    lonely = np.array([[40.0, 0.0, 0.0]])
    verts = np.concatenate([dense, lonely, dense[:1]])  # an isolated point and a duplicate
    spacing = local_spacing(verts)
    median = np.median(spacing)
    assert spacing[400] == pytest.approx(2.0 * median, rel=1e-3)  # the isolated point: clamped
    assert spacing[401] == spacing[0] > 0  # duplicates share their spacing and do not shrink it
    np.testing.assert_allclose(splat_radii(verts), 0.5 * spacing)
    np.testing.assert_allclose(splat_radii(verts, SplatSettings(radius=0.2)), 0.2)


def test_bad_clouds_get_clear_errors():
    camera = axis_camera()
    with pytest.raises(RenderError, match="distinct point"):
        rasterize_points(np.array([[0.0, 0.0, 2.0]] * 3), camera)
    with pytest.raises(RenderError, match="NaN"):
        rasterize_points(np.array([[0.0, np.nan, 2.0], [0.0, 0.0, 2.0]]), camera)
    with pytest.raises(RenderError, match="radii"):
        rasterize_points(np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0]]), camera, radii=np.ones(3))
    with pytest.raises(RenderError, match="radius"):
        SplatSettings(radius=0.0)
    # one point with a given radius is a defined result
    one = rasterize_points(np.array([[0.0, 0.0, 2.0]]), camera, SplatSettings(radius=0.5))
    assert one.pix_to_point[0, 4, 4] == 0


def test_splats_are_shaded_with_their_normal_turned_to_the_camera():
    camera = axis_camera()
    point = np.array([[0.0, 0.0, 2.0]])
    for normal in ([0.0, 0.0, -1.0], [0.0, 0.0, 1.0]):  # facing the camera, and away from it
        images = render_points_phong(point, camera, SplatSettings(radius=0.5), normals=np.array([normal])).images
        torch.testing.assert_close(images[0, 4, 4], torch.tensor([0.81, 0.81, 0.89]), rtol=0, atol=1e-6)  # head-on
        torch.testing.assert_close(images[0, 0, 0], torch.ones(3))  # background


def test_discs_on_a_sphere_cover_what_the_mesh_rasterizer_covers():
    """Discs of 0.5 x the spacing leave no hole; the silhouette grows by about a disc radius.

    A disc on the rim reaches ``r`` beyond the sphere's outline, so the points' foreground is
    the sphere's, of radius 1, grown to about ``1 + r``, and the IoU is about
    ``1 / (1 + r) ** 2`` (0.85 for the 642 vertices of a level-3 icosphere, r = 0.087).
    """
    mesh = sphere(3)
    cameras = make_cameras(mesh, 6, layout="uniform", image_size=48, device="cpu")
    mesh_foreground = rasterize(mesh, None, cameras).pix_to_face >= 0
    point_foreground = rasterize_points(mesh, cameras).pix_to_point >= 0
    radius = float(splat_radii(mesh).mean())
    iou = float((mesh_foreground & point_foreground).sum() / (mesh_foreground | point_foreground).sum())
    holes = float((mesh_foreground & ~point_foreground).sum() / mesh_foreground.sum())
    assert 0.08 < radius < 0.095
    assert abs(iou - 1 / (1 + radius) ** 2) < 0.03 and iou > 0.8
    assert holes < 0.002


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_same_code_on_every_device(faust_mesh, device):
    cameras = make_cameras(faust_mesh, 4, layout="official", image_size=(32, 40), device="cpu")
    reference = rasterize_points(faust_mesh.verts, cameras)
    on_device = rasterize_points(faust_mesh.verts, cameras.to(device))
    assert on_device.pix_to_point.device.type == device
    assert (on_device.pix_to_point.cpu() != reference.pix_to_point).float().mean() < 1e-3
    same = on_device.pix_to_point.cpu() == reference.pix_to_point
    torch.testing.assert_close(on_device.depth.cpu()[same], reference.depth[same], rtol=1e-6, atol=0)
