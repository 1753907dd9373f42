"""The one multi-view feature path: the trainer and the descriptors agree, gradients on or off."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from shapes import bumpy
from tiny_models import tiny_dinov3

import geofeat
from geofeat.backbones import DinoBackbone, load_backbone
from geofeat.errors import RenderError
from geofeat.multiview import multiview_features
from geofeat.multiview.backproject import VertexFeatureAccumulator
from geofeat.render import make_cameras, render_phong
from geofeat.train.config import TrainConfig
from geofeat.train.trainer import GeoLoraTrainer

IMAGE_SIZE = 64


@pytest.fixture(scope="module")
def backbone_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("tiny_dinov3")
    tiny_dinov3().save_pretrained(folder)
    return folder


def _randomize_lora_b(backbone: DinoBackbone, seed: int = 5) -> None:
    """Give the LoRA B matrices (zero after initialisation) random values, as after training."""
    torch.manual_seed(seed)
    with torch.no_grad():
        for name, param in backbone.model.named_parameters():
            if "lora_B" in name:
                param.copy_(torch.randn_like(param) * 0.5)


def _trainer(tmp_path, backbone_folder, backproject: str) -> GeoLoraTrainer:
    config = TrainConfig(
        data="unused",
        out=str(tmp_path / "run"),
        image_size=IMAGE_SIZE,
        backproject=backproject,
        camera_layout="official",
        geodesic_cache=str(tmp_path / "geodesics"),
        progress=False,
        device="cpu",
        validate_every=0,
    )
    backbone = load_backbone(backbone_folder, kind="dinov3", device="cpu")
    trainer = GeoLoraTrainer(config, backbone=backbone, shapes=[bumpy(0, 2)])
    trainer._start_or_resume()  # adds LoRA (B = 0)
    _randomize_lora_b(trainer.backbone)
    return trainer


@pytest.mark.parametrize("backproject, fill", [("ball", "nearest"), ("ball", "zero"), ("face", "nearest")])
def test_trainer_and_geolora_descriptor_give_the_same_features(tmp_path, backbone_folder, backproject, fill):
    """Same shape, views and LoRA: the trainer's features (with and without autograd) equal the descriptor's."""
    trainer = _trainer(tmp_path, backbone_folder, backproject)
    checkpoint = trainer.save_checkpoint()
    mesh = bumpy(1, 3)
    views = 9  # the descriptor encodes them in batches of 4, 4 and 1; the trainer all at once
    training, seen = trainer.mesh_features(mesh, views, fill=fill)
    assert training.requires_grad and training.grad_fn is not None
    with torch.no_grad():
        validation, _ = trainer.mesh_features(mesh, views, fill=fill)
    assert not validation.requires_grad
    served = geofeat.compute(
        mesh,
        "geolora",
        checkpoint=str(checkpoint),
        weights=str(backbone_folder),
        views=views,
        image_size=IMAGE_SIZE,
        camera_layout="official",
        backproject=backproject,
        fill=fill,
        batch_size=4,
        device="cpu",
        cache=False,
    )
    assert served.shape == tuple(training.shape) and served.dtype == np.float32
    assert 0.1 < float(seen.float().mean()) <= 1.0
    assert backproject == "face" or not bool(seen.all())  # ball: some vertices unseen, the fill mode matters
    np.testing.assert_allclose(training.detach().numpy(), served, rtol=0, atol=1e-5)
    np.testing.assert_allclose(validation.numpy(), served, rtol=0, atol=1e-5)
    raw = geofeat.compute(
        mesh,
        "dinov3",
        weights=str(backbone_folder),
        views=views,
        image_size=IMAGE_SIZE,
        backproject=backproject,
        fill=fill,
        device="cpu",
        cache=False,
    )
    assert np.abs(raw - served).max() > 1e-3  # the LoRA is in use (the agreement above is 1e-5)


def test_gradients_reach_the_lora_parameters_only_when_asked(tmp_path, backbone_folder):
    trainer = _trainer(tmp_path, backbone_folder, "face")
    mesh = bumpy(2, 2)
    cameras = make_cameras(mesh, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    with torch.no_grad():  # grad=True wins over the caller's mode
        on = multiview_features(mesh, cameras, trainer.backbone, backproject="face", fill="zero", grad=True)
    lora = [p for name, p in trainer.backbone.model.named_parameters() if "lora_" in name]
    grads = torch.autograd.grad(on.features.square().sum(), lora)
    assert all(torch.isfinite(g).all() for g in grads) and any(bool(g.abs().sum() > 0) for g in grads)
    off = multiview_features(mesh, cameras, trainer.backbone, backproject="face", fill="zero", grad=False)
    assert off.features.grad_fn is None
    torch.testing.assert_close(off.features, on.features.detach(), rtol=0, atol=1e-6)
    torch.testing.assert_close(off.seen, on.seen)


def test_batches_of_views_give_the_same_features(backbone_folder):
    backbone = load_backbone(backbone_folder, kind="dinov3", device="cpu")
    mesh = bumpy(3, 2)
    cameras = make_cameras(mesh, 5, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    one = multiview_features(mesh, cameras, backbone, batch_size=1)
    every = multiview_features(mesh, cameras, backbone)  # all five at once
    torch.testing.assert_close(one.features, every.features, rtol=0, atol=1e-5)
    assert torch.equal(one.seen, every.seen)


@pytest.mark.parametrize("backproject", ["ball", "face"])
def test_foreground_sampling_equals_back_projecting_upsampled_images(backbone_folder, backproject):
    """The features equal those of the former path: whole images upsampled to the render size, then back-projected."""
    backbone = load_backbone(backbone_folder, kind="dinov3", device="cpu")
    mesh = bumpy(4, 3)
    cameras = make_cameras(mesh, 4, layout="official", image_size=IMAGE_SIZE, device="cpu")
    rendering = render_phong(mesh, None, cameras)
    images = backbone.pixel_features(rendering.images)  # (4, 64, 64, C), upsampled and normalised
    whole = VertexFeatureAccumulator(mesh.verts, mesh.faces, backbone.embed_dim, mode=backproject)
    whole.add(images, rendering.fragments.pix_to_face, rendering.fragments.bary)
    expected, expected_seen = whole.result("nearest")
    features, seen = multiview_features(mesh, cameras, backbone, backproject=backproject, batch_size=2)
    np.testing.assert_allclose(features.numpy(), expected, rtol=0, atol=1e-5)
    np.testing.assert_array_equal(seen.numpy(), expected_seen)


def test_no_full_resolution_feature_images(backbone_folder, monkeypatch):
    """The descriptor path never upsamples whole patch grids."""
    import geofeat.backbones.dino as dino

    def refuse(*args, **kwargs):
        raise AssertionError("whole feature images were formed")

    monkeypatch.setattr(dino, "upsample_patch_features", refuse)
    monkeypatch.setattr(dino.DinoBackbone, "pixel_features", refuse)
    features = geofeat.compute(
        bumpy(0, 2), "dinov3", weights=str(backbone_folder), views=4, image_size=IMAGE_SIZE, device="cpu", cache=False
    )
    assert np.isfinite(features).all()


def test_timer_is_charged_with_every_phase(backbone_folder):
    backbone = load_backbone(backbone_folder, kind="dinov3", device="cpu")
    mesh = bumpy(0, 2)
    cameras = make_cameras(mesh, 4, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    calls = []

    def timer(phase):
        calls.append(phase)
        return torch.no_grad()  # any context manager

    multiview_features(mesh, cameras, backbone, batch_size=2, timer=timer)
    # per batch: render, the back-projection plan, the backbone, the sums; then the means
    assert calls == ["render", "backproject", "forward", "backproject"] * 2 + ["backproject"]


def test_bad_input_is_refused(backbone_folder):
    backbone = load_backbone(backbone_folder, kind="dinov3", device="cpu")
    mesh = bumpy(0, 1)
    cameras = make_cameras(mesh, 2, layout="uniform", image_size=IMAGE_SIZE, device="cpu")
    with pytest.raises(RenderError, match="distinct point"):  # a cloud of one point, twice: no disc radius
        multiview_features(geofeat.Mesh(mesh.verts[[0, 0]], None, "cloud"), cameras, backbone)
    with pytest.raises(RenderError, match="fill"):
        multiview_features(mesh, cameras, backbone, fill="mean")
    with pytest.raises(RenderError, match="backproject"):
        multiview_features(mesh, cameras, backbone, backproject="splat")
    with pytest.raises(RenderError, match="batch_size"):
        multiview_features(mesh, cameras, backbone, batch_size=0)


def test_view_batches_pack_the_views_of_several_shapes_in_order():
    from geofeat.multiview.pipeline import ViewSegment, view_batches

    batches = view_batches([9, 4, 4], 7)
    assert batches == [
        [ViewSegment(0, 0, 7)],
        [ViewSegment(0, 7, 9), ViewSegment(1, 0, 4), ViewSegment(2, 0, 1)],
        [ViewSegment(2, 1, 4)],
    ]
    assert view_batches([3], 10) == [[ViewSegment(0, 0, 3)]]
    assert view_batches([2, 0, 1], 1) == [[ViewSegment(0, 0, 1)], [ViewSegment(0, 1, 2)], [ViewSegment(2, 0, 1)]]


@pytest.mark.parametrize("batch_size", [None, 5])
def test_several_shapes_in_one_call_equal_one_call_each(batch_size):
    """Views of three shapes packed into shared backbone calls: each shape's features as when computed alone."""
    from geofeat.multiview.pipeline import multiview_features_many

    backbone = DinoBackbone(tiny_dinov3(), kind="dinov3")
    meshes = [bumpy(0, 2), bumpy(1, 2), bumpy(2, 2)]
    cameras = [
        make_cameras(m, n, layout="official", image_size=IMAGE_SIZE, device="cpu") for m, n in zip(meshes, (9, 4, 4), strict=True)
    ]
    together = multiview_features_many(meshes, cameras, backbone, batch_size=batch_size, fill="zero")
    for mesh, views, many in zip(meshes, cameras, together, strict=True):
        alone = multiview_features(mesh, views, backbone, batch_size=3, fill="zero")
        assert torch.equal(alone.seen, many.seen)
        torch.testing.assert_close(alone.features, many.features, rtol=0, atol=1e-5)


def test_several_shapes_need_one_image_size_and_one_camera_set_each():
    from geofeat.multiview.pipeline import multiview_features_many

    backbone = DinoBackbone(tiny_dinov3(), kind="dinov3")
    mesh = bumpy(0, 1)
    small = make_cameras(mesh, 4, layout="official", image_size=IMAGE_SIZE, device="cpu")
    large = make_cameras(mesh, 4, layout="official", image_size=2 * IMAGE_SIZE, device="cpu")
    with pytest.raises(RenderError, match="one image size"):
        multiview_features_many([mesh, mesh], [small, large], backbone)
    with pytest.raises(RenderError, match="one Cameras per mesh"):
        multiview_features_many([mesh, mesh], [small], backbone)


def test_prepared_views_give_the_features_of_a_plain_compute(backbone_folder):
    """The descriptor's prepare (renders made ahead, as geofeat extract does on another thread) changes nothing."""
    descriptor = geofeat.make_descriptor("dinov3", weights=str(backbone_folder), views=9, image_size=IMAGE_SIZE, batch_size=4)
    mesh = bumpy(4, 2)
    prepared = descriptor.prepare(mesh)
    assert [len(batch.images) for batch in prepared.rendered] == [4, 4, 1]
    np.testing.assert_array_equal(descriptor.compute_prepared(mesh, prepared), descriptor.compute(mesh))


def test_amp_is_keyed_as_it_resolves_and_batch_size_is_not_keyed(backbone_folder):
    make = geofeat.make_descriptor
    plain = make("dinov3", weights=str(backbone_folder), device="cpu")
    assert plain.get_params()["amp"] == "off"  # "auto" on the CPU: float32
    assert "batch_size" not in plain.get_params() and "device" not in plain.get_params()
    assert make("dinov3", weights=str(backbone_folder), device="cpu", batch_size=3).params_json() == plain.params_json()
    forced = make("dinov3", weights=str(backbone_folder), device="cpu", amp="on")
    assert forced.get_params()["amp"] == "on" and forced.params_json() != plain.params_json()
    reference = make("dinov3", weights=str(backbone_folder), recipe="reference", amp="auto")
    assert reference.get_params()["amp"] == "off"  # a recipe that reproduces other code keeps float32
    with pytest.raises(geofeat.GeofeatError, match="amp"):
        make("dinov3", weights=str(backbone_folder), amp="bf16")


def test_auto_batch_size_on_the_cpu_is_the_cpu_batch():
    from geofeat.multiview.pipeline import CPU_BATCH_SIZE, auto_batch_size

    backbone = DinoBackbone(tiny_dinov3(), kind="dinov3")
    assert auto_batch_size(49, 512, 512, backbone) == CPU_BATCH_SIZE
    assert auto_batch_size(2, 512, 512, backbone) == 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_auto_batch_size_on_cuda_fits_the_free_memory():
    from geofeat.multiview.pipeline import BATCH_MEMORY_SHARE, auto_batch_size

    backbone = DinoBackbone(tiny_dinov3(), kind="dinov3")
    backbone.model.to("cuda")
    views = auto_batch_size(49, 512, 512, backbone)
    free, _ = torch.cuda.mem_get_info()
    assert 1 <= views <= 49
    assert views == 49 or views * 512 * 512 * (8 * backbone.embed_dim + 64) <= BATCH_MEMORY_SHARE * free


@pytest.mark.parametrize("offset, scale", [(1e6, 1.0), (-3e5, 1.0), (0.0, 1e-6), (0.0, 1e6), (0.0, 1e-12)])
def test_features_do_not_depend_on_where_the_mesh_sits_or_its_size(backbone_folder, offset, scale):
    """Cameras follow the mesh; the features must too, to float32 rounding (a near plane, a normalisation eps or
    barycentric sums of world coordinates must not bring the mesh's position or scale in)."""
    from geofeat.apps.demo import blob

    mesh = blob(2, 0, "b")
    params = {"weights": str(backbone_folder), "views": 4, "image_size": IMAGE_SIZE, "device": "cpu", "cache": False}
    base = geofeat.compute(mesh, "dinov3", **params)
    moved = geofeat.compute(geofeat.Mesh(mesh.verts * scale + offset, mesh.faces, "moved"), "dinov3", **params)
    np.testing.assert_allclose(moved, base, rtol=0, atol=1e-6)


def test_a_mesh_no_pixel_reaches_is_refused_not_given_zero_features(backbone_folder, caplog, tmp_path):
    from geofeat.apps.demo import blob

    mesh = blob(2, 0, "b")
    params = {"weights": str(backbone_folder), "views": 4, "image_size": 16, "device": "cpu", "cache": False}
    with pytest.raises(RenderError, match="no vertex of 'b' .* received a pixel in any of its 4 views of 16 x 16"):
        geofeat.compute(mesh, "dinov3", **params)
    zeros = geofeat.compute(mesh, "dinov3", fill="zero", **params)  # asked for: zeros, with a warning
    assert not zeros.any() and "features are all zeros (fill='zero')" in caplog.text
    store = geofeat.FeatureCache(tmp_path / "store")
    with pytest.raises(RenderError):
        geofeat.compute(mesh, "dinov3", cache=store, **{k: v for k, v in params.items() if k != "cache"})
    assert list(store.entries()) == []  # nothing cached
