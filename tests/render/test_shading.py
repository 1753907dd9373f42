import numpy as np
import pytest
import torch
from shapes import sphere

from geofeat.errors import RenderError
from geofeat.render import (
    PhongSettings,
    official_grid_cameras,
    orbit_cameras,
    rasterize,
    render_phong,
    shade_phong,
    vertex_normals,
)


def facing_quad(size=1.0):
    """A square in the plane z = 0, counter-clockwise seen from +z (normal +z), split into 8 x 8 x 2 faces."""
    n = 9
    xs = np.linspace(-size, size, n)
    grid_x, grid_y = np.meshgrid(xs, xs)
    verts = np.stack([grid_x.ravel(), grid_y.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            i = r * n + c
            faces += [[i, i + 1, i + n + 1], [i, i + n + 1, i + n]]
    return verts, np.array(faces)


def expected_phong(cos_angle, settings=None):
    """Closed form for a flat surface lit from the camera: L = V, so V . R = 2 cos^2 - 1."""
    settings = settings or PhongSettings()
    cos_angle = np.asarray(cos_angle)[..., None]
    highlight = np.clip(2 * cos_angle**2 - 1, 0, None) * (cos_angle > 0)
    lit = np.array(settings.ambient) + np.array(settings.diffuse) * np.clip(cos_angle, 0, None)
    return lit * np.array(settings.vertex_color) + np.array(settings.specular) * highlight**settings.shininess


def test_quad_facing_the_camera_gets_the_geolora_colour():
    verts, faces = facing_quad(3.0)  # fills the 90 degree view
    cams = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], 33, device="cpu")  # on +z, looking at the centre
    images, fragments = render_phong(verts, faces, cams)
    # centre pixel: head-on, 0.8 * (0.6 + 0.4) + 0.01 in red/green, 0.8 * (0.6 + 0.5) + 0.01 in blue
    np.testing.assert_allclose(images[0, 16, 16].numpy(), [0.81, 0.81, 0.89], atol=1e-4)
    # every covered pixel follows the closed form with its own angle to the light
    foreground = fragments.foreground[0]
    points = cams.unproject(cams.pixel_centers(torch.float64)[foreground], fragments.depth[0][foreground].double())[0]
    to_camera = cams.position[0] - points
    cos_angle = (to_camera[:, 2] / to_camera.norm(dim=-1)).numpy()
    np.testing.assert_allclose(images[0][foreground].numpy(), expected_phong(cos_angle), atol=1e-5)
    assert cos_angle.min() < 0.8  # the test covers oblique pixels too, where the highlight has faded


def test_background_is_white_and_settings_change_it():
    verts, faces = facing_quad(0.3)
    cams = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], 16, device="cpu")
    images, fragments = render_phong(verts, faces, cams)
    assert (images[0][~fragments.foreground[0]] == 1.0).all()
    black = PhongSettings(background=(0.0, 0.0, 0.0))
    images = shade_phong(fragments, verts, faces, cams, black)
    assert (images[0][~fragments.foreground[0]] == 0.0).all()


def test_back_face_without_culling_gets_ambient_light_only():
    verts, faces = facing_quad()
    behind = orbit_cameras(np.zeros(3), 2.0, [0.0], [180.0], 17, device="cpu")
    from geofeat.render import RasterSettings

    images, fragments = render_phong(verts, faces, behind, RasterSettings(cull_backfaces=False))
    assert fragments.foreground[0, 8, 8]
    np.testing.assert_allclose(images[0, 8, 8].numpy(), [0.48, 0.48, 0.48], atol=1e-6)


def test_vertex_colours_are_interpolated():
    verts, faces = facing_quad()
    cams = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], 17, device="cpu")
    colours = np.tile([0.2, 0.5, 1.0], (len(verts), 1))
    images, _ = render_phong(verts, faces, cams, vertex_colors=colours)
    expected = (np.array([0.6, 0.6, 0.6]) + np.array([0.4, 0.4, 0.5])) * colours[0] + 0.01
    np.testing.assert_allclose(images[0, 8, 8].numpy(), expected, atol=1e-4)
    with pytest.raises(RenderError, match="vertex_colors"):
        render_phong(verts, faces, cams, vertex_colors=colours[:5])


def test_vertex_normals_are_area_weighted_and_unit():
    mesh = sphere(2)
    normals = vertex_normals(torch.as_tensor(mesh.verts.copy()), torch.as_tensor(mesh.faces.copy()))
    radial = torch.as_tensor(mesh.verts.copy())
    radial = radial / radial.norm(dim=-1, keepdim=True)
    assert ((normals * radial).sum(dim=-1) > 0.99).all()
    # a vertex shared by a big and a small face: the big face's normal dominates
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0.1], [0, 0.1, 0.0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [0, 4, 3]])
    big = torch.tensor([0, 0, 1.0], dtype=torch.float64)  # cross product of face 0: twice its area (0.5) times +z
    small = torch.linalg.cross(verts[4] - verts[0], verts[3] - verts[0])
    torch.testing.assert_close(vertex_normals(verts, faces)[0], (big + small) / (big + small).norm())


def test_faust_images_look_like_the_official_ones(faust_mesh):
    cams = official_grid_cameras(faust_mesh, 4, image_size=(64, 48), device="cpu")
    images, fragments = render_phong(faust_mesh, None, cams)
    assert images.shape == (4, 64, 48, 3) and images.dtype == torch.float32
    foreground = fragments.foreground
    assert (images[~foreground] == 1.0).all()
    shaded = images[foreground]
    assert shaded.min() >= 0.48 - 1e-6 and shaded.max() <= 0.89 + 1e-6  # ambient-only .. head-on blue
    assert (shaded[:, 2] >= shaded[:, 0]).all()  # the blue tint of the diffuse light


def test_views_shaded_together_equal_views_shaded_one_at_a_time(faust_mesh):
    cams = official_grid_cameras(faust_mesh, 4, image_size=(64, 48), device="cpu")
    fragments = rasterize(faust_mesh, None, cams)
    together = shade_phong(fragments, faust_mesh, None, cams)
    for view in range(len(cams)):
        alone = fragments._make(field[view : view + 1] for field in fragments)
        assert torch.equal(shade_phong(alone, faust_mesh, None, cams[view : view + 1]), together[view : view + 1])


def test_settings_and_fragments_are_checked():
    with pytest.raises(RenderError, match="three"):
        PhongSettings(ambient=(0.5, 0.5))
    with pytest.raises(RenderError, match="shininess"):
        PhongSettings(shininess=-1)
    verts, faces = facing_quad(0.3)
    cams = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], 16, device="cpu")
    fragments = rasterize(verts, faces, cams)
    other = orbit_cameras(np.zeros(3), 2.0, [0.0], [0.0], 8, device="cpu")
    with pytest.raises(RenderError, match="do not match"):
        shade_phong(fragments, verts, faces, other)
