"""Official Meta layout -> transformers layout: exact key mapping, config inference, equal tokens.

Each test builds a tiny random transformers model, writes its weights in Meta's official layout
with an inverse mapping written here (independently of geofeat's converter), converts them back
and checks that the converted weights, and the model built from them, are the original ones.
"""

from __future__ import annotations

import math
import re

import pytest
import torch

pytest.importorskip("transformers")
from safetensors.torch import load_file  # noqa: E402
from transformers import (  # noqa: E402
    Dinov2Config,
    Dinov2Model,
    Dinov2WithRegistersConfig,
    Dinov2WithRegistersModel,
    DINOv3ViTConfig,
    DINOv3ViTModel,
)

from geofeat.backbones import (  # noqa: E402
    DinoBackbone,
    convert_dinov2_state_dict,
    convert_dinov3_state_dict,
    convert_official,
    detect_official_kind,
    infer_dinov2_config,
    infer_dinov3_config,
    load_backbone,
    unwrap_official_checkpoint,
)
from geofeat.errors import BackboneError, GeofeatError  # noqa: E402

# ----------------------------------------------------------------------------- tiny models


def tiny_dinov2(registers: int = 0, swiglu: bool = False, hidden: int = 128, heads: int = 2, seed: int = 0):
    torch.manual_seed(seed)
    common = dict(
        hidden_size=hidden,
        num_hidden_layers=2,
        num_attention_heads=heads,
        mlp_ratio=2,
        patch_size=14,
        image_size=56,
        use_swiglu_ffn=swiglu,
    )
    if registers:
        model = Dinov2WithRegistersModel(Dinov2WithRegistersConfig(num_register_tokens=registers, **common))
    else:
        model = Dinov2Model(Dinov2Config(**common))
    return _randomise(model).eval()


def tiny_dinov3(
    registers: int = 2,
    gated: bool = False,
    key_bias: bool = False,
    qkv_bias: bool = True,
    rope_theta: float = 100.0,
    seed: int = 0,
):
    torch.manual_seed(seed)
    config = DINOv3ViTConfig(
        hidden_size=64,
        intermediate_size=96,
        num_hidden_layers=2,
        num_attention_heads=2,
        patch_size=16,
        image_size=64,
        num_register_tokens=registers,
        use_gated_mlp=gated,
        hidden_act="silu" if gated else "gelu",
        key_bias=key_bias,
        query_bias=qkv_bias,
        value_bias=qkv_bias,
        rope_theta=rope_theta,
    )
    return _randomise(DINOv3ViTModel(config)).eval()


def _randomise(model):
    """Random values everywhere (layer scales, norms, biases, tokens), so a mix-up cannot go unnoticed."""
    with torch.no_grad():
        for param in model.parameters():
            param.copy_(torch.randn_like(param) * 0.2)
    return model


def hub_layout(model, tmp_path) -> dict[str, torch.Tensor]:
    """The serialised transformers layout, as save_pretrained writes it."""
    folder = tmp_path / "hf"
    model.save_pretrained(folder)
    return load_file(folder / "model.safetensors")


# ----------------------------------------------------------------------------- inverse mappings (test-only)

_V2_RENAMES = [
    (r"^embeddings\.cls_token$", "cls_token"),
    (r"^embeddings\.mask_token$", "mask_token"),
    (r"^embeddings\.position_embeddings$", "pos_embed"),
    (r"^embeddings\.register_tokens$", "register_tokens"),
    (r"^embeddings\.patch_embeddings\.projection\.", "patch_embed.proj."),
    (r"^encoder\.layer\.(\d+)\.attention\.output\.dense\.", r"blocks.\1.attn.proj."),
    (r"^encoder\.layer\.(\d+)\.layer_scale(\d)\.lambda1$", r"blocks.\1.ls\2.gamma"),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_in\.", r"blocks.\1.mlp.w12."),
    (r"^encoder\.layer\.(\d+)\.mlp\.weights_out\.", r"blocks.\1.mlp.w3."),
    (r"^encoder\.layer\.(\d+)\.", r"blocks.\1."),
    (r"^layernorm\.", "norm."),
]
_V3_RENAMES = [
    (r"^embeddings\.cls_token$", "cls_token"),
    (r"^embeddings\.register_tokens$", "storage_tokens"),
    (r"^embeddings\.patch_embeddings\.", "patch_embed.proj."),
    (r"^layer\.(\d+)\.attention\.o_proj\.", r"blocks.\1.attn.proj."),
    (r"^layer\.(\d+)\.layer_scale(\d)\.lambda1$", r"blocks.\1.ls\2.gamma"),
    (r"^layer\.(\d+)\.mlp\.gate_proj\.", r"blocks.\1.mlp.w1."),
    (r"^layer\.(\d+)\.mlp\.up_proj\.", r"blocks.\1.mlp.UP."),
    (r"^layer\.(\d+)\.mlp\.down_proj\.", r"blocks.\1.mlp.DOWN."),
    (r"^layer\.(\d+)\.", r"blocks.\1."),
]


def _rename(key: str, rules) -> str:
    for pattern, repl in rules:
        new, n = re.subn(pattern, repl, key)
        if n:
            return new
    return key


def _fuse(hub: dict, prefix: str, names: tuple[str, str, str], suffix: str):
    parts = [hub.pop(f"{prefix}{n}{suffix}") for n in names]
    return torch.cat(parts, dim=0)


def dinov2_official(hub: dict[str, torch.Tensor], depth: int) -> dict[str, torch.Tensor]:
    hub = dict(hub)
    official = {}
    for i in range(depth):
        p = f"encoder.layer.{i}.attention.attention."
        official[f"blocks.{i}.attn.qkv.weight"] = _fuse(hub, p, ("query", "key", "value"), ".weight")
        if f"{p}query.bias" in hub:
            official[f"blocks.{i}.attn.qkv.bias"] = _fuse(hub, p, ("query", "key", "value"), ".bias")
    official.update({_rename(k, _V2_RENAMES): v for k, v in hub.items()})
    return official


def dinov3_official(
    hub: dict[str, torch.Tensor], depth: int, gated: bool, masked: bool = True, theta: float = 100.0, head_dim: int = 32
) -> dict[str, torch.Tensor]:
    hub = dict(hub)
    official = {"mask_token": hub.pop("embeddings.mask_token").reshape(1, -1)}
    for i in range(depth):
        p = f"layer.{i}.attention."
        official[f"blocks.{i}.attn.qkv.weight"] = _fuse(hub, p, ("q_proj", "k_proj", "v_proj"), ".weight")
        if f"{p}q_proj.bias" in hub:
            q, v = hub.pop(f"{p}q_proj.bias"), hub.pop(f"{p}v_proj.bias")
            k = hub.pop(f"{p}k_proj.bias") if not masked else torch.randn_like(q)  # masked: any value, never used
            official[f"blocks.{i}.attn.qkv.bias"] = torch.cat([q, k, v])
            if masked:
                official[f"blocks.{i}.attn.qkv.bias_mask"] = torch.cat(
                    [torch.ones_like(q), torch.zeros_like(k), torch.ones_like(v)]
                )
    for key, value in hub.items():
        name = _rename(key, _V3_RENAMES)
        name = name.replace("mlp.UP.", "mlp.w2." if gated else "mlp.fc1.").replace(
            "mlp.DOWN.", "mlp.w3." if gated else "mlp.fc2."
        )
        official[name] = value
    # official periods: base ** (2 * arange(head_dim // 4) / (head_dim // 2))
    official["rope_embed.periods"] = theta ** (2 * torch.arange(head_dim // 4, dtype=torch.float32) / (head_dim // 2))
    return official


def _tokens(model, pixels):
    with torch.no_grad():
        return model(pixel_values=pixels).last_hidden_state


def _assert_same_dict(a: dict, b: dict):
    assert sorted(a) == sorted(b)
    for key in a:
        assert a[key].shape == b[key].shape, key
        assert torch.equal(a[key], b[key]), key


def _build(config, state_dict):
    from transformers import AutoModel

    cls = type(AutoModel.from_config(config))
    model, info = cls.from_pretrained(None, config=config, state_dict=state_dict, output_loading_info=True)
    assert not info["missing_keys"] and not info["unexpected_keys"] and not info["mismatched_keys"], info
    return model.eval()


# ----------------------------------------------------------------------------- DINOv2


@pytest.mark.parametrize(("registers", "swiglu"), [(0, False), (4, True)])
def test_dinov2_official_layout_converts_back_exactly(tmp_path, registers, swiglu):
    model = tiny_dinov2(registers=registers, swiglu=swiglu)
    hub = hub_layout(model, tmp_path)
    official = dinov2_official(hub, depth=2)
    assert "blocks.0.attn.qkv.weight" in official and "pos_embed" in official
    _assert_same_dict(convert_dinov2_state_dict(official), hub)

    config = infer_dinov2_config(official)
    assert config.model_type == model.config.model_type
    for field in (
        "hidden_size",
        "num_hidden_layers",
        "num_attention_heads",
        "patch_size",
        "image_size",
        "mlp_ratio",
        "use_swiglu_ffn",
    ):
        assert getattr(config, field) == getattr(model.config, field), field
    assert getattr(config, "num_register_tokens", 0) == registers

    pixels = torch.randn(2, 3, 56, 42)  # non-square: position embeddings interpolated at run time
    rebuilt = _build(*convert_official(official, "dinov2"))
    torch.testing.assert_close(_tokens(rebuilt, pixels), _tokens(model, pixels), atol=1e-6, rtol=0)


def test_dinov2_chunked_blocks_and_missing_layer_scale(tmp_path):
    model = tiny_dinov2()
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lambda1" in name:
                param.fill_(1.0)  # identity layer scale == no LayerScale module in the official model
    official = dinov2_official(hub_layout(model, tmp_path), depth=2)
    chunked = {re.sub(r"^blocks\.(\d+)\.", r"blocks.0.\1.", k): v for k, v in official.items() if ".gamma" not in k}
    assert not any(".ls1." in k for k in chunked)
    pixels = torch.randn(1, 3, 56, 56)
    rebuilt = _build(*convert_official(chunked, "dinov2"))
    torch.testing.assert_close(_tokens(rebuilt, pixels), _tokens(model, pixels), atol=1e-6, rtol=0)


def test_dinov2_heads_cannot_be_inferred_without_64_dim_heads(tmp_path):
    model = tiny_dinov2(hidden=96, heads=3)
    official = dinov2_official(hub_layout(model, tmp_path), depth=2)
    with pytest.raises(BackboneError, match="num_attention_heads"):
        infer_dinov2_config(official)
    config, state_dict = convert_official(official, "dinov2", overrides={"num_attention_heads": 3})
    pixels = torch.randn(1, 3, 28, 28)
    torch.testing.assert_close(_tokens(_build(config, state_dict), pixels), _tokens(model, pixels), atol=1e-6, rtol=0)
    with pytest.raises(BackboneError, match="unknown config field"):
        convert_official(official, "dinov2", overrides={"num_attention_heads": 3, "num_heads": 3})


# ----------------------------------------------------------------------------- DINOv3


@pytest.mark.parametrize(("registers", "gated", "qkv_bias"), [(2, False, True), (0, True, False)])
def test_dinov3_official_layout_converts_back_exactly(tmp_path, registers, gated, qkv_bias):
    model = tiny_dinov3(registers=registers, gated=gated, qkv_bias=qkv_bias)
    hub = hub_layout(model, tmp_path)
    official = dinov3_official(hub, depth=2, gated=gated)
    official["local_cls_norm.weight"] = torch.ones(64)  # training-only, dropped
    assert official["mask_token"].shape == (1, 64)
    converted = convert_dinov3_state_dict(official)
    if registers == 0:  # transformers keeps an empty (1, 0, D) parameter
        assert converted["embeddings.register_tokens"].shape == hub["embeddings.register_tokens"].shape == (1, 0, 64)
    _assert_same_dict(converted, hub)
    assert not any("k_proj.bias" in k for k in converted)  # the masked key bias is dropped

    config = infer_dinov3_config(official)
    for field in (
        "hidden_size",
        "num_hidden_layers",
        "num_attention_heads",
        "patch_size",
        "num_register_tokens",
        "intermediate_size",
        "use_gated_mlp",
        "hidden_act",
        "query_bias",
        "key_bias",
        "value_bias",
        "rope_theta",
    ):
        assert getattr(config, field) == getattr(model.config, field), field

    pixels = torch.randn(2, 3, 64, 48)
    rebuilt = _build(config, converted)
    torch.testing.assert_close(_tokens(rebuilt, pixels), _tokens(model, pixels), atol=1e-6, rtol=0)


def test_dinov3_unmasked_key_bias_is_kept(tmp_path):
    model = tiny_dinov3(key_bias=True)
    official = dinov3_official(hub_layout(model, tmp_path), depth=2, gated=False, masked=False)
    config, converted = convert_official(official, "dinov3")
    assert config.key_bias is True and "layer.0.attention.k_proj.bias" in converted
    pixels = torch.randn(1, 3, 32, 32)
    torch.testing.assert_close(_tokens(_build(config, converted), pixels), _tokens(model, pixels), atol=1e-6, rtol=0)


def test_dinov3_dropping_the_masked_bias_matters_only_because_it_is_masked(tmp_path):
    """Sanity check of the test itself: a non-zero key bias changes the tokens (RoPE breaks the softmax invariance)."""
    model = tiny_dinov3(key_bias=True)
    pixels = torch.randn(1, 3, 32, 32)
    before = _tokens(model, pixels)
    with torch.no_grad():
        model.model.layer[0].attention.k_proj.bias.add_(1.0)
    assert not torch.allclose(_tokens(model, pixels), before, atol=1e-4)


@pytest.mark.parametrize("bad", ["wrong", "nan"])
def test_dinov3_bad_bias_mask_is_refused(tmp_path, bad):
    official = dinov3_official(hub_layout(tiny_dinov3(), tmp_path), depth=2, gated=False)
    mask = official["blocks.1.attn.qkv.bias_mask"]
    official["blocks.1.attn.qkv.bias_mask"] = torch.ones_like(mask) if bad == "wrong" else torch.full_like(mask, math.nan)
    with pytest.raises(BackboneError, match=r"blocks\.1\.attn\.qkv\.bias_mask"):
        convert_dinov3_state_dict(official)


def test_dinov3_rope_base_is_recovered_and_checked(tmp_path):
    model = tiny_dinov3(rope_theta=1000.0)
    official = dinov3_official(hub_layout(model, tmp_path), depth=2, gated=False, theta=1000.0)
    assert infer_dinov3_config(official).rope_theta == 1000.0
    pixels = torch.randn(1, 3, 48, 32)
    torch.testing.assert_close(
        _tokens(_build(*convert_official(official, "dinov3")), pixels), _tokens(model, pixels), atol=1e-6, rtol=0
    )
    official["rope_embed.periods"] = torch.tensor([1.0, 3.0, 4.0, 50.0])  # min/max-period style, not a base power
    with pytest.raises(BackboneError, match="rope_embed.periods"):
        infer_dinov3_config(official)


# ----------------------------------------------------------------------------- errors and wrappers


def test_kind_mismatch_unknown_keys_and_missing_keys_are_clear(tmp_path):
    v3 = dinov3_official(hub_layout(tiny_dinov3(), tmp_path), depth=2, gated=False)
    v2 = dinov2_official(hub_layout(tiny_dinov2(), tmp_path / "b"), depth=2)
    assert detect_official_kind(v3) == "dinov3" and detect_official_kind(v2) == "dinov2"
    with pytest.raises(BackboneError, match="kind='dinov3'"):
        convert_official(v3, "dinov2")
    with pytest.raises(BackboneError, match="kind='dinov2'"):
        convert_official(v2, "dinov3")
    with pytest.raises(BackboneError, match=r"blocks\.0\.attn\.extra\.weight"):
        convert_dinov2_state_dict({**v2, "blocks.0.attn.extra.weight": torch.zeros(1)})
    with pytest.raises(BackboneError, match="head.weight"):
        convert_dinov3_state_dict({**v3, "head.weight": torch.zeros(1)})
    with pytest.raises(BackboneError, match="'norm.weight'"):
        convert_dinov2_state_dict({k: v for k, v in v2.items() if k != "norm.weight"})
    with pytest.raises(BackboneError, match="cls_norm"):
        infer_dinov3_config({**v3, "cls_norm.weight": torch.ones(64)})
    with pytest.raises(GeofeatError, match="kind must be"):
        convert_official(v2, "dinov4")


def test_unwrap_training_checkpoint(tmp_path):
    v2 = dinov2_official(hub_layout(tiny_dinov2(), tmp_path), depth=2)
    wrapped = {"teacher": {f"backbone.{k}": v for k, v in v2.items()} | {"dino_head.w": torch.zeros(1)}, "iteration": 3}
    _assert_same_dict(unwrap_official_checkpoint(wrapped), v2)
    with pytest.raises(BackboneError, match="cls_token"):
        unwrap_official_checkpoint({"foo": torch.zeros(1)})
    with pytest.raises(BackboneError, match="state dict"):
        unwrap_official_checkpoint([1, 2])


# ----------------------------------------------------------------------------- through load_backbone


@pytest.mark.parametrize("kind", ["dinov2", "dinov3"])
def test_pth_round_trip_through_load_backbone(tmp_path, kind):
    if kind == "dinov2":
        model = tiny_dinov2(registers=4)
        official = dinov2_official(hub_layout(model, tmp_path), depth=2)
        size = 28
    else:
        model = tiny_dinov3()
        official = dinov3_official(hub_layout(model, tmp_path), depth=2, gated=False)
        size = 32
    path = tmp_path / f"{kind}_official.pth"
    torch.save(official, path)
    loaded = load_backbone(path, kind=kind, device="cpu")
    reference = DinoBackbone(model, kind=kind)
    images = torch.rand(2, size, 2 * size, 3)
    torch.testing.assert_close(loaded.patch_features(images), reference.patch_features(images), atol=1e-6, rtol=0)
    assert loaded.weights_digest == reference.weights_digest  # same weights, whatever the file layout
    other = "dinov3" if kind == "dinov2" else "dinov2"
    with pytest.raises(BackboneError, match=f"kind='{kind}'"):
        load_backbone(path, kind=other, device="cpu")
