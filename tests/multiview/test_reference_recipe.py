"""The ``reference`` recipe against recorded outputs of the official GeoLoRA code.

``tests/data/geolora_reference.npz`` and ``geolora_reference_lora.pth`` were written by
``python -m benchmarks.parity.geolora --record tests/data`` (see ``tests/data/README.md``): the official
code (vikiehm/geo-lora with pytorch3d, and the official DINOv3 model class at test size) run on
FAUST_r ``tr_reg_080``. Here geofeat alone, with no pytorch3d and no reference code, loads the
same weights through its official-layout converters and must give the same stages.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

import geofeat
from geofeat.backbones import load_backbone
from geofeat.backbones.dino import grid_sample_patch_features
from geofeat.backbones.lora import load_official_lora
from geofeat.errors import BackboneError
from geofeat.multiview import multiview_features
from geofeat.multiview.pipeline import RECIPES, backbone_input, corner_points
from geofeat.render import make_cameras
from geofeat.render.rasterizer import RasterSettings
from geofeat.render.shading import render_phong

DATA = Path(__file__).resolve().parent.parent / "data"
RECIPE = RECIPES["reference"]
SIZE, VIEWS, EVERY = 64, 4, 10  # benchmarks/parity/geolora.py RECORD_SIZE, RECORD_VIEWS, RECORD_EVERY


@pytest.fixture(scope="module")
def recorded() -> dict[str, np.ndarray]:
    path = DATA / "geolora_reference.npz"
    if not path.is_file():
        pytest.fail(f"{path} is missing; rebuild it as tests/data/README.md says.", pytrace=False)
    with np.load(path) as data:
        return {key: data[key] for key in data.files}


@pytest.fixture(scope="module")
def official_pth(recorded, tmp_path_factory) -> Path:
    """The recorded official-layout state dict, saved as an official checkpoint file."""
    state = {key[len("weights/") :]: torch.from_numpy(value) for key, value in recorded.items() if key.startswith("weights/")}
    path = tmp_path_factory.mktemp("official") / "dinov3_tiny.pth"
    torch.save(state, path)
    return path


def _backbone(official_pth, lora: bool):
    backbone = load_backbone(str(official_pth), kind="dinov3", device="cpu")
    if lora:
        load_official_lora(backbone, DATA / "geolora_reference_lora.pth")
    return backbone


@pytest.fixture(scope="module")
def mesh(faust_dir) -> geofeat.Mesh:
    return geofeat.load_mesh(faust_dir / "off" / "tr_reg_080.off")


def test_official_dinov3_weights_convert_exactly(recorded, official_pth):
    image = torch.from_numpy(recorded["tokens/image"])
    with torch.no_grad():
        tokens = _backbone(official_pth, lora=False).patch_features(image)
    np.testing.assert_allclose(tokens.reshape(recorded["tokens/plain"].shape).numpy(), recorded["tokens/plain"], atol=2e-5)


def test_official_lora_file_loads_exactly(recorded, official_pth):
    """A LoRA saved by the official code path (peft on the fused qkv, r=16, alpha=32) adapts the model exactly."""
    image = torch.from_numpy(recorded["tokens/image"])
    with torch.no_grad():
        tokens = _backbone(official_pth, lora=True).patch_features(image)
    expected = recorded["tokens/lora"]
    assert np.abs(expected - recorded["tokens/plain"]).max() > 1e-2  # the LoRA changes the tokens
    np.testing.assert_allclose(tokens.reshape(expected.shape).numpy(), expected, atol=2e-5)


def test_official_lora_mismatch_is_refused_with_the_keys(official_pth, tmp_path):
    state = torch.load(DATA / "geolora_reference_lora.pth", weights_only=True)
    extra = dict(state)
    extra["base_model.model.blocks.0.attn.proj.lora_A.default.weight"] = torch.zeros(16, 16)
    with pytest.raises(BackboneError, match=r"blocks\.0\.attn\.proj\.lora_A"):
        load_official_lora(_backbone(official_pth, lora=False), extra)
    missing = {k: v for k, v in state.items() if "blocks.1." not in k or "lora_B" not in k}
    with pytest.raises(BackboneError, match="incomplete: \\[1\\]"):
        load_official_lora(_backbone(official_pth, lora=False), missing)
    deeper = {**state, **{k.replace("blocks.1.", "blocks.2."): v for k, v in state.items() if "blocks.1." in k}}
    with pytest.raises(BackboneError, match="adapts 3 blocks but this backbone has 2"):
        load_official_lora(_backbone(official_pth, lora=False), deeper)


def test_reference_recipe_stages_equal_the_official_code(recorded, official_pth, mesh):
    backbone = _backbone(official_pth, lora=True)
    cameras = make_cameras(mesh, VIEWS, image_size=SIZE, device="cpu")
    np.testing.assert_allclose(cameras.rotation.numpy(), recorded["path/rotation"], atol=1e-6)
    np.testing.assert_allclose(cameras.position.numpy(), recorded["path/position"], atol=1e-6)

    rendering = render_phong(mesh, None, cameras, RasterSettings(cull_backfaces=RECIPE.cull_backfaces))
    foreground = (rendering.fragments.pix_to_face >= 0).numpy()
    theirs = recorded["path/foreground"]
    assert (foreground != theirs).sum() <= 2  # a pixel on a silhouette may go either way (none did when recorded)
    both = foreground & theirs
    depth_theirs = np.zeros(theirs.shape, np.float32)
    depth_theirs[theirs] = recorded["path/depth"]
    np.testing.assert_allclose(rendering.fragments.depth.numpy()[both], depth_theirs[both], rtol=1e-5)

    view0 = theirs[0].reshape(-1)
    common0 = both[0].reshape(-1)[view0]  # the recorded view-0 rows that we see too
    ours_image = rendering.images[0].reshape(-1, 3)[torch.from_numpy(view0)].numpy()
    np.testing.assert_allclose(ours_image[common0], recorded["path/image_view0"][common0], atol=1e-5)

    images = backbone_input(rendering.images, RECIPE, backbone.patch_size)
    with torch.no_grad():
        grid = backbone.patch_features(images)
    pixels0 = torch.nonzero(torch.from_numpy(theirs[:1]))
    sampled = grid_sample_patch_features(grid[:1], pixels0, (SIZE, SIZE), RECIPE.dtype).float().numpy()
    np.testing.assert_allclose(sampled[common0], recorded["path/pixel_features_view0"][common0], atol=1e-3)  # float16

    depth = torch.from_numpy(depth_theirs)
    points = corner_points(cameras, pixels0, depth).numpy()
    np.testing.assert_allclose(points, recorded["path/points_view0"], atol=1e-5)

    with torch.no_grad():
        features, _ = multiview_features(mesh, cameras, backbone, recipe=RECIPE, fill="nearest")
    theirs_features = recorded["path/features"]
    np.testing.assert_allclose(features.numpy()[::EVERY], theirs_features, atol=1e-3)  # 8e-6 when recorded
    with torch.no_grad():  # the check can tell recipes apart: geofeat's default is not the reference
        default, _ = multiview_features(mesh, cameras, backbone, recipe=RECIPES["default"], fill="nearest")
    assert np.abs(default.numpy()[::EVERY] - theirs_features).max() > 1e-2


def test_reference_training_step_equals_the_official_step(recorded, official_pth, mesh):
    """One GeoLoRA step on the recorded pair: the trainer's loss and LoRA gradients equal the official ``train.py``'s."""
    from benchmarks.parity.geolora import training_pair
    from geofeat.geometry.geodesic import geodesic_matrix
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    backbone = _backbone(official_pth, lora=True)
    views_full, views_partial = (int(v) for v in recorded["step/views"])
    full, partial, gt = training_pair(mesh)
    geodesics = torch.as_tensor(geodesic_matrix(full, normalize=True, cache=False), dtype=torch.float32)
    np.testing.assert_allclose(geodesics[0].numpy(), recorded["step/geodesics_row0"], rtol=1e-5, atol=1e-6)
    with tempfile.TemporaryDirectory() as tmp:
        config = TrainConfig(
            data="unused",
            out=tmp,
            recipe="reference",
            views_full=views_full,
            views_partial=views_partial,
            image_size=512,
            device="cpu",
            amp="off",
            progress=False,
        )
        trainer = GeoLoraTrainer(config, backbone=backbone, shapes=[full])
        for name, param in backbone.model.named_parameters():
            param.requires_grad_("lora_" in name)
        with torch.enable_grad():
            feat_full, seen_full = trainer.mesh_features(full, views_full)
            feat_partial, seen_partial = trainer.mesh_features(partial, views_partial)
            loss = trainer._loss(feat_partial, feat_full, gt, geodesics, seen_partial, seen_full)
            loss.backward()
    np.testing.assert_allclose(float(loss.detach()), float(recorded["step/loss"]), rtol=1e-5)
    named = dict(backbone.model.named_parameters(remove_duplicate=False))
    for key, expected in recorded.items():
        if not key.startswith("step/grad/"):
            continue
        block = int(key.split("blocks.")[1].split(".")[0])
        which = "lora_A" if ".lora_A." in key else "lora_B"
        parts = [
            named[f"base_model.model.model.layer.{block}.attention.{t}.{which}.default.weight"].grad
            for t in ("q_proj", "k_proj", "v_proj")
        ]
        ours = sum({id(g): g for g in parts}.values()) if which == "lora_A" else torch.cat(parts)  # a shared A once
        # float16 sums and sampling: up to 2e-3 of the largest entry when recorded
        np.testing.assert_allclose(ours.numpy(), expected, rtol=0, atol=4e-3 * np.abs(expected).max())
