"""Point clouds through the one multi-view path: drawn as discs, lifted to their points, filled like meshes."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree
from shapes import bumpy
from tiny_models import tiny_dinov2, tiny_dinov3

import geofeat
from geofeat.backbones import load_backbone
from geofeat.errors import RenderError
from geofeat.multiview import multiview_features
from geofeat.multiview.backproject import Backprojector
from geofeat.multiview.neighbours import PointGrid
from geofeat.render import make_cameras, rasterize_points

IMAGE_SIZE = 64


@pytest.fixture(scope="module")
def dinov3_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_dinov3")
    tiny_dinov3().save_pretrained(folder)
    return folder


@pytest.fixture(scope="module")
def dinov3_backbone(dinov3_folder):
    return load_backbone(dinov3_folder, kind="dinov3", device="cpu")


@pytest.fixture(scope="module")
def dinov2_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_dinov2")
    tiny_dinov2().save_pretrained(folder)
    return folder


def cloud_of(mesh: geofeat.Mesh) -> geofeat.Mesh:
    return geofeat.Mesh(mesh.verts, None, name=f"{mesh.name}_cloud")


def test_dinov2_features_of_a_cloud_have_the_shape_and_are_cached(dinov2_folder, isolated_cache):
    cloud = cloud_of(bumpy(0, 2))
    params = {"weights": str(dinov2_folder), "views": 4, "image_size": 56, "camera_layout": "uniform", "device": "cpu"}
    features = geofeat.compute(cloud, "dinov2", **params)
    assert features.shape == (cloud.n_vertices, 32) and features.dtype == np.float32 and features.flags["C_CONTIGUOUS"]
    assert np.isfinite(features).all() and features.std(axis=0).mean() > 0
    again = geofeat.compute(cloud, "dinov2", **params)  # a cache hit
    np.testing.assert_array_equal(features, again)
    assert len(geofeat.FeatureCache().entries()) == 1


@pytest.mark.parametrize("backproject", ["ball", "face", "ball_last"])
def test_unseen_points_are_filled_as_on_meshes(dinov3_backbone, backproject):
    cloud = cloud_of(bumpy(1, 2))
    cameras = make_cameras(cloud, 2, layout="uniform", image_size=IMAGE_SIZE, device="cpu")  # two views: a side is unseen
    zero = multiview_features(cloud, cameras, dinov3_backbone, backproject=backproject, fill="zero")
    nearest = multiview_features(cloud, cameras, dinov3_backbone, backproject=backproject, fill="nearest")
    seen = zero.seen.numpy()
    assert 0.05 < seen.mean() < 0.95  # the ball at 64 pixels misses most points: fill matters
    torch.testing.assert_close(zero.seen, nearest.seen)
    assert bool((zero.features[~zero.seen] == 0).all())
    torch.testing.assert_close(nearest.features[zero.seen], zero.features[zero.seen])
    _, source = cKDTree(cloud.verts[seen]).query(cloud.verts[~seen])
    torch.testing.assert_close(nearest.features[~zero.seen], zero.features[zero.seen][source])


def test_face_mode_gives_each_pixel_to_its_own_point(dinov3_backbone):
    cloud = cloud_of(bumpy(2, 2))
    cameras = make_cameras(cloud, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    result = multiview_features(cloud, cameras, dinov3_backbone, backproject="face", fill="zero")
    drawn = torch.unique(rasterize_points(cloud, cameras).pix_to_point)
    expected = torch.zeros(cloud.n_vertices, dtype=torch.bool)
    expected[drawn[drawn >= 0]] = True
    torch.testing.assert_close(result.seen, expected)


def test_ball_plans_of_a_cloud_need_the_pixel_points():
    cloud = cloud_of(bumpy(0, 1))
    backprojector = Backprojector(cloud.verts, None, "ball")
    fragments = rasterize_points(cloud, make_cameras(cloud, 1, layout="uniform", image_size=16, device="cpu"))
    with pytest.raises(RenderError, match="splat_points"):
        backprojector.plan(fragments.pix_to_point, None)


def test_the_grid_finds_exactly_the_pairs_a_kd_tree_finds(monkeypatch):
    rng = np.random.default_rng(3)
    verts = rng.uniform(size=(500, 3)) * [1.0, 0.5, 0.2]
    verts = np.concatenate([verts, verts[:5]])  # duplicates are both found
    queries = rng.uniform(-0.1, 1.1, size=(300, 3)) * [1.0, 0.5, 0.2]  # some outside the cloud's box
    radius = 0.08
    monkeypatch.setattr(PointGrid, "CHUNK_PAIRS", 200)  # many chunks of queries and of pairs
    rows, cols = PointGrid(verts, radius, "cpu").pairs_within(torch.as_tensor(queries), radius)
    assert bool((torch.diff(cols) >= 0).all())
    found = set(zip(cols.tolist(), rows.tolist(), strict=True))
    expected = {(q, v) for q, near in enumerate(cKDTree(verts).query_ball_point(queries, radius)) for v in near}
    assert found == expected and len(found) > 300


def test_duplicates_and_flat_clouds_get_defined_features(dinov3_backbone):
    mesh = bumpy(3, 2)
    duplicated = geofeat.Mesh(np.concatenate([mesh.verts, mesh.verts[:10]]), None, name="duplicated")
    cameras = make_cameras(duplicated, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    for backproject in ("ball", "face"):
        features = multiview_features(duplicated, cameras, dinov3_backbone, backproject=backproject).features
        torch.testing.assert_close(features[-10:], features[:10])  # a point and its copy: the same features
    grid = np.stack(np.meshgrid(np.linspace(0, 1, 20), np.linspace(0, 1, 20)), -1).reshape(-1, 2)
    flat = geofeat.Mesh(np.column_stack([grid, np.zeros(len(grid))]), None, name="flat")
    cameras = make_cameras(flat, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    result = multiview_features(flat, cameras, dinov3_backbone, backproject="face")
    assert bool(torch.isfinite(result.features).all()) and float(result.seen.float().mean()) > 0.5


def test_clouds_of_one_to_three_points(dinov3_backbone):
    one = geofeat.Mesh(np.array([[0.0, 0.0, 0.0]]), None, name="one")
    with pytest.raises(RenderError, match="coincide"):
        make_cameras(one, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    for n in (2, 3):
        few = geofeat.Mesh(np.eye(3)[:n], None, name=f"{n} points")
        cameras = make_cameras(few, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
        result = multiview_features(few, cameras, dinov3_backbone, backproject="face")
        assert tuple(result.features.shape) == (n, 32) and bool(result.seen.all())
        assert bool(torch.isfinite(result.features).all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("mode", ["ball", "face", "ball_last"])
def test_cuda_cloud_features_equal_the_cpu(faust_mesh, dinov3_folder, mode):
    cloud = cloud_of(faust_mesh)
    results = []
    for device in ("cpu", "cuda"):
        backbone = load_backbone(dinov3_folder, kind="dinov3", device=device)
        cameras = make_cameras(cloud, 4, layout="uniform", image_size=IMAGE_SIZE, device=device)
        result = multiview_features(cloud, cameras, backbone, backproject=mode, fill="zero")
        results.append([t.cpu() for t in result])
    assert (results[0][1] != results[1][1]).float().mean() < 0.01  # a disc edge may round the other way
    same = results[0][1] & results[1][1]
    close = (results[0][0][same] - results[1][0][same]).abs().amax(dim=1) < 1e-3
    assert float(close.float().mean()) > 0.98  # the rest: a pixel on a disc edge went to a neighbour


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_grid_equals_the_cpu():
    rng = np.random.default_rng(4)
    verts, queries = rng.uniform(size=(2000, 3)), torch.as_tensor(rng.uniform(size=(500, 3)))
    cpu = PointGrid(verts, 0.1, "cpu").pairs_within(queries, 0.1)
    cuda = PointGrid(verts, 0.1, "cuda").pairs_within(queries.cuda(), 0.1)
    as_set = [set(zip(c.tolist(), r.tolist(), strict=True)) for r, c in (cpu, cuda)]
    assert as_set[0] == as_set[1]
