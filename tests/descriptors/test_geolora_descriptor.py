"""The geolora descriptor: a DINOv3 folder plus a LoRA folder or a release checkpoint."""

import numpy as np
import pytest
import torch
from shapes import bumpy
from tiny_models import tiny_dinov3

import geofeat
from geofeat.backbones import add_lora, load_backbone, lora_digest, save_lora
from geofeat.descriptors.registry import make_descriptor

PARAMS = {"views": 4, "image_size": 64, "camera_layout": "uniform", "device": "cpu"}


@pytest.fixture(scope="module")
def folders(tmp_path_factory):
    """A tiny DINOv3 folder, a fresh LoRA (B = 0) and a trained-looking one (random B)."""
    root = tmp_path_factory.mktemp("geolora")
    tiny_dinov3().save_pretrained(root / "backbone")
    backbone = add_lora(load_backbone(root / "backbone", kind="dinov3", device="cpu"))
    save_lora(backbone, root / "fresh")
    torch.manual_seed(5)
    with torch.no_grad():
        for name, param in backbone.model.named_parameters():
            if "lora_B" in name:
                param.copy_(torch.randn_like(param) * 0.5)
    save_lora(backbone, root / "trained")
    return root


def test_fresh_lora_gives_the_raw_backbone_features(folders):
    mesh = bumpy(0, 2)
    raw = geofeat.compute(mesh, "dinov3", weights=str(folders / "backbone"), **PARAMS)
    fresh = geofeat.compute(mesh, "geolora", checkpoint=str(folders / "fresh"), weights=str(folders / "backbone"), **PARAMS)
    np.testing.assert_allclose(fresh, raw, atol=1e-6)


def test_trained_lora_changes_features_and_cache_key(folders):
    mesh = bumpy(0, 2)
    common = {"weights": str(folders / "backbone"), **PARAMS}
    fresh = geofeat.compute(mesh, "geolora", checkpoint=str(folders / "fresh"), **common)
    trained = geofeat.compute(mesh, "geolora", checkpoint=str(folders / "trained"), **common)
    assert trained.shape == (mesh.n_vertices, 32) and trained.dtype == np.float32
    assert np.abs(trained - fresh).max() > 1e-3  # fresh vs raw agree to 1e-6 (test above)
    assert len(geofeat.FeatureCache().entries()) == 2
    descriptor = make_descriptor("geolora", checkpoint=str(folders / "trained"), **common)
    assert descriptor.weights_digest() == lora_digest(folders / "trained")
    assert descriptor.weights_digest() != make_descriptor("geolora", checkpoint=str(folders / "fresh"), **common).weights_digest()


def test_release_checkpoint_is_loaded_like_its_converted_lora(folders, tmp_path):
    """checkpoint=<release .pth> gives the features of the same LoRA saved in our format."""
    torch.manual_seed(9)
    release = {}
    for block in range(2):  # tiny_dinov3: 2 blocks of width 32; rank 4
        release[f"base_model.model.blocks.{block}.attn.qkv.lora_A.default.weight"] = torch.randn(4, 32) * 0.3
        release[f"base_model.model.blocks.{block}.attn.qkv.lora_B.default.weight"] = torch.randn(96, 4) * 0.3
    torch.save(release, tmp_path / "release.pth")
    from geofeat.backbones import load_official_lora

    converted = load_official_lora(load_backbone(folders / "backbone", kind="dinov3", device="cpu"), tmp_path / "release.pth")
    save_lora(converted, tmp_path / "converted")
    mesh = bumpy(1, 2)
    common = {"weights": str(folders / "backbone"), "cache": False, **PARAMS}
    from_release = geofeat.compute(mesh, "geolora", checkpoint=str(tmp_path / "release.pth"), **common)
    from_folder = geofeat.compute(mesh, "geolora", checkpoint=str(tmp_path / "converted"), **common)
    raw = geofeat.compute(mesh, "dinov3", **common)
    np.testing.assert_allclose(from_release, from_folder, atol=1e-6)
    assert np.abs(from_release - raw).max() > 1e-2


def test_missing_checkpoint_errors(folders, tmp_path):
    mesh = bumpy(0, 2)
    with pytest.raises(geofeat.DescriptorError, match="checkpoint="):
        geofeat.compute(mesh, "geolora", weights=str(folders / "backbone"), cache=False, **PARAMS)
    with pytest.raises(geofeat.DescriptorError, match="does not exist"):
        geofeat.compute(
            mesh, "geolora", checkpoint=str(tmp_path / "nope"), weights=str(folders / "backbone"), cache=False, **PARAMS
        )
