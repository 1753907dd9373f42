import time

import numpy as np
import pytest
import torch
from shapes import bumpy, sphere
from trimesh.ray.ray_triangle import ray_triangle_id

import geofeat
from geofeat.errors import RenderError
from geofeat.render import Cameras, RasterSettings, look_at_rotation, official_grid_cameras, orbit_cameras, rasterize
from geofeat.render.rasterizer import _chunks


class BoxIndex:
    """The two calls trimesh's ray casting makes on an rtree index, answered with numpy (no rtree needed)."""

    def __init__(self, triangles):
        self.lo, self.hi = triangles.min(axis=1), triangles.max(axis=1)
        self.bounds = np.concatenate([self.lo.min(axis=0), self.hi.max(axis=0)])

    def intersection(self, box):
        box = np.asarray(box)
        return np.flatnonzero(np.all(self.lo <= box[3:], axis=1) & np.all(self.hi >= box[:3], axis=1))


@pytest.fixture(scope="module")
def faust_views(faust_mesh):
    cams = official_grid_cameras(faust_mesh, 9, image_size=(96, 128), device="cpu")
    return cams, rasterize(faust_mesh, None, cams, RasterSettings(cull_backfaces=False))


def sample_pixels(fragments, view, rng, n_fore=60, n_back=20):
    foreground = fragments.pix_to_face[view].numpy() >= 0
    fy, fx = np.nonzero(foreground)
    by, bx = np.nonzero(~foreground)
    i = rng.choice(len(fy), n_fore, replace=False)
    j = rng.choice(len(by), n_back, replace=False)
    return np.concatenate([fy[i], by[j]]), np.concatenate([fx[i], bx[j]])


def surface_points(mesh, fragments):
    """Points interpolated with the rasterizer's barycentrics, shape (N, H, W, 3) float64."""
    corners = torch.as_tensor(mesh.verts[mesh.faces])[fragments.pix_to_face.clamp(min=0)]
    return (fragments.bary.double()[..., None] * corners).sum(dim=-2)


def test_faces_agree_with_trimesh_ray_casting(faust_mesh, faust_views):
    cams, fragments = faust_views
    triangles = faust_mesh.verts[faust_mesh.faces]
    index = BoxIndex(triangles)
    rng = np.random.default_rng(0)
    for view in range(0, 9, 2):
        rows, cols = sample_pixels(fragments, view, rng)
        pixels = np.stack([cols + 0.5, rows + 0.5], axis=1)
        on_ray = cams[view].unproject(pixels, np.ones(len(pixels)))[0].numpy()
        origins = np.tile(cams.position[view].numpy(), (len(pixels), 1))
        hit_face, hit_ray, hit_point = ray_triangle_id(triangles, origins, on_ray - origins, tree=index, multiple_hits=False)
        expected = np.full(len(pixels), -1)
        expected[hit_ray] = hit_face
        np.testing.assert_array_equal(fragments.pix_to_face[view].numpy()[rows, cols], expected)
        # depth is the hit point's distance along the optical axis
        axis_distance = (hit_point - cams.position[view].numpy()) @ cams.rotation[view, 2].numpy()
        np.testing.assert_allclose(fragments.depth[view].numpy()[rows[hit_ray], cols[hit_ray]], axis_distance, rtol=1e-5)


def test_barycentrics_reconstruct_the_hit_point(faust_mesh, faust_views):
    cams, fragments = faust_views
    foreground = fragments.foreground
    points = surface_points(faust_mesh, fragments)
    projected = cams.project(points.reshape(9, -1, 3))
    pixels = projected.pixels.reshape(*foreground.shape, 2)
    centres = cams.pixel_centers(torch.float64).expand_as(pixels)
    assert (pixels[foreground] - centres[foreground]).abs().max() < 1e-3  # the point lies on the pixel's ray
    depth = projected.depth.reshape(foreground.shape)
    torch.testing.assert_close(fragments.depth[foreground].double(), depth[foreground], rtol=1e-6, atol=0)
    bary = fragments.bary[foreground]
    assert bary.min() >= 0 and torch.allclose(bary.sum(dim=-1), torch.ones(len(bary)), atol=1e-6)


def test_background_and_dtypes(faust_views):
    _, fragments = faust_views
    background = ~fragments.foreground
    assert fragments.pix_to_face.dtype == torch.int64
    assert fragments.bary.dtype == torch.float32 and fragments.depth.dtype == torch.float32
    assert fragments.bary.shape == (9, 96, 128, 3)
    assert background.any() and fragments.foreground.any()
    assert torch.isinf(fragments.depth[background]).all()
    assert (fragments.bary[background] == 0).all()
    assert torch.isfinite(fragments.depth[fragments.foreground]).all()


def tilted_quad(tilt_degrees=75.0):
    """A unit square through the origin, facing +z before being tilted about x; two counter-clockwise faces."""
    t = np.radians(tilt_degrees)
    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float)
    turn = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    return corners @ turn.T, np.array([[0, 1, 2], [0, 2, 3]])


def test_barycentrics_are_perspective_correct():
    verts, faces = tilted_quad(60.0)  # depth from 0.7 to 2.5
    cams = orbit_cameras(np.zeros(3), 1.6, [0.0], [0.0], 64, fov_degrees=120.0, device="cpu")
    fragments = rasterize(verts, faces, cams)
    foreground = fragments.foreground[0]
    assert foreground.sum() > 200
    corners = torch.as_tensor(verts[faces])[fragments.pix_to_face[0][foreground]]
    points = (fragments.bary[0][foreground].double()[..., None] * corners).sum(dim=1)
    pixels = cams.project(points).pixels[0]
    centres = cams.pixel_centers(torch.float64)[foreground]
    assert (pixels - centres).abs().max() < 1e-3
    # screen-space (affine) barycentrics would miss the rays on this steep plane: the test can fail
    screen = cams.project(corners.reshape(-1, 3)).pixels[0].reshape(-1, 3, 2)
    affine = _screen_barycentrics(screen, centres)
    affine_points = (affine[..., None] * corners).sum(dim=1)
    assert (cams.project(affine_points).pixels[0] - centres).abs().max() > 0.05


def _screen_barycentrics(tri, p):
    a, b, c = tri.unbind(1)
    cross = lambda u, v: u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]  # noqa: E731
    area = cross(b - a, c - a)
    return torch.stack([cross(c - b, p - b), cross(a - c, p - c), cross(b - a, p - a)], dim=-1) / area[:, None]


def test_back_faces_are_culled():
    verts, faces = tilted_quad(0.0)  # faces +z
    front = orbit_cameras(np.zeros(3), 3.0, [0.0], [0.0], 16, device="cpu")  # at +z
    back = orbit_cameras(np.zeros(3), 3.0, [0.0], [180.0], 16, device="cpu")  # at -z
    assert rasterize(verts, faces, front).foreground.any()
    assert not rasterize(verts, faces, back).foreground.any()
    assert rasterize(verts, faces, back, RasterSettings(cull_backfaces=False)).foreground.any()


def test_culling_keeps_only_faces_turned_to_the_camera(faust_mesh, faust_views):
    cams, unculled = faust_views
    culled = rasterize(faust_mesh, None, cams)
    # a closed surface seen from outside: the nearest face is always a front face
    assert torch.equal(culled.pix_to_face, unculled.pix_to_face)
    triangles = torch.as_tensor(faust_mesh.verts[faust_mesh.faces])
    normals = torch.linalg.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0], dim=-1)
    for view in range(9):
        faces = culled.pix_to_face[view][culled.foreground[view]].unique()
        to_camera = cams.position[view] - triangles[faces, 0]
        assert ((normals[faces] * to_camera).sum(dim=-1) > 0).all()


def test_nearest_face_wins_and_faces_behind_the_camera_are_dropped():
    near, faces = tilted_quad(0.0)
    far = near * 3 + np.array([0.0, 0.0, -1.0])
    verts = np.concatenate([far, near])
    cams = orbit_cameras(np.zeros(3), 3.0, [0.0], [0.0], 32, device="cpu")
    fragments = rasterize(verts, np.concatenate([faces, faces + 4]), cams)
    centre = fragments.pix_to_face[0, 16, 16]
    assert centre >= 2  # one of the near faces
    assert fragments.depth[0, 16, 16] == pytest.approx(3.0)
    behind = orbit_cameras(np.zeros(3), 0.5, [0.0], [0.0], 32, device="cpu")  # inside the far quad's span
    assert not rasterize(far + np.array([0, 0, 2.0]), faces, behind).foreground.any()


def test_batching_gives_the_same_result_as_one_pass(faust_mesh):
    cams = official_grid_cameras(faust_mesh, 9, image_size=(40, 56), device="cpu")
    one_pass = rasterize(faust_mesh, None, cams, RasterSettings(views_per_batch=9, max_candidates=1 << 30))
    chunked = rasterize(faust_mesh, None, cams, RasterSettings(views_per_batch=2, max_candidates=500))
    assert torch.equal(one_pass.pix_to_face, chunked.pix_to_face)
    assert torch.equal(one_pass.bary, chunked.bary)
    assert torch.equal(one_pass.depth, chunked.depth)
    separate = [rasterize(faust_mesh, None, cams[i]) for i in range(9)]
    assert torch.equal(torch.cat([f.pix_to_face for f in separate]), one_pass.pix_to_face)


def test_chunks_respect_the_candidate_budget():
    count = torch.tensor([5, 5, 5, 30, 1, 1, 1, 9, 2])
    chunks = _chunks(count, 10)
    assert chunks[0].start == 0 and chunks[-1].stop == len(count)
    assert all(a.stop == b.start for a, b in zip(chunks[:-1], chunks[1:], strict=True))
    for chunk in chunks:
        assert count[chunk].sum() <= 10 or chunk.stop - chunk.start == 1


def test_sphere_depth_matches_the_analytic_surface():
    mesh = sphere(4)
    cams = official_grid_cameras(mesh, 4, image_size=48, device="cpu")
    fragments = rasterize(mesh, None, cams)
    points = surface_points(mesh, fragments)[fragments.foreground]
    radius = points.norm(dim=-1)
    assert radius.max() <= 1 + 1e-9 and radius.min() > 0.995  # flat facets sit just inside the sphere


def test_nine_views_of_faust_at_224_take_seconds_at_most(faust_mesh):
    cams = official_grid_cameras(faust_mesh, 9, image_size=224, device="cpu")
    start = time.perf_counter()
    fragments = rasterize(faust_mesh, None, cams)
    assert time.perf_counter() - start < 5.0
    assert fragments.foreground.float().mean() > 0.03


def test_bad_input_is_refused():
    cams = orbit_cameras(np.zeros(3), 3.0, [0.0], [0.0], 8, device="cpu")
    verts, faces = tilted_quad(0.0)
    with pytest.raises(RenderError, match="point cloud"):
        rasterize(geofeat.Mesh(verts), None, cams)
    with pytest.raises(RenderError, match=r"\[0, 3\]"):
        rasterize(verts, faces + 1, cams)
    with pytest.raises(RenderError, match="integer"):
        rasterize(verts, faces.astype(float), cams)
    with pytest.raises(RenderError, match="faces are required"):
        rasterize(verts, None, cams)
    with pytest.raises(RenderError, match="positive integer"):
        RasterSettings(max_candidates=0)
    with pytest.raises(RenderError, match="Cameras"):
        rasterize(verts, faces, look_at_rotation(np.array([[0.0, 0.0, 3.0]]), np.zeros(3)))


def test_mesh_and_arrays_give_the_same_fragments():
    mesh = bumpy(3, 2)
    cams = official_grid_cameras(mesh, 4, image_size=24, device="cpu")
    a = rasterize(mesh, None, cams)
    b = rasterize(torch.as_tensor(mesh.verts.copy()).float(), torch.as_tensor(mesh.faces.copy()), cams)
    assert (a.pix_to_face != b.pix_to_face).float().mean() < 0.01  # float32 vertices: ties may flip
    assert isinstance(cams, Cameras)


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.mark.parametrize("device", DEVICES)
def test_same_code_on_every_device(faust_mesh, device):
    cams = official_grid_cameras(faust_mesh, 4, image_size=(32, 40), device="cpu")
    reference = rasterize(faust_mesh, None, cams)
    on_device = rasterize(faust_mesh, None, cams.to(device))
    assert on_device.pix_to_face.device.type == device
    assert (on_device.pix_to_face.cpu() != reference.pix_to_face).float().mean() < 1e-3
    same = on_device.pix_to_face.cpu() == reference.pix_to_face
    torch.testing.assert_close(on_device.depth.cpu()[same], reference.depth[same], rtol=1e-5, atol=0)
