"""The dinov2/dinov3 descriptors end to end, on tiny random backbones and real FAUST_r shapes."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from shapes import bumpy
from tiny_models import tiny_dinov3
from transformers import DINOv3ViTModel

import geofeat
from geofeat.multiview import multiview_features
from geofeat.render import Cameras, make_cameras


@pytest.fixture(scope="module")
def tiny_dinov3_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_dinov3")
    tiny_dinov3().save_pretrained(folder)
    return folder


def test_identity_backbone_recovers_vertex_positions(faust_mesh):
    """Cameras, rasterizer, depth, unprojection and back-projection together."""
    from geofeat.multiview.backproject import VertexFeatureAccumulator
    from geofeat.render import render_phong

    cameras = make_cameras(faust_mesh, 9, layout="uniform", image_size=192, device="cpu")
    accumulator = VertexFeatureAccumulator(faust_mesh.verts, faust_mesh.faces, 3, mode="ball")
    for start in range(0, len(cameras), 3):
        views = cameras[start : start + 3]
        rendering = render_phong(faust_mesh, None, views)
        depth = rendering.fragments.depth  # (B, H, W), +inf on background
        n, h, w = depth.shape
        pixels = views.pixel_centers().reshape(1, h * w, 2).expand(n, -1, -1)
        points = views.unproject(pixels, depth.reshape(n, h * w)).reshape(n, h, w, 3)
        points = torch.where(torch.isfinite(points), points, torch.zeros_like(points))
        accumulator.add(points.float(), rendering.fragments.pix_to_face, rendering.fragments.bary)
    features, seen = accumulator.result(fill="zero")
    assert seen.mean() > 0.8
    error = np.linalg.norm(features[seen] - faust_mesh.verts[seen], axis=1)
    assert error.max() < 1.5 * accumulator.radius  # averaged points lie within the ball around the vertex
    assert error.mean() < 0.5 * accumulator.radius


def test_dinov3_descriptor_on_a_tiny_random_model(tiny_dinov3_folder, isolated_cache):
    mesh = bumpy(0, 2)
    params = {"weights": str(tiny_dinov3_folder), "views": 4, "image_size": 64, "batch_size": 2, "camera_layout": "uniform"}
    features = geofeat.compute(mesh, "dinov3", **params)
    assert features.shape == (mesh.n_vertices, 32) and features.dtype == np.float32 and features.flags["C_CONTIGUOUS"]
    assert np.isfinite(features).all() and features.std(axis=0).mean() > 0
    again = geofeat.compute(mesh, "dinov3", **params)  # a cache hit
    np.testing.assert_array_equal(features, again)
    assert len(geofeat.FeatureCache().entries()) == 1
    face = geofeat.compute(mesh, "dinov3", cache=False, **(params | {"backproject": "face"}))
    assert face.shape == features.shape and not np.allclose(face, features)


def test_weights_digest_is_part_of_the_cache_key(tiny_dinov3_folder, tmp_path):
    from geofeat.descriptors.registry import make_descriptor

    a = make_descriptor("dinov3", weights=str(tiny_dinov3_folder))
    model = DINOv3ViTModel.from_pretrained(tiny_dinov3_folder)
    with torch.no_grad():
        model.norm.weight[0] += 1e-3
    model.save_pretrained(tmp_path / "changed")
    b = make_descriptor("dinov3", weights=str(tmp_path / "changed"))
    assert a.weights_digest() != b.weights_digest()
    assert a.params_json() != b.params_json()  # and the path differs too
    assert "device" not in a.params_json()


def test_rotating_mesh_and_cameras_together_leaves_features_unchanged(tiny_dinov3_folder):
    from geofeat.backbones import load_backbone

    backbone = load_backbone(str(tiny_dinov3_folder), kind="dinov3", device="cpu")
    mesh = bumpy(3, 2)
    rotation = Rotation.from_euler("xyz", [30, -50, 70], degrees=True).as_matrix()
    turned = geofeat.Mesh(mesh.verts @ rotation.T, mesh.faces)
    cameras = make_cameras(mesh, 4, layout="uniform", image_size=64, device="cpu")
    rot = torch.as_tensor(rotation, dtype=cameras.rotation.dtype)
    turned_cameras = Cameras(
        rotation=cameras.rotation @ rot.T,
        position=cameras.position @ rot.T,
        image_size=cameras.image_size,
        fov_degrees=cameras.fov_degrees,
        device="cpu",
    )

    a, seen_a = (t.numpy() for t in multiview_features(mesh, cameras, backbone, fill="zero", batch_size=2))
    b, seen_b = (t.numpy() for t in multiview_features(turned, turned_cameras, backbone, fill="zero", batch_size=2))
    assert (seen_a == seen_b).mean() > 0.99
    both = seen_a & seen_b
    np.testing.assert_allclose(a[both], b[both], atol=2e-3)


def test_missing_weights_names_the_parameter_and_variable(monkeypatch):
    monkeypatch.delenv("GEOFEAT_DINOV3_WEIGHTS", raising=False)
    with pytest.raises(geofeat.GeofeatError, match="GEOFEAT_DINOV3_WEIGHTS") as info:
        geofeat.compute(bumpy(0, 1), "dinov3", cache=False)
    assert "weights" in str(info.value)


def test_bad_parameters():
    with pytest.raises(geofeat.DescriptorError, match="backproject"):
        geofeat.compute(bumpy(0, 1), "dinov2", backproject="splat")
    with pytest.raises(geofeat.DescriptorError, match="views"):
        geofeat.compute(bumpy(0, 1), "dinov2", views=0)


def test_compute_prepared_refuses_what_prepare_did_not_make():
    from geofeat.descriptors.dino import DINOv2

    with pytest.raises(geofeat.DescriptorError, match="prepare"):
        DINOv2().compute_prepared(bumpy(0, 1), "views")


def test_recipes_apply_end_to_end_and_keep_explicit_parameters(tiny_dinov3_folder, isolated_cache):
    """``recipe="reference"`` is the reference recipe end to end; explicit parameters override the recipe's."""
    from geofeat.backbones import load_backbone
    from geofeat.errors import DescriptorError
    from geofeat.multiview.pipeline import RECIPES

    mesh = bumpy(1, 2)
    # on the CPU, as the backbone compared with: device "auto" would take a GPU where there is one
    params = {"weights": str(tiny_dinov3_folder), "views": 4, "image_size": 64, "batch_size": 2, "device": "cpu"}
    reference = geofeat.compute(mesh, "dinov3", recipe="reference", **params)
    backbone = load_backbone(str(tiny_dinov3_folder), kind="dinov3", device="cpu")
    cameras = make_cameras(mesh, 4, image_size=64, device="cpu")
    with torch.no_grad():
        expected, _ = multiview_features(mesh, cameras, backbone, recipe=RECIPES["reference"], fill="nearest")
    np.testing.assert_array_equal(reference, expected.numpy())
    default = geofeat.compute(mesh, "dinov3", **params)
    assert not np.allclose(default, reference, atol=1e-3)
    overridden = geofeat.compute(mesh, "dinov3", recipe="reference", backproject="ball", cache=False, **params)
    with torch.no_grad():
        expected, _ = multiview_features(mesh, cameras, backbone, recipe=RECIPES["reference"], backproject="ball")
    np.testing.assert_array_equal(overridden, expected.numpy())
    assert len(geofeat.FeatureCache().entries()) == 2  # the recipe is part of the cache key
    with pytest.raises(DescriptorError, match="recipe"):
        geofeat.compute(mesh, "dinov3", recipe="dsmk", **params)  # DeepShapeMatchingKit's recipe is for DINOv2


def test_an_instance_loads_its_backbone_once_for_every_mesh(tiny_dinov3_folder, monkeypatch):
    """What the removed LRU of compute did for names, the caller's instance does: one load for many meshes."""
    import geofeat.backbones

    loads = []
    real = geofeat.backbones.load_backbone
    monkeypatch.setattr(geofeat.backbones, "load_backbone", lambda *a, **k: loads.append(a) or real(*a, **k))
    params = {"weights": str(tiny_dinov3_folder), "views": 2, "image_size": 32, "camera_layout": "uniform"}
    descriptor = geofeat.make_descriptor("dinov3", **params)
    meshes = [bumpy(0, 2), bumpy(1, 2)]
    for mesh in meshes + meshes:  # computed, then read back from the cache
        geofeat.compute(mesh, descriptor)
    assert len(loads) == 1
    geofeat.compute(meshes[0], "dinov3", **params)  # by name: a new instance, which loads its own backbone
    assert len(loads) == 2
