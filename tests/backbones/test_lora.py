"""LoRA on tiny random DINOv3 models: freezing, training step, save/load, release-checkpoint conversion."""

from __future__ import annotations

import copy
import json
import logging
import re

import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("peft")
pytest.importorskip("safetensors")

from tiny_models import tiny_dinov3  # noqa: E402

from geofeat.backbones import DinoBackbone  # noqa: E402
from geofeat.backbones.lora import (  # noqa: E402
    LoraSettings,
    add_lora,
    convert_official_lora,
    load_lora,
    load_official_lora,
    lora_digest,
    lora_state_dict,
    save_lora,
)
from geofeat.errors import BackboneError, GeofeatError  # noqa: E402
from geofeat.storage.pretrained import CONFIG_FILE, WEIGHTS_FILE  # noqa: E402

DIM, DEPTH, RANK = 32, 2, 16


@pytest.fixture
def base_model():
    return tiny_dinov3(seed=0)


@pytest.fixture
def images():
    return torch.rand(2, 32, 48, 3, generator=torch.Generator().manual_seed(0))


def _randomize_lora(backbone: DinoBackbone, seed: int = 3) -> None:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, param in backbone.model.named_parameters():
            if "lora_" in name:
                param.copy_(torch.randn(param.shape, generator=gen) * 0.3)


def _base_params(backbone: DinoBackbone) -> dict[str, torch.Tensor]:
    return {n: p.detach().clone() for n, p in backbone.model.named_parameters() if "lora_" not in n}


# ----------------------------------------------------------------------------- adding and training


def test_add_lora_freezes_base_and_counts_trainable(base_model, images):
    backbone = DinoBackbone(base_model, kind="dinov3")
    digest = backbone.weights_digest
    before = backbone.patch_features(images).detach()
    assert add_lora(backbone) is backbone
    trainable = {n: p.numel() for n, p in backbone.model.named_parameters() if p.requires_grad}
    # q, k, v per block: A (r, D) + B (D, r)
    assert sum(trainable.values()) == DEPTH * 3 * (RANK * DIM + DIM * RANK) == 6144
    assert all("lora_" in n for n in trainable) and len(trainable) == DEPTH * 3 * 2
    assert backbone.weights_digest == digest
    torch.testing.assert_close(backbone.patch_features(images).detach(), before, rtol=0, atol=0)  # B = 0 at start
    with pytest.raises(BackboneError, match="already has a LoRA"):
        add_lora(backbone)


def test_optimizer_step_moves_only_lora(base_model, images):
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"))
    base = _base_params(backbone)
    lora_before = lora_state_dict(backbone)
    features_before = backbone.patch_features(images).detach()
    params = [p for p in backbone.model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(params, lr=1e-2)
    loss = (backbone.patch_features(images) ** 2).mean()
    loss.backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in params)
    optimizer.step()
    for name, value in _base_params(backbone).items():
        assert torch.equal(value, base[name]), name
    after = lora_state_dict(backbone)
    assert any(not torch.equal(after[k], lora_before[k]) for k in after)
    assert not torch.allclose(backbone.patch_features(images).detach(), features_before)


def test_custom_settings_and_validation(base_model):
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"), LoraSettings(rank=2, alpha=4, targets=("q_proj", "v_proj")))
    assert sum(p.numel() for p in backbone.model.parameters() if p.requires_grad) == DEPTH * 2 * (2 * DIM * 2)
    with pytest.raises(BackboneError, match="rank"):
        LoraSettings(rank=0)
    with pytest.raises(BackboneError, match="dropout"):
        LoraSettings(dropout=1.0)
    with pytest.raises(BackboneError, match="JSON"):
        LoraSettings(training={"bad": object()})
    with pytest.raises(BackboneError, match="not modules"):
        add_lora(DinoBackbone(tiny_dinov3(seed=0), kind="dinov3"), LoraSettings(targets=("qkv",)))


def test_settings_json_round_trip(tmp_path, caplog):
    settings = LoraSettings(rank=8, alpha=16, dropout=0.1, targets=("q_proj",), training={"lr": 1e-4, "views": 49})
    settings.save(tmp_path / "s.json")
    assert LoraSettings.load(tmp_path / "s.json") == settings
    data = json.loads((tmp_path / "s.json").read_text()) | {"from_the_future": 1}
    with caplog.at_level(logging.DEBUG, logger="geofeat.backbones.lora"):
        assert LoraSettings.from_dict(data) == settings
    assert "from_the_future" in caplog.text


# ----------------------------------------------------------------------------- save / load


def test_save_load_round_trip(base_model, images, tmp_path):
    fresh = copy.deepcopy(base_model)
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3", source="tiny"))
    _randomize_lora(backbone)
    expected = backbone.pixel_features(images)
    settings = LoraSettings(training={"lr": 1e-4, "partial": ["cuts", "holes"]})
    save_lora(backbone, tmp_path / "lora", settings, extra_info={"step": 7})

    envelope = json.loads((tmp_path / "lora" / CONFIG_FILE).read_text())
    config = envelope["config"]
    assert envelope["kind"] == "lora"
    assert config["backbone_kind"] == "dinov3" and config["backbone_digest"] == backbone.weights_digest
    assert (config["rank"], config["alpha"], sorted(config["targets"])) == (16, 32.0, ["k_proj", "q_proj", "v_proj"])
    assert config["training"] == settings.training and envelope["info"] == {"step": 7}
    assert "geofeat_version" in envelope
    assert sorted(p.name for p in (tmp_path / "lora").iterdir()) == [CONFIG_FILE, WEIGHTS_FILE]

    restored = load_lora(DinoBackbone(fresh, kind="dinov3"), tmp_path / "lora")
    assert torch.equal(restored.pixel_features(images), expected)
    assert all(("lora_" in n) == p.requires_grad for n, p in restored.model.named_parameters())
    assert not torch.equal(DinoBackbone(tiny_dinov3(seed=0), kind="dinov3").pixel_features(images), expected)


def test_lora_digest_tracks_weights(base_model, tmp_path):
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"))
    _randomize_lora(backbone, seed=1)
    save_lora(backbone, tmp_path / "a", LoraSettings(training={"lr": 1}))
    save_lora(backbone, tmp_path / "b", LoraSettings(training={"lr": 2}))  # training settings do not count
    _randomize_lora(backbone, seed=2)
    save_lora(backbone, tmp_path / "c")
    digests = [lora_digest(tmp_path / n) for n in "abc"]
    assert len(digests[0]) == 64 and digests[0] == digests[1] != digests[2]


def test_unknown_config_keys_are_ignored(base_model, images, tmp_path, caplog):
    fresh = copy.deepcopy(base_model)
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"))
    _randomize_lora(backbone)
    save_lora(backbone, tmp_path)
    path = tmp_path / CONFIG_FILE
    envelope = json.loads(path.read_text())
    envelope["config"]["new_option"] = {"x": 1}
    path.write_text(json.dumps(envelope | {"new_top_level_key": 2}))
    with caplog.at_level(logging.DEBUG, logger="geofeat.backbones.lora"):
        restored = load_lora(DinoBackbone(fresh, kind="dinov3"), tmp_path)
    assert "new_option" in caplog.text
    assert torch.equal(restored.pixel_features(images), backbone.pixel_features(images))


def test_digest_mismatch_names_the_training_backbone(base_model, tmp_path):
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3", source="/models/tiny-a"))
    save_lora(backbone, tmp_path)
    other = DinoBackbone(tiny_dinov3(seed=5), kind="dinov3", source="/models/tiny-b")
    with pytest.raises(
        GeofeatError, match=r"trained on a dinov3 backbone from /models/tiny-a .*digest " + backbone.weights_digest[:12]
    ):
        load_lora(other, tmp_path)
    assert not any("lora_" in n for n, _ in other.model.named_parameters())  # nothing was attached


def test_missing_or_incomplete_lora_errors(base_model, tmp_path):
    backbone = DinoBackbone(base_model, kind="dinov3")
    with pytest.raises(BackboneError, match="does not exist"):
        load_lora(backbone, tmp_path / "nowhere")
    with pytest.raises(BackboneError, match="has no LoRA; call add_lora"):
        save_lora(backbone, tmp_path / "x")
    (tmp_path / CONFIG_FILE).write_text(
        json.dumps({"kind": "lora", "format_version": 1, "geofeat_version": "0", "config": {"rank": 16}, "info": {}})
    )
    with pytest.raises(BackboneError, match="lacks the keys"):
        load_lora(backbone, tmp_path)
    (tmp_path / CONFIG_FILE).write_text(
        json.dumps({"kind": "head", "format_version": 1, "geofeat_version": "0", "config": {}, "info": {}})
    )
    with pytest.raises(BackboneError, match="holds a 'head', not a 'lora'"):
        load_lora(backbone, tmp_path)


def test_damaged_lora_weights_are_a_backbone_error(base_model, tmp_path):
    backbone = add_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3"))
    save_lora(backbone, tmp_path / "a")
    weights = tmp_path / "a" / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:64])
    with pytest.raises(BackboneError, match="truncated or damaged"):
        load_lora(DinoBackbone(base_model, kind="dinov3"), tmp_path / "a")


def test_save_lora_refuses_a_folder_of_other_files(base_model, tmp_path):
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"))
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(BackboneError, match="not written by save_pretrained"):
        save_lora(backbone, tmp_path)
    assert [p.name for p in tmp_path.iterdir()] == ["notes.txt"]


def test_a_lora_of_another_layout_is_refused(base_model, tmp_path):
    """adapter_config.json + adapter.safetensors: an error that names what was found and what is expected."""
    import safetensors.torch

    fresh = copy.deepcopy(base_model)
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3", source="tiny"))
    _randomize_lora(backbone)
    save_lora(backbone, tmp_path / "new", LoraSettings(training={"lr": 1e-4}), extra_info={"step": 3})
    envelope = json.loads((tmp_path / "new" / CONFIG_FILE).read_text())
    old = tmp_path / "old"
    old.mkdir()
    other = {"format": "geofeat-lora", "format_version": 1, **envelope["config"], "extra_info": {"step": 3}}
    (old / "adapter_config.json").write_text(json.dumps(other))
    safetensors.torch.save_file(lora_state_dict(backbone), str(old / "adapter.safetensors"))
    (old / "trainer_state.pt").write_bytes(b"kept as it is")
    with pytest.raises(
        BackboneError,
        match=r"holds a LoRA or trainer checkpoint as adapter_config.json \+ adapter.safetensors, a layout "
        r"this geofeat does not read; expected a '\w+' as config.json \+ weights.safetensors .* Save it again",
    ):
        load_lora(DinoBackbone(fresh, kind="dinov3"), old)
    assert sorted(p.name for p in old.iterdir()) == ["adapter.safetensors", "adapter_config.json", "trainer_state.pt"]


def test_a_lora_folder_of_kind_lora_adapter_is_refused(base_model, tmp_path):
    """A config.json of kind 'lora_adapter': an error that names it and says to save the LoRA again."""
    save_lora(add_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3")), tmp_path)
    envelope = json.loads((tmp_path / CONFIG_FILE).read_text())
    (tmp_path / CONFIG_FILE).write_text(json.dumps({**envelope, "kind": "lora_adapter"}))
    found = r"holds a LoRA or trainer checkpoint of kind 'lora_adapter', a layout this geofeat does not read; expected a 'lora'"
    with pytest.raises(BackboneError, match=found + r" .* Save it again"):
        load_lora(DinoBackbone(base_model, kind="dinov3"), tmp_path)
    with pytest.raises(BackboneError, match=found):
        lora_digest(tmp_path)


# ----------------------------------------------------------------------------- release checkpoints


def _official_state_dict(seed: int = 7, rank: int = RANK) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    out = {}
    for i in range(DEPTH):
        prefix = f"base_model.model.blocks.{i}.attn.qkv."
        out[prefix + "lora_A.default.weight"] = torch.randn(rank, DIM, generator=gen) * 0.2
        out[prefix + "lora_B.default.weight"] = torch.randn(3 * DIM, rank, generator=gen) * 0.2
    return out


def test_official_conversion_is_exact(base_model, images, tmp_path):
    official = _official_state_dict()
    torch.save(official, tmp_path / "becos.pth")
    plain = copy.deepcopy(base_model)
    base_features = DinoBackbone(copy.deepcopy(base_model), kind="dinov3").patch_features(images).detach()
    backbone = load_official_lora(DinoBackbone(base_model, kind="dinov3"), tmp_path / "becos.pth")
    scale = 32 / 16

    # per-projection deltas equal the thirds of the fused update x @ (B A)^T * scale
    x = torch.randn(5, DIM, generator=torch.Generator().manual_seed(1))
    modules = {}
    for name, module in backbone.model.named_modules():
        match = re.search(r"layer\.(\d+)\.attention\.([qkv]_proj)$", name)
        if match:
            modules[f"{match.group(1)}.{match.group(2)}"] = module
    assert len(modules) == 3 * DEPTH
    for i in range(DEPTH):
        a = official[f"base_model.model.blocks.{i}.attn.qkv.lora_A.default.weight"]
        b = official[f"base_model.model.blocks.{i}.attn.qkv.lora_B.default.weight"]
        fused = x @ (b @ a).T * scale
        for third, proj in enumerate(("q_proj", "k_proj", "v_proj")):
            layer = modules[f"{i}.{proj}"]
            assert layer.scaling["default"] == scale
            ours = layer.lora_B["default"](layer.lora_A["default"](x)) * layer.scaling["default"]
            torch.testing.assert_close(ours, fused[:, third * DIM : (third + 1) * DIM], rtol=1e-5, atol=1e-6)

    # whole model: same as a plain copy with the merged deltas added to its q/k/v weights
    with torch.no_grad():
        for i in range(DEPTH):
            delta = (
                scale
                * official[f"base_model.model.blocks.{i}.attn.qkv.lora_B.default.weight"]
                @ official[f"base_model.model.blocks.{i}.attn.qkv.lora_A.default.weight"]
            )
            attention = plain.model.layer[i].attention
            for third, proj in enumerate((attention.q_proj, attention.k_proj, attention.v_proj)):
                proj.weight += delta[third * DIM : (third + 1) * DIM]
    manual = DinoBackbone(plain, kind="dinov3").patch_features(images).detach()
    ours = backbone.patch_features(images).detach()
    torch.testing.assert_close(ours, manual, rtol=1e-4, atol=1e-5)
    assert not torch.allclose(ours, base_features, atol=1e-3)


def test_a_lora_saved_in_the_release_layout_loads_back_exactly(base_model, tmp_path):
    from geofeat.backbones.lora import official_lora_state_dict, save_official_lora

    official = _official_state_dict(seed=3)
    backbone = load_official_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3"), official)
    save_official_lora(backbone, tmp_path / "run.pth")
    saved = torch.load(tmp_path / "run.pth", weights_only=True)
    assert set(saved) == set(official)
    for key, value in official.items():
        assert torch.equal(saved[key], value)
    again = load_official_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3"), tmp_path / "run.pth")
    for key, value in lora_state_dict(backbone).items():
        assert torch.equal(lora_state_dict(again)[key], value)
    separate = add_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3"), LoraSettings(rank=RANK, shared_a=False))
    with pytest.raises(BackboneError, match="shared_a"):
        official_lora_state_dict(separate)


def test_official_converts_to_our_layout():
    official = _official_state_dict(rank=4)
    tensors = convert_official_lora({k.replace(".default", ""): v for k, v in official.items()}, DIM)
    assert len(tensors) == DEPTH * 6
    b = official["base_model.model.blocks.1.attn.qkv.lora_B.default.weight"]
    assert torch.equal(tensors["layer.1.k_proj.lora_B.weight"], b[DIM : 2 * DIM])
    assert torch.equal(
        tensors["layer.1.v_proj.lora_A.weight"], official["base_model.model.blocks.1.attn.qkv.lora_A.default.weight"]
    )


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda sd: sd.update({"base_model.model.blocks.0.attn.proj.lora_A.default.weight": torch.zeros(RANK, DIM)}),
            "unexpected entry",
        ),
        (
            lambda sd: sd.update({"base_model.model.blocks.1.attn.qkv.lora_B.default.weight": torch.zeros(3 * DIM - 1, RANK)}),
            "block 1",
        ),
        (
            lambda sd: sd.update({"base_model.model.blocks.0.attn.qkv.lora_A.default.weight": torch.zeros(RANK, DIM + 1)}),
            "expected",
        ),
        (lambda sd: sd.pop("base_model.model.blocks.1.attn.qkv.lora_A.default.weight"), "incomplete"),
        (lambda sd: [sd.pop(k) for k in list(sd) if ".blocks.1." in k], "adapts 1 blocks"),
        (lambda sd: sd.clear(), "no LoRA tensors"),
    ],
)
def test_official_bad_checkpoint_errors(base_model, edit, message):
    official = _official_state_dict()
    edit(official)
    backbone = DinoBackbone(base_model, kind="dinov3")
    with pytest.raises(BackboneError, match=message):
        load_official_lora(backbone, official)
    assert not any("lora_" in n for n, _ in backbone.model.named_parameters())


def test_official_unreadable_file(base_model, tmp_path):
    (tmp_path / "bad.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(BackboneError, match="could not read"):
        load_official_lora(DinoBackbone(base_model, kind="dinov3"), tmp_path / "bad.pth")


def test_shared_a_is_one_parameter_per_block_and_survives_save_and_load(base_model, images, tmp_path):
    """``shared_a``: q, k and v of a block train one A, as the release's fused-qkv LoRA; saved and loaded as such."""
    fresh = copy.deepcopy(base_model)
    backbone = add_lora(DinoBackbone(base_model, kind="dinov3"), LoraSettings(shared_a=True))
    named = dict(backbone.model.named_parameters(remove_duplicate=False))
    for block in range(DEPTH):
        a = [n for n in named if f"layer.{block}." in n and "lora_A" in n]
        assert len(a) == 3 and len({id(named[n]) for n in a}) == 1
    trainable = [p for p in backbone.model.parameters() if p.requires_grad]
    assert sum(p.numel() for p in trainable) == DEPTH * (RANK * DIM + 3 * DIM * RANK)  # one A and three B per block
    _randomize_lora(backbone)
    backbone.patch_features(images).square().mean().backward()
    torch.optim.Adam(trainable, lr=1e-2).step()  # a step keeps the three projections on one A
    expected = backbone.pixel_features(images)
    save_lora(backbone, tmp_path / "lora")
    assert json.loads((tmp_path / "lora" / CONFIG_FILE).read_text())["config"]["shared_a"] is True
    restored = load_lora(DinoBackbone(fresh, kind="dinov3"), tmp_path / "lora")
    assert torch.equal(restored.pixel_features(images), expected)
    named = dict(restored.model.named_parameters(remove_duplicate=False))
    assert (
        named["base_model.model.model.layer.0.attention.q_proj.lora_A.default.weight"]
        is named["base_model.model.model.layer.0.attention.v_proj.lora_A.default.weight"]
    )


def test_separate_a_tensors_do_not_load_into_a_shared_lora(base_model, tmp_path):
    backbone = add_lora(DinoBackbone(copy.deepcopy(base_model), kind="dinov3"))
    _randomize_lora(backbone)  # three different A per block
    save_lora(backbone, tmp_path / "separate", LoraSettings())
    config_path = tmp_path / "separate" / CONFIG_FILE
    envelope = json.loads(config_path.read_text())
    envelope["config"]["shared_a"] = True
    config_path.write_text(json.dumps(envelope))
    with pytest.raises(BackboneError, match="different lora_A tensors"):
        load_lora(DinoBackbone(base_model, kind="dinov3"), tmp_path / "separate")


def test_release_checkpoints_load_with_a_shared_a(base_model, images):
    """The fused-qkv release layout shares its A: loaded, the three projections hold one A parameter."""
    state = {}
    gen = torch.Generator().manual_seed(5)
    for block in range(DEPTH):
        prefix = f"base_model.model.blocks.{block}.attn.qkv"
        state[f"{prefix}.lora_A.default.weight"] = torch.randn(RANK, DIM, generator=gen)
        state[f"{prefix}.lora_B.default.weight"] = torch.randn(3 * DIM, RANK, generator=gen)
    backbone = load_official_lora(DinoBackbone(base_model, kind="dinov3"), state)
    named = dict(backbone.model.named_parameters(remove_duplicate=False))
    a = [named[f"base_model.model.model.layer.1.attention.{t}.lora_A.default.weight"] for t in ("q_proj", "k_proj", "v_proj")]
    assert a[0] is a[1] is a[2] and torch.equal(a[0], state["base_model.model.blocks.1.attn.qkv.lora_A.default.weight"])
