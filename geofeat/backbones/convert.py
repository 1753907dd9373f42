"""Official Meta DINO checkpoints -> the Hugging Face `transformers` layout.

Meta publishes DINOv2 weights as torch-hub ``.pth`` files (``dinov2_vitb14_pretrain.pth``,
``dinov2_vitb14_reg4_pretrain.pth``, ...) and DINOv3 weights as release ``.pth`` files
(``dinov3_vitb16_pretrain_lvd1689m-73cec8be.pth``, ...). Both are plain state dicts of the
models in facebookresearch/dinov2 and facebookresearch/dinov3. This module renames them,
tensor by tensor, into the layout of the checkpoints that `transformers` writes with
``save_pretrained`` and that the Hub model pages hold (``facebook/dinov2-base``,
``facebook/dinov3-vitb16-pretrain-lvd1689m``). That serialised layout is the stable one:
newer `transformers` releases rename some modules internally (for example DINOv2's
``attention.attention.query`` became ``attention.q_proj``) and translate the serialised names
while loading, so the output of this module is loaded with ``from_pretrained(None,
config=..., state_dict=...)``, never with a bare ``load_state_dict``.

DINOv2 (``i`` = block index; chunked training checkpoints ``blocks.<chunk>.<i>.`` are accepted)::

    cls_token            (1, 1, D)       -> embeddings.cls_token
    pos_embed            (1, 1 + M*M, D) -> embeddings.position_embeddings
    register_tokens      (1, R, D)       -> embeddings.register_tokens      (Dinov2WithRegisters)
    mask_token           (1, D)          -> embeddings.mask_token
    patch_embed.proj.*                   -> embeddings.patch_embeddings.projection.*
    blocks.i.norm1.*, norm2.*            -> encoder.layer.i.norm1.*, norm2.*
    blocks.i.attn.qkv.weight (3D, D)     -> encoder.layer.i.attention.attention.{query,key,value}.weight
    blocks.i.attn.qkv.bias   (3D,)       -> encoder.layer.i.attention.attention.{query,key,value}.bias
    blocks.i.attn.proj.*                 -> encoder.layer.i.attention.output.dense.*
    blocks.i.ls1.gamma, ls2.gamma        -> encoder.layer.i.layer_scale1.lambda1, layer_scale2.lambda1
    blocks.i.mlp.fc1.*, fc2.*            -> encoder.layer.i.mlp.fc1.*, fc2.*
    blocks.i.mlp.w12.*, w3.* (SwiGLU)    -> encoder.layer.i.mlp.weights_in.*, weights_out.*
    norm.*                               -> layernorm.*

DINOv3::

    cls_token            (1, 1, D)       -> embeddings.cls_token
    mask_token           (1, D)          -> embeddings.mask_token           reshaped to (1, 1, D)
    storage_tokens       (1, R, D)       -> embeddings.register_tokens      (absent: an empty (1, 0, D))
    patch_embed.proj.*                   -> embeddings.patch_embeddings.*
    rope_embed.periods   (head_dim/4,)   -> dropped: transformers recomputes ``inv_freq = 1 / periods``
                                            from ``rope_theta``, which is inferred from the periods and
                                            checked against them
    blocks.i.norm1.*, norm2.*            -> layer.i.norm1.*, norm2.*
    blocks.i.attn.qkv.weight (3D, D)     -> layer.i.attention.{q,k,v}_proj.weight
    blocks.i.attn.qkv.bias   (3D,)       -> layer.i.attention.q_proj.bias, v_proj.bias; the key third
                                            is dropped when ``bias_mask`` zeroes it (released models),
                                            kept as k_proj.bias (``key_bias=True``) when there is no mask
    blocks.i.attn.qkv.bias_mask          -> dropped after checking it is (1, 0, 1) by thirds
    blocks.i.attn.proj.*                 -> layer.i.attention.o_proj.*
    blocks.i.ls1.gamma, ls2.gamma        -> layer.i.layer_scale1.lambda1, layer_scale2.lambda1
    blocks.i.mlp.fc1.*, fc2.*            -> layer.i.mlp.up_proj.*, down_proj.*
    blocks.i.mlp.w1.*, w2.*, w3.* (SwiGLU) -> layer.i.mlp.gate_proj.*, up_proj.*, down_proj.*
    norm.*                               -> norm.*
    local_cls_norm.*                     -> dropped (used only for local crops in training)

A block without layer scale (``ls1``/``ls2`` absent, i.e. identity) gets ``lambda1 = 1``, which is
the same function. ``cls_norm`` (``untie_cls_and_patch_norms``, used by no released model) has no
counterpart in `transformers` and is refused.

What the shapes give and what they do not
-----------------------------------------
Inferred: width ``D``, depth, patch size, input channels, register/storage tokens, qkv/proj/ffn
biases, FFN type and hidden size, DINOv2's native grid (``image_size``), DINOv3's head size
(``4 * len(periods)``) and RoPE base. Not in the state dict, set to the values of Meta's released
models and changeable through ``overrides`` (any field of the transformers config class):

* DINOv2 ``num_attention_heads``: ``D // 64`` (every released DINOv2 has 64-dim heads);
* DINOv2 ``layer_norm_eps=1e-6`` and DINOv3 ``layer_norm_eps=1e-5`` (``layernormbf16``);
* ``hidden_act``: GELU for the plain MLP, SiLU for SwiGLU;
* DINOv3 RoPE coordinates normalised per axis (``"separate"``, the only mode transformers has)
  and its training-time coordinate augmentation (inactive in ``eval()``);
* DINOv2 position-embedding interpolation at other resolutions is transformers' own (bicubic to
  the target grid; Meta's non-register models add a 0.1 offset to the scale factor).
"""

from __future__ import annotations

import logging
import math
import re
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import torch

from geofeat.errors import BackboneError, MissingDependencyError

if TYPE_CHECKING:
    from transformers import PreTrainedConfig

logger = logging.getLogger(__name__)

Tensor = torch.Tensor

__all__ = [
    "convert_dinov2_state_dict",
    "convert_dinov3_state_dict",
    "convert_official",
    "detect_official_kind",
    "infer_dinov2_config",
    "infer_dinov3_config",
    "unwrap_official_checkpoint",
]

_CHUNKED_BLOCK = re.compile(r"^blocks\.\d+\.(\d+)\.(.+)$")
_BLOCK = re.compile(r"^blocks\.(\d+)\.(.+)$")

_DINOV2_BLOCK_RENAMES = {
    "norm1.weight": "norm1.weight",
    "norm1.bias": "norm1.bias",
    "norm2.weight": "norm2.weight",
    "norm2.bias": "norm2.bias",
    "attn.proj.weight": "attention.output.dense.weight",
    "attn.proj.bias": "attention.output.dense.bias",
    "ls1.gamma": "layer_scale1.lambda1",
    "ls2.gamma": "layer_scale2.lambda1",
    "mlp.fc1.weight": "mlp.fc1.weight",
    "mlp.fc1.bias": "mlp.fc1.bias",
    "mlp.fc2.weight": "mlp.fc2.weight",
    "mlp.fc2.bias": "mlp.fc2.bias",
    "mlp.w12.weight": "mlp.weights_in.weight",
    "mlp.w12.bias": "mlp.weights_in.bias",
    "mlp.w3.weight": "mlp.weights_out.weight",
    "mlp.w3.bias": "mlp.weights_out.bias",
}
_DINOV2_QKV = ("attention.attention.query", "attention.attention.key", "attention.attention.value")

_DINOV3_BLOCK_RENAMES = {
    "norm1.weight": "norm1.weight",
    "norm1.bias": "norm1.bias",
    "norm2.weight": "norm2.weight",
    "norm2.bias": "norm2.bias",
    "attn.proj.weight": "attention.o_proj.weight",
    "attn.proj.bias": "attention.o_proj.bias",
    "ls1.gamma": "layer_scale1.lambda1",
    "ls2.gamma": "layer_scale2.lambda1",
    "mlp.fc1.weight": "mlp.up_proj.weight",
    "mlp.fc1.bias": "mlp.up_proj.bias",
    "mlp.fc2.weight": "mlp.down_proj.weight",
    "mlp.fc2.bias": "mlp.down_proj.bias",
    "mlp.w1.weight": "mlp.gate_proj.weight",
    "mlp.w1.bias": "mlp.gate_proj.bias",
    "mlp.w2.weight": "mlp.up_proj.weight",
    "mlp.w2.bias": "mlp.up_proj.bias",
    "mlp.w3.weight": "mlp.down_proj.weight",
    "mlp.w3.bias": "mlp.down_proj.bias",
}
_DINOV3_QKV = ("attention.q_proj", "attention.k_proj", "attention.v_proj")
_DINOV3_DROPPED_GLOBALS = ("local_cls_norm.weight", "local_cls_norm.bias")

_DINOV2_HEAD_DIM = 64
_SOURCES = "Meta's releases: https://github.com/facebookresearch/dinov2 and https://github.com/facebookresearch/dinov3"


def require_transformers() -> Any:
    """Import `transformers`, or raise `MissingDependencyError` naming the ``dino`` extra.

    Returns
    -------
    module
        The imported ``transformers`` package.
    """
    try:
        import transformers
    except ImportError as exc:
        raise MissingDependencyError(
            "DINO backbones need the optional dependency 'transformers' (>= 5.4), which is not installed; "
            "install it with: pip install 'geofeat[dino]'"
        ) from exc
    return transformers


# ----------------------------------------------------------------------------- input checks


def unwrap_official_checkpoint(obj: Any) -> dict[str, Tensor]:
    """Return the backbone state dict inside a loaded official checkpoint.

    Parameters
    ----------
    obj : Mapping
        What ``torch.load`` returned: a plain state dict (the released ``.pth`` files), or a
        training checkpoint holding one under ``"teacher"``, ``"model"`` or ``"state_dict"``,
        possibly with a ``"backbone."`` or ``"module."`` prefix on every backbone key.

    Returns
    -------
    dict[str, torch.Tensor]
        Official key names without prefix.
    """
    if not isinstance(obj, Mapping):
        raise BackboneError(
            f"expected an official checkpoint holding a state dict (a mapping of names to tensors), found {type(obj).__name__}"
        )
    for wrapper in ("teacher", "model", "state_dict"):
        if wrapper in obj and isinstance(obj[wrapper], Mapping) and not isinstance(obj[wrapper], Tensor):
            obj = obj[wrapper]
            break
    for prefix in ("module.", "backbone."):
        if any(k.startswith(prefix) for k in obj) and not any(k.startswith("blocks.") for k in obj):
            obj = {k[len(prefix) :]: v for k, v in obj.items() if k.startswith(prefix)}
    tensors = {k: v for k, v in obj.items() if isinstance(v, Tensor)}
    if not tensors or "cls_token" not in tensors:
        found = ", ".join(sorted(map(str, obj))[:8]) or "nothing"
        raise BackboneError(
            "expected an official DINOv2/DINOv3 state dict with keys such as 'cls_token', 'patch_embed.proj.weight' and "
            f"'blocks.0.attn.qkv.weight', found keys: {found}. Pass the backbone .pth from {_SOURCES}"
        )
    return tensors


def detect_official_kind(official: Mapping[str, Tensor]) -> str | None:
    """Tell a DINOv2 from a DINOv3 official state dict by its keys.

    Returns
    -------
    str or None
        ``"dinov3"`` (RoPE periods, storage tokens or a masked qkv bias), ``"dinov2"`` (a learned
        ``pos_embed``), or None when neither marker is present.
    """
    if "pos_embed" in official:
        return "dinov2"
    if "rope_embed.periods" in official or "storage_tokens" in official or any(k.endswith("qkv.bias_mask") for k in official):
        return "dinov3"
    return None


def _require(official: Mapping[str, Tensor], key: str, kind: str) -> Tensor:
    if key not in official:
        raise BackboneError(f"the official {kind} state dict has no '{key}'; it is truncated or not a {kind} backbone checkpoint")
    return official[key]


def _take(tensors: dict[str, Tensor], key: str, kind: str) -> Tensor:
    """Pop a required tensor, with a clear error when it is missing."""
    value = _require(tensors, key, kind)
    del tensors[key]
    return value


def _split_blocks(official: Mapping[str, Tensor], kind: str) -> tuple[dict[str, Tensor], list[dict[str, Tensor]]]:
    """Separate global tensors from per-block tensors (``blocks.i.`` or chunked ``blocks.c.i.``)."""
    globals_: dict[str, Tensor] = {}
    blocks: dict[int, dict[str, Tensor]] = {}
    for key, value in official.items():
        match = _CHUNKED_BLOCK.match(key) or _BLOCK.match(key)
        if match is None:
            globals_[key] = value
        else:
            blocks.setdefault(int(match.group(1)), {})[match.group(2)] = value
    depth = len(blocks)
    if depth == 0 or sorted(blocks) != list(range(depth)):
        raise BackboneError(
            f"the official {kind} state dict should hold blocks 0..N-1, found block indices {sorted(blocks)[:10]}"
        )
    return globals_, [blocks[i] for i in range(depth)]


def _refuse_leftovers(leftover: Mapping[str, Any], kind: str) -> None:
    if leftover:
        names = ", ".join(sorted(leftover)[:10])
        raise BackboneError(
            f"the official {kind} state dict has tensors with no transformers counterpart: {names}. "
            "Only the plain ViT backbones that Meta released are supported"
        )


def _patch_geometry(official: Mapping[str, Tensor], kind: str) -> tuple[int, int, int]:
    """Return (width D, patch size, input channels) from ``patch_embed.proj.weight`` (D, C, p, p)."""
    weight = _require(official, "patch_embed.proj.weight", kind)
    if weight.ndim != 4 or weight.shape[2] != weight.shape[3]:
        raise BackboneError(f"expected patch_embed.proj.weight of shape (D, C, p, p), found {tuple(weight.shape)}")
    return int(weight.shape[0]), int(weight.shape[2]), int(weight.shape[1])


def _apply_overrides(config_cls: type, fields: dict[str, Any], overrides: Mapping[str, Any] | None) -> PreTrainedConfig:
    """Build ``config_cls(**fields)`` with ``overrides`` winning; unknown override names are refused."""
    overrides = dict(overrides or {})
    known = set(config_cls().to_dict())
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise BackboneError(
            f"unknown config field(s) {unknown} for {config_cls.__name__}; known fields include {sorted(known)[:30]}"
        )
    try:
        return config_cls(**{**fields, **overrides})
    except Exception as exc:  # transformers' strict dataclass validation
        raise BackboneError(f"invalid {config_cls.__name__} settings {overrides}: {exc}") from exc


# ----------------------------------------------------------------------------- DINOv2


def _dinov2_mlp_fields(block: Mapping[str, Tensor], dim: int) -> dict[str, Any]:
    """FFN type and integer ``mlp_ratio`` that reproduce the official FFN hidden size."""
    if "mlp.fc1.weight" in block:
        hidden = int(block["mlp.fc1.weight"].shape[0])
        if hidden % dim:
            raise BackboneError(
                f"DINOv2 MLP hidden size {hidden} is not an integer multiple of the width {dim}; transformers needs an integer mlp_ratio"
            )
        return {"use_swiglu_ffn": False, "mlp_ratio": hidden // dim}
    if "mlp.w12.weight" in block:
        hidden = int(block["mlp.w12.weight"].shape[0]) // 2
        for ratio in range(1, 17):  # transformers: (int(D * ratio * 2 / 3) + 7) // 8 * 8
            if (int(dim * ratio * 2 / 3) + 7) // 8 * 8 == hidden:
                return {"use_swiglu_ffn": True, "mlp_ratio": ratio}
        raise BackboneError(f"no integer mlp_ratio gives the DINOv2 SwiGLU hidden size {hidden} for width {dim}")
    raise BackboneError("the official DINOv2 block 0 has neither 'mlp.fc1.weight' nor 'mlp.w12.weight'")


def infer_dinov2_config(official: Mapping[str, Tensor], overrides: Mapping[str, Any] | None = None) -> PreTrainedConfig:
    """Infer the transformers config of an official DINOv2 state dict from its tensor shapes.

    Parameters
    ----------
    official : Mapping[str, torch.Tensor]
        Official DINOv2 state dict (keys as in ``dinov2_vitb14_pretrain.pth``).
    overrides : Mapping[str, Any], optional
        Config fields that the shapes cannot give (see the module docstring), e.g.
        ``{"num_attention_heads": 12}``; they win over inferred values.

    Returns
    -------
    transformers.Dinov2Config or transformers.Dinov2WithRegistersConfig
        The latter when the state dict holds ``register_tokens``.
    """
    transformers = require_transformers()
    dim, patch, channels = _patch_geometry(official, "DINOv2")
    globals_, blocks = _split_blocks(official, "DINOv2")
    n_pos = int(_require(official, "pos_embed", "DINOv2").shape[1]) - 1
    grid = math.isqrt(n_pos)
    if grid * grid != n_pos:
        raise BackboneError(f"DINOv2 pos_embed should cover a square grid plus CLS, found {n_pos} patch positions")
    default_heads = dim // _DINOV2_HEAD_DIM if dim % _DINOV2_HEAD_DIM == 0 else 0
    heads = dict(overrides or {}).get("num_attention_heads", default_heads)
    if heads < 1 or dim % heads:
        raise BackboneError(
            f"cannot infer the number of attention heads for width {dim} (released DINOv2 models use 64-dim heads); "
            "pass overrides={'num_attention_heads': H} with H dividing the width"
        )
    fields: dict[str, Any] = {
        "hidden_size": dim,
        "num_hidden_layers": len(blocks),
        "num_attention_heads": heads,
        "patch_size": patch,
        "num_channels": channels,
        "image_size": grid * patch,
        "qkv_bias": "attn.qkv.bias" in blocks[0],
        "layer_norm_eps": 1e-6,
        "hidden_act": "gelu",
        **_dinov2_mlp_fields(blocks[0], dim),
    }
    if "register_tokens" in globals_:
        fields["num_register_tokens"] = int(globals_["register_tokens"].shape[1])
        return _apply_overrides(transformers.Dinov2WithRegistersConfig, fields, overrides)
    return _apply_overrides(transformers.Dinov2Config, fields, overrides)


def _split_qkv(tensor: Tensor, names: tuple[str, str, str], prefix: str, suffix: str) -> dict[str, Tensor]:
    """Split a fused (3D, ...) qkv tensor into three (D, ...) tensors named ``prefix + name + suffix``."""
    if tensor.shape[0] % 3:
        raise BackboneError(f"fused qkv tensor {prefix}...{suffix} has first dimension {tensor.shape[0]}, not a multiple of 3")
    return {f"{prefix}{name}{suffix}": part.clone() for name, part in zip(names, tensor.chunk(3, dim=0), strict=True)}


def _ones_layer_scale(block: dict[str, Tensor], dim: int, dtype: torch.dtype) -> None:
    """Identity layer scale (no ``ls1``/``ls2`` in the block) becomes ``gamma = 1``."""
    for name in ("ls1.gamma", "ls2.gamma"):
        block.setdefault(name, torch.ones(dim, dtype=dtype))


def _convert_dinov2_block(i: int, block: Mapping[str, Tensor]) -> dict[str, Tensor]:
    prefix = f"encoder.layer.{i}."
    block = dict(block)
    norm1 = _require(block, "norm1.weight", f"DINOv2 (block {i})")
    _ones_layer_scale(block, int(norm1.shape[0]), norm1.dtype)
    out = _split_qkv(_take(block, "attn.qkv.weight", f"DINOv2 (block {i})"), _DINOV2_QKV, prefix, ".weight")
    if "attn.qkv.bias" in block:
        out.update(_split_qkv(block.pop("attn.qkv.bias"), _DINOV2_QKV, prefix, ".bias"))
    for name in [n for n in block if n in _DINOV2_BLOCK_RENAMES]:
        out[prefix + _DINOV2_BLOCK_RENAMES[name]] = block.pop(name)
    _refuse_leftovers({f"blocks.{i}.{n}": v for n, v in block.items()}, "DINOv2")
    return out


def convert_dinov2_state_dict(official: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Rename an official DINOv2 state dict into the transformers (Hub) layout.

    Parameters
    ----------
    official : Mapping[str, torch.Tensor]
        Official DINOv2 state dict (torch-hub ``.pth``), with or without register tokens.

    Returns
    -------
    dict[str, torch.Tensor]
        Same tensors (dtypes kept; the fused qkv split into three), keyed as in the
        ``model.safetensors`` of ``facebook/dinov2-*``; load with ``Dinov2Model.from_pretrained(
        None, config=infer_dinov2_config(official), state_dict=...)``.
    """
    _patch_geometry(official, "DINOv2")
    globals_, blocks = _split_blocks(official, "DINOv2")
    globals_ = dict(globals_)
    out: dict[str, Tensor] = {
        "embeddings.cls_token": _take(globals_, "cls_token", "DINOv2"),
        "embeddings.position_embeddings": _take(globals_, "pos_embed", "DINOv2"),
        "embeddings.patch_embeddings.projection.weight": _take(globals_, "patch_embed.proj.weight", "DINOv2"),
        "layernorm.weight": _take(globals_, "norm.weight", "DINOv2"),
    }
    renames = {
        "mask_token": "embeddings.mask_token",
        "register_tokens": "embeddings.register_tokens",
        "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
        "norm.bias": "layernorm.bias",
    }
    out.update({renames[k]: globals_.pop(k) for k in list(globals_) if k in renames})
    if "embeddings.mask_token" not in out:  # never read at inference; transformers expects the parameter
        out["embeddings.mask_token"] = torch.zeros(
            1, out["embeddings.cls_token"].shape[-1], dtype=out["embeddings.cls_token"].dtype
        )
    _refuse_leftovers(globals_, "DINOv2")
    for i, block in enumerate(blocks):
        out.update(_convert_dinov2_block(i, block))
    return out


# ----------------------------------------------------------------------------- DINOv3


def _rope_theta(periods: Tensor, head_dim: int) -> float:
    """Recover the RoPE base from official periods ``base ** (4 i / head_dim)``, i < head_dim / 4, and check them."""
    n = periods.numel()
    p = periods.detach().double().cpu()
    if n < 2:
        return 100.0  # a single period (== 1) carries no base; the official default
    base = float(p[-1]) ** (n / (n - 1))
    if abs(base - round(base)) < 1e-3 * base:
        base = float(round(base))
    expected = base ** (torch.arange(n, dtype=torch.float64) * 4 / head_dim)
    tol = 1e-2 if periods.dtype in (torch.bfloat16, torch.float16) else 1e-4
    if not torch.allclose(p, expected, rtol=tol, atol=0.0):
        raise BackboneError(
            f"rope_embed.periods {p[:4].tolist()}... do not follow base ** (4 i / {head_dim}) for any base; checkpoints "
            "made with pos_embed_rope_min_period/max_period cannot be expressed in transformers (rope_theta only)"
        )
    return base


def _check_k_bias_mask(mask: Tensor, where: str) -> None:
    """The official ``LinearKMaskedBias`` multiplies the qkv bias by a mask that must be 1, 0, 1 by thirds."""
    q, k, v = mask.detach().float().cpu().chunk(3)
    if not (torch.all(q == 1) and torch.all(k == 0) and torch.all(v == 1)):
        raise BackboneError(
            f"{where}.bias_mask should keep the query and value biases (ones) and mask the key bias (zeros); "
            f"found query {q.unique().tolist()[:4]}, key {k.unique().tolist()[:4]}, value {v.unique().tolist()[:4]} "
            "(NaN means the mask was never initialised)"
        )


def _dinov3_mlp_fields(block: Mapping[str, Tensor]) -> dict[str, Any]:
    if "mlp.w1.weight" in block:
        return {
            "use_gated_mlp": True,
            "hidden_act": "silu",
            "intermediate_size": int(block["mlp.w1.weight"].shape[0]),
            "mlp_bias": "mlp.w1.bias" in block,
        }
    if "mlp.fc1.weight" in block:
        return {
            "use_gated_mlp": False,
            "hidden_act": "gelu",
            "intermediate_size": int(block["mlp.fc1.weight"].shape[0]),
            "mlp_bias": "mlp.fc1.bias" in block,
        }
    raise BackboneError("the official DINOv3 block 0 has neither 'mlp.fc1.weight' nor 'mlp.w1.weight'")


def _dinov3_heads(official: Mapping[str, Tensor], dim: int, overrides: Mapping[str, Any] | None) -> tuple[int, float]:
    """Number of heads and RoPE base, from ``rope_embed.periods`` (head_dim / 4 entries)."""
    periods = official.get("rope_embed.periods")
    override = dict(overrides or {}).get("num_attention_heads")
    if periods is None:
        heads = override or dim // 64
        logger.warning("official DINOv3 state dict has no rope_embed.periods; assuming %d heads and rope_theta=100", heads)
        return heads, 100.0
    head_dim = 4 * periods.numel()
    if dim % head_dim or (override is not None and override * head_dim != dim):
        raise BackboneError(
            f"rope_embed.periods has {periods.numel()} entries, i.e. head size {head_dim}, which does not fit width {dim}"
            + (f" with {override} heads" if override is not None else "")
        )
    return dim // head_dim, _rope_theta(periods, head_dim)


def infer_dinov3_config(official: Mapping[str, Tensor], overrides: Mapping[str, Any] | None = None) -> PreTrainedConfig:
    """Infer the transformers config of an official DINOv3 ViT state dict from its tensor shapes.

    Parameters
    ----------
    official : Mapping[str, torch.Tensor]
        Official DINOv3 state dict (keys as in ``dinov3_vitb16_pretrain_lvd1689m-*.pth``).
    overrides : Mapping[str, Any], optional
        Config fields the shapes cannot give (see the module docstring); they win.

    Returns
    -------
    transformers.DINOv3ViTConfig
    """
    transformers = require_transformers()
    dim, patch, channels = _patch_geometry(official, "DINOv3")
    globals_, blocks = _split_blocks(official, "DINOv3")
    if "cls_norm.weight" in globals_:
        raise BackboneError(
            "this DINOv3 checkpoint unties the CLS and patch norms (cls_norm), which transformers cannot represent"
        )
    heads, theta = _dinov3_heads(official, dim, overrides)
    qkv_bias = "attn.qkv.bias" in blocks[0]
    masked = "attn.qkv.bias_mask" in blocks[0]
    fields: dict[str, Any] = {
        "hidden_size": dim,
        "num_hidden_layers": len(blocks),
        "num_attention_heads": heads,
        "patch_size": patch,
        "num_channels": channels,
        "num_register_tokens": int(globals_["storage_tokens"].shape[1]) if "storage_tokens" in globals_ else 0,
        "rope_theta": theta,
        "query_bias": qkv_bias,
        "key_bias": qkv_bias and not masked,
        "value_bias": qkv_bias,
        "proj_bias": "attn.proj.bias" in blocks[0],
        "layer_norm_eps": 1e-5,
        **_dinov3_mlp_fields(blocks[0]),
    }
    return _apply_overrides(transformers.DINOv3ViTConfig, fields, overrides)


def _convert_dinov3_qkv(i: int, block: dict[str, Tensor], prefix: str) -> dict[str, Tensor]:
    out = _split_qkv(_take(block, "attn.qkv.weight", f"DINOv3 (block {i})"), _DINOV3_QKV, prefix, ".weight")
    mask = block.pop("attn.qkv.bias_mask", None)
    bias = block.pop("attn.qkv.bias", None)
    if bias is None:
        if mask is not None:
            raise BackboneError(f"blocks.{i}.attn.qkv has a bias_mask but no bias")
        return out
    split = _split_qkv(bias, _DINOV3_QKV, prefix, ".bias")
    if mask is not None:
        _check_k_bias_mask(mask, f"blocks.{i}.attn.qkv")
        dropped = split.pop(f"{prefix}attention.k_proj.bias")
        logger.debug("blocks.%d: dropped the masked key bias (max |b_k| = %.3g)", i, float(dropped.abs().max()))
    out.update(split)
    return out


def _convert_dinov3_block(i: int, block: Mapping[str, Tensor]) -> dict[str, Tensor]:
    prefix = f"layer.{i}."
    block = dict(block)
    norm1 = _require(block, "norm1.weight", f"DINOv3 (block {i})")
    _ones_layer_scale(block, int(norm1.shape[0]), norm1.dtype)
    out = _convert_dinov3_qkv(i, block, prefix)
    for name in [n for n in block if n in _DINOV3_BLOCK_RENAMES]:
        out[prefix + _DINOV3_BLOCK_RENAMES[name]] = block.pop(name)
    _refuse_leftovers({f"blocks.{i}.{n}": v for n, v in block.items()}, "DINOv3")
    return out


def convert_dinov3_state_dict(official: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """Rename an official DINOv3 ViT state dict into the transformers (Hub) layout.

    Parameters
    ----------
    official : Mapping[str, torch.Tensor]
        Official DINOv3 state dict (release ``.pth``).

    Returns
    -------
    dict[str, torch.Tensor]
        Same tensors (dtypes kept; qkv split; masked key bias, bias masks and RoPE periods
        dropped), keyed as in the ``model.safetensors`` of ``facebook/dinov3-*``; load with
        ``DINOv3ViTModel.from_pretrained(None, config=infer_dinov3_config(official), state_dict=...)``.
    """
    _patch_geometry(official, "DINOv3")
    globals_, blocks = _split_blocks(official, "DINOv3")
    globals_ = dict(globals_)
    cls = _take(globals_, "cls_token", "DINOv3")
    dim = int(cls.shape[-1])
    out: dict[str, Tensor] = {
        "embeddings.cls_token": cls,
        "embeddings.patch_embeddings.weight": _take(globals_, "patch_embed.proj.weight", "DINOv3"),
        "embeddings.register_tokens": globals_.pop("storage_tokens", cls.new_zeros(1, 0, dim)),
        "embeddings.mask_token": globals_.pop("mask_token", cls.new_zeros(1, dim)).reshape(1, 1, dim),
        "norm.weight": _take(globals_, "norm.weight", "DINOv3"),
    }
    renames = {"patch_embed.proj.bias": "embeddings.patch_embeddings.bias", "norm.bias": "norm.bias"}
    out.update({renames[k]: globals_.pop(k) for k in list(globals_) if k in renames})
    for name in ("rope_embed.periods", *_DINOV3_DROPPED_GLOBALS):
        globals_.pop(name, None)
    _refuse_leftovers(globals_, "DINOv3")
    for i, block in enumerate(blocks):
        out.update(_convert_dinov3_block(i, block))
    return out


# ----------------------------------------------------------------------------- both


def convert_official(
    official: Mapping[str, Tensor], kind: str, overrides: Mapping[str, Any] | None = None
) -> tuple[PreTrainedConfig, dict[str, Tensor]]:
    """Config and converted state dict of an official checkpoint of the given kind.

    Parameters
    ----------
    official : Mapping[str, torch.Tensor]
        Official state dict (see `unwrap_official_checkpoint`).
    kind : {"dinov2", "dinov3"}
        Which model family the checkpoint belongs to; a checkpoint of the other family is refused.
    overrides : Mapping[str, Any], optional
        Config fields the shapes cannot give.

    Returns
    -------
    config : transformers.PreTrainedConfig
    state_dict : dict[str, torch.Tensor]
        In the transformers (Hub) layout.
    """
    if kind not in ("dinov2", "dinov3"):
        raise BackboneError(f"kind must be 'dinov2' or 'dinov3', found {kind!r}")
    found = detect_official_kind(official)
    if found is not None and found != kind:
        raise BackboneError(
            f"kind={kind!r} was requested but this official checkpoint is a {found} model "
            f"({'it has a learned pos_embed' if found == 'dinov2' else 'it has RoPE periods / storage tokens'}); pass kind={found!r}"
        )
    if kind == "dinov2":
        return infer_dinov2_config(official, overrides), convert_dinov2_state_dict(official)
    return infer_dinov3_config(official, overrides), convert_dinov3_state_dict(official)
