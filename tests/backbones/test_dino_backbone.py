"""DinoBackbone and load_backbone with tiny random DINOv2 / DINOv3 models (no real weights needed)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
from tiny_models import randomized, tiny_dinov3  # noqa: E402
from transformers import Dinov2Config, Dinov2Model  # noqa: E402

from geofeat.backbones import (  # noqa: E402
    IMAGENET_MEAN,
    IMAGENET_STD,
    WEIGHTS_ENV,
    DinoBackbone,
    load_backbone,
    state_dict_digest,
)
from geofeat.backbones.convert import require_transformers  # noqa: E402
from geofeat.errors import BackboneError, GeofeatError, MissingDependencyError  # noqa: E402


@pytest.fixture
def dinov2():
    torch.manual_seed(0)
    config = Dinov2Config(hidden_size=32, num_hidden_layers=2, num_attention_heads=2, mlp_ratio=2, patch_size=14, image_size=28)
    return randomized(Dinov2Model(config))


@pytest.fixture
def dinov3():
    return tiny_dinov3()


@pytest.fixture
def images():
    return torch.rand(3, 32, 48, 3, generator=torch.Generator().manual_seed(0))


@pytest.fixture(autouse=True)
def no_env_weights(monkeypatch):
    for name in WEIGHTS_ENV.values():
        monkeypatch.delenv(name, raising=False)


# ----------------------------------------------------------------------------- features


def test_pixel_features_shape_dtype_unit_norm(dinov3, images):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    assert (backbone.patch_size, backbone.embed_dim, backbone.num_prefix_tokens) == (16, 32, 3)
    feats = backbone.pixel_features(images, out_size=(40, 24), batch_size=2)
    assert feats.shape == (3, 40, 24, 32) and feats.dtype == torch.float32
    torch.testing.assert_close(feats.norm(dim=-1), torch.ones(3, 40, 24), atol=1e-5, rtol=0)
    default = backbone.pixel_features(images.numpy())  # numpy in, render resolution by default
    assert default.shape == (3, 32, 48, 32) and default.device.type == "cpu"


@pytest.mark.parametrize(("kind", "prefix", "patch"), [("dinov2", 1, 14), ("dinov3", 3, 16)])
def test_pixel_features_match_manual_recipe(request, kind, prefix, patch):
    """ImageNet normalisation, last layer after the final LayerNorm, CLS + registers dropped, bilinear, L2."""
    model = request.getfixturevalue(kind)
    backbone = DinoBackbone(model, kind=kind)
    imgs = torch.rand(2, 2 * patch, 3 * patch, 3)
    feats = backbone.pixel_features(imgs, out_size=(56, 84))
    mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])  # ImageNet, as in Meta's code
    pixels = ((imgs - mean) / std).permute(0, 3, 1, 2)
    with torch.no_grad():
        tokens = model(pixel_values=pixels).last_hidden_state
    assert tokens.shape[1] == prefix + 6
    grid = tokens[:, prefix:].reshape(2, 2, 3, 32).permute(0, 3, 1, 2)
    expected = torch.nn.functional.interpolate(grid, size=(56, 84), mode="bilinear", align_corners=False)
    expected = torch.nn.functional.normalize(expected, dim=1).permute(0, 2, 3, 1)
    torch.testing.assert_close(feats, expected, atol=1e-5, rtol=0)
    assert (IMAGENET_MEAN, IMAGENET_STD) == ((0.485, 0.456, 0.406), (0.229, 0.224, 0.225))


@pytest.mark.parametrize("kind", ["dinov2", "dinov3"])
def test_intermediate_layer_is_that_block_after_the_final_norm(request, kind):
    """layer=0 equals the last layer of a 1-block copy holding block 0 and the same final norm."""
    model = request.getfixturevalue(kind)
    config = {k: v for k, v in model.config.to_dict().items() if k not in ("out_features", "out_indices", "stage_names")}
    config["num_hidden_layers"] = 1
    short = type(model)(type(model.config).from_dict(config)).eval()
    state = {k: v for k, v in model.state_dict().items() if ".layer.1." not in k}
    missing, unexpected = short.load_state_dict(state, strict=False)
    assert not missing and not unexpected
    imgs = torch.rand(1, 32 if kind == "dinov3" else 28, 32 if kind == "dinov3" else 28, 3)
    torch.testing.assert_close(
        DinoBackbone(model, kind=kind, layer=0).pixel_features(imgs),
        DinoBackbone(short, kind=kind).pixel_features(imgs),
        atol=1e-6,
        rtol=0,
    )


def test_batching_does_not_change_features(dinov3, images):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    torch.testing.assert_close(
        backbone.pixel_features(images, batch_size=1), backbone.pixel_features(images, batch_size=3), atol=1e-5, rtol=0
    )


def test_dinov3_features_are_computed_in_eval_mode(dinov3, images):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    reference = backbone.pixel_features(images)
    dinov3.train()  # e.g. a trainer left the model in training mode: RoPE coordinates jitter there
    pixels = torch.randn(1, 3, 32, 48)
    with torch.no_grad():
        jittered = [dinov3(pixel_values=pixels).last_hidden_state for _ in range(3)]
    assert any(not torch.allclose(jittered[0], j) for j in jittered[1:])  # the hazard is real
    dinov3.train()
    first, second = backbone.pixel_features(images), backbone.pixel_features(images)
    assert torch.equal(first, second)
    torch.testing.assert_close(first, reference, atol=1e-6, rtol=0)
    assert not dinov3.training


def test_rope_augmentation_runs_dinov3_in_training_mode_on_request(dinov3, dinov2, images):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    plain = backbone.patch_features(images).detach()
    backbone.rope_augmentation = True
    torch.manual_seed(0)
    first = backbone.patch_features(images).detach()
    torch.manual_seed(0)
    again = backbone.patch_features(images).detach()
    assert dinov3.training and torch.equal(first, again)  # drawn from torch's generator
    assert not torch.equal(first, plain)  # the RoPE coordinates were rescaled
    backbone.rope_augmentation = False
    assert torch.equal(backbone.patch_features(images).detach(), plain) and not dinov3.training
    with pytest.raises(BackboneError, match="DINOv3"):
        DinoBackbone(dinov2, kind="dinov2").rope_augmentation = True


def test_layer_choice(dinov2, images):
    last = DinoBackbone(dinov2, kind="dinov2").pixel_features(images[:1, :28, :42])
    same = DinoBackbone(dinov2, kind="dinov2", layer=1).pixel_features(images[:1, :28, :42])
    first = DinoBackbone(dinov2, kind="dinov2", layer=0).pixel_features(images[:1, :28, :42])
    torch.testing.assert_close(same, last, atol=1e-6, rtol=0)
    assert not torch.allclose(first, last, atol=1e-3)
    torch.testing.assert_close(first.norm(dim=-1), torch.ones(first.shape[:-1]), atol=1e-5, rtol=0)
    with pytest.raises(BackboneError, match=r"\[-2, 1\]"):
        DinoBackbone(dinov2, kind="dinov2", layer=2)
    with pytest.raises(BackboneError, match="layer"):
        DinoBackbone(dinov2, kind="dinov2", layer=True)


def test_patch_features_are_differentiable(dinov3):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    imgs = torch.rand(1, 32, 32, 3, requires_grad=True)
    grid = backbone.patch_features(imgs)
    assert grid.shape == (1, 2, 2, 32)
    grid.square().sum().backward()
    assert imgs.grad is not None and imgs.grad.abs().sum() > 0


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (torch.rand(1, 30, 32, 3), r"30x32 is not a multiple of the dinov3 patch size 16"),
        (torch.rand(1, 32, 40, 3), r"multiple"),
        (torch.rand(32, 32, 3), r"\(N, H, W, 3\)"),
        (torch.rand(1, 32, 32, 4), r"\(N, H, W, 3\)"),
        (torch.randint(0, 255, (1, 32, 32, 3), dtype=torch.uint8), "divide by 255"),
        (torch.rand(1, 32, 32, 3) * 255, r"\[0, 1\]"),
    ],
)
def test_bad_images_are_refused(dinov3, bad, match):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    with pytest.raises(BackboneError, match=match):
        backbone.pixel_features(bad)


def test_bad_arguments_are_refused(dinov3, images):
    backbone = DinoBackbone(dinov3, kind="dinov3")
    with pytest.raises(BackboneError, match="out_size"):
        backbone.pixel_features(images, out_size=(0, 10))
    with pytest.raises(BackboneError, match="batch_size"):
        backbone.pixel_features(images, batch_size=0)
    with pytest.raises(BackboneError, match="kind"):
        DinoBackbone(dinov3, kind="dinov4")


# ----------------------------------------------------------------------------- digest


def test_digest_stable_and_sensitive(dinov2, tmp_path):
    a = DinoBackbone(dinov2, kind="dinov2").weights_digest
    assert len(a) == 64 and a == DinoBackbone(dinov2, kind="dinov2").weights_digest
    state = {k: v.clone() for k, v in dinov2.state_dict().items()}
    assert state_dict_digest(state) == a
    state["encoder.layer.1.norm2.bias"][3] += 1e-6
    assert state_dict_digest(state) != a
    renamed = {("x" + k if k.startswith("layernorm") else k): v for k, v in dinov2.state_dict().items()}
    assert state_dict_digest(renamed) != a
    assert state_dict_digest({k: v.double() for k, v in dinov2.state_dict().items()}) != a
    assert state_dict_digest({"w": torch.ones(2, dtype=torch.bfloat16)}) != state_dict_digest({"w": torch.ones(2)})


# ----------------------------------------------------------------------------- loading


@pytest.mark.parametrize("kind", ["dinov2", "dinov3"])
def test_hf_folder_round_trip(request, tmp_path, kind):
    model = request.getfixturevalue(kind)
    folder = tmp_path / kind
    model.save_pretrained(folder)
    loaded = load_backbone(folder, kind=kind, layer=0, device="cpu")
    again = load_backbone(str(folder), kind=kind, layer=0, device="auto")
    reference = DinoBackbone(model, kind=kind, layer=0)
    size = 14 * 2 if kind == "dinov2" else 32
    imgs = torch.rand(2, size, size, 3)
    torch.testing.assert_close(loaded.pixel_features(imgs), reference.pixel_features(imgs), atol=1e-6, rtol=0)
    assert loaded.weights_digest == again.weights_digest == reference.weights_digest
    assert not loaded.model.training and loaded.layer == 0 and loaded.kind == kind
    assert loaded.model.dtype == torch.float32


def test_weights_from_environment_variable(dinov3, tmp_path, monkeypatch):
    dinov3.save_pretrained(tmp_path / "v3")
    monkeypatch.setenv("GEOFEAT_DINOV3_WEIGHTS", str(tmp_path / "v3"))
    backbone = load_backbone(kind="dinov3", device="cpu")
    assert backbone.weights_digest == DinoBackbone(dinov3, kind="dinov3").weights_digest


@pytest.mark.parametrize(
    ("kind", "page", "repo"),
    [
        ("dinov2", "huggingface.co/facebook/dinov2-base", "github.com/facebookresearch/dinov2"),
        ("dinov3", "huggingface.co/facebook/dinov3-vitb16-pretrain-lvd1689m", "github.com/facebookresearch/dinov3"),
    ],
)
def test_missing_weights_error_says_how_to_fix(kind, page, repo):
    with pytest.raises(BackboneError) as info:
        load_backbone(None, kind=kind)
    text = str(info.value)
    for needle in ("weights=", WEIGHTS_ENV[kind], page, repo):
        assert needle in text, needle
    assert isinstance(info.value, GeofeatError) and isinstance(info.value, ValueError)


def test_nonexistent_path_and_offline_hub_id(tmp_path, monkeypatch):
    import huggingface_hub.constants

    with pytest.raises(BackboneError, match="does not exist.*GEOFEAT_DINOV2_WEIGHTS"):
        load_backbone(tmp_path / "nope.pth", kind="dinov2")
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)  # fail fast instead of retrying
    with pytest.raises(BackboneError, match="Hugging Face Hub.*GEOFEAT_DINOV3_WEIGHTS"):
        load_backbone("geofeat-tests/no-such-model", kind="dinov3")


def test_wrong_files_and_kind_mismatch(dinov3, tmp_path):
    folder = tmp_path / "v3"
    dinov3.save_pretrained(folder)
    with pytest.raises(BackboneError, match="kind='dinov3'"):
        load_backbone(folder, kind="dinov2")
    with pytest.raises(BackboneError, match="folder"):
        load_backbone(folder / "model.safetensors", kind="dinov3")
    (tmp_path / "empty").mkdir()
    with pytest.raises(BackboneError, match="config.json"):
        load_backbone(tmp_path / "empty", kind="dinov3")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(BackboneError, match="junk.pth"):
        load_backbone(tmp_path / "junk.pth", kind="dinov3")
    with pytest.raises(BackboneError, match="config_overrides"):
        load_backbone(folder, kind="dinov3", config_overrides={"num_attention_heads": 2})
    with pytest.raises(BackboneError, match="layer"):
        load_backbone(folder, kind="dinov3", layer=5)


def test_truncated_folder_is_refused(dinov2, tmp_path):
    from safetensors.torch import load_file, save_file

    folder = tmp_path / "v2"
    dinov2.save_pretrained(folder)
    state = load_file(folder / "model.safetensors")
    del state["layernorm.weight"]
    save_file(state, folder / "model.safetensors", metadata={"format": "pt"})
    with pytest.raises(BackboneError, match="layernorm.weight"):
        load_backbone(folder, kind="dinov2")


def test_missing_transformers_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "transformers", None)
    with pytest.raises(MissingDependencyError, match=r"pip install 'geofeat\[dino\]'"):
        require_transformers()


# ----------------------------------------------------------------------------- LoRA hook points


@pytest.mark.parametrize("kind", ["dinov2", "dinov3"])
def test_attention_projections_are_lora_targets(request, kind, images):
    peft = pytest.importorskip("peft")
    backbone = DinoBackbone(request.getfixturevalue(kind), kind=kind)
    names = backbone.attention_projections
    # DINOv3 has always named them q/k/v_proj; DINOv2 is query/key/value up to transformers 5.17
    # (seen on the GPU machine) and q/k/v_proj in later 5.x releases: pyproject allows both.
    allowed = [("q_proj", "k_proj", "v_proj")] + ([("query", "key", "value")] if kind == "dinov2" else [])
    assert names in allowed
    linear = [n for n, m in backbone.model.named_modules() if isinstance(m, torch.nn.Linear) and n.endswith(names)]
    assert len(linear) == 3 * backbone.num_layers  # every block's three projections, nothing else
    before = backbone.pixel_features(images[:1, :28, :28] if kind == "dinov2" else images[:1])
    config = peft.LoraConfig(r=2, lora_alpha=4, target_modules=list(names), init_lora_weights=False)
    peft.inject_adapter_in_model(config, backbone.model)
    wrapped = [n for n, _ in backbone.model.named_modules() if n.endswith(names)]
    assert len(wrapped) == 3 * backbone.num_layers
    assert any("lora_" in n for n, p in backbone.model.named_parameters() if p.requires_grad)
    after = backbone.pixel_features(images[:1, :28, :28] if kind == "dinov2" else images[:1])
    assert not torch.allclose(before, after, atol=1e-4)  # the LoRA is in the forward path
    assert np.isfinite(after.numpy()).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu(dinov3, images):
    cpu = DinoBackbone(dinov3, kind="dinov3").pixel_features(images)
    digest = DinoBackbone(dinov3, kind="dinov3").weights_digest
    gpu_backbone = DinoBackbone(dinov3.to("cuda"), kind="dinov3")
    assert gpu_backbone.weights_digest == digest
    from_cpu_input = gpu_backbone.pixel_features(images)
    assert from_cpu_input.device.type == "cpu"
    from_gpu_input = gpu_backbone.pixel_features(images.cuda())
    assert from_gpu_input.device.type == "cuda"
    torch.testing.assert_close(from_cpu_input, cpu, atol=5e-3, rtol=0)  # TF32 convolutions on CUDA
    torch.testing.assert_close(from_gpu_input.cpu(), from_cpu_input, atol=1e-6, rtol=0)
