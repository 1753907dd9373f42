"""DINOv2 / DINOv3 feature extractors on top of Hugging Face `transformers`.

>>> backbone = load_backbone("/models/dinov3-vitb16", kind="dinov3")      # doctest: +SKIP
>>> feats = backbone.pixel_features(images, out_size=(512, 512))          # doctest: +SKIP
>>> feats.shape                                                           # doctest: +SKIP
torch.Size([n_views, 512, 512, 768])

Weights come from (a) a local Hugging Face model folder (``config.json`` + ``*.safetensors``,
as written by ``save_pretrained``), (b) an official Meta checkpoint ``.pth`` converted on load by
`geofeat.backbones.convert`, or (c) a Hub id such as ``"facebook/dinov2-base"`` (only when it is
not an existing path; needs a network, and for DINOv3 an accepted licence, unless it is already in
the Hugging Face cache). ``weights=None`` reads ``GEOFEAT_DINOV2_WEIGHTS`` / ``GEOFEAT_DINOV3_WEIGHTS``.
A converted official checkpoint can be stored as a folder for faster loads later with
``load_backbone(path_pth, kind=...).model.save_pretrained(folder)``.

Features follow the official recipe: ImageNet normalisation, the patch tokens of one block after
the model's final LayerNorm (``forward_features()["x_norm_patchtokens"]`` for the last block,
``get_intermediate_layers(..., norm=True)`` for the others), CLS and register tokens dropped,
bilinear upsampling to the render resolution, L2 normalisation per pixel. The model is always
run in ``eval()`` mode: DINOv3 jitters and rescales its RoPE coordinates in training mode.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.backbones.convert import convert_official, require_transformers, unwrap_official_checkpoint
from geofeat.checks import check_integer
from geofeat.errors import BackboneError
from geofeat.runtime.devices import resolve_device
from geofeat.storage.safe_load import is_unsafe_pickle_error, load_torch_file, unsafe_pickle_message

if TYPE_CHECKING:
    from transformers import PreTrainedModel

logger = logging.getLogger(__name__)

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "KINDS",
    "WEIGHTS_ENV",
    "DinoBackbone",
    "load_backbone",
    "missing_weights_message",
    "grid_sample_patch_features",
    "imagenet_normalized",
    "sample_patch_features",
    "state_dict_digest",
    "upsample_patch_features",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
KINDS = ("dinov2", "dinov3")
WEIGHTS_ENV = {"dinov2": "GEOFEAT_DINOV2_WEIGHTS", "dinov3": "GEOFEAT_DINOV3_WEIGHTS"}

# transformers model_type -> model class, per kind
_MODEL_CLASSES = {
    "dinov2": {"dinov2": "Dinov2Model", "dinov2_with_registers": "Dinov2WithRegistersModel"},
    "dinov3": {"dinov3_vit": "DINOv3ViTModel"},
}
_SOURCES = {
    "dinov2": (
        "the Hugging Face model page https://huggingface.co/facebook/dinov2-base (download the folder, e.g. "
        "`hf download facebook/dinov2-base --local-dir dinov2-base`), or Meta's torch-hub checkpoints listed at "
        "https://github.com/facebookresearch/dinov2 (e.g. https://dl.fbaipublicfiles.com/dinov2/dinov2_vitb14/dinov2_vitb14_pretrain.pth)"
    ),
    "dinov3": (
        "the Hugging Face model page https://huggingface.co/facebook/dinov3-vitb16-pretrain-lvd1689m (gated: accept the "
        "licence on the page, then `hf download facebook/dinov3-vitb16-pretrain-lvd1689m --local-dir dinov3-vitb16`), or "
        "Meta's release checkpoints (e.g. dinov3_vitb16_pretrain_lvd1689m-73cec8be.pth; request access at "
        "https://github.com/facebookresearch/dinov3)"
    ),
}
_HUB_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*/[A-Za-z0-9][A-Za-z0-9_.-]*$")
_FILE_SUFFIXES = (".pth", ".pt", ".bin", ".safetensors", ".json", ".ckpt")
_OFFICIAL_SUFFIXES = (".pth", ".pt")
_RANGE_TOL = 1e-3


# ----------------------------------------------------------------------------- small helpers


def _check_kind(kind: str) -> str:
    if kind not in KINDS:
        raise BackboneError(f"kind must be one of {KINDS}, found {kind!r}")
    return kind


def missing_weights_message(kind: str, reason: str | None = None) -> str:
    """The text of the error raised when no usable weights were given.

    Parameters
    ----------
    kind : {"dinov2", "dinov3"}
    reason : str, optional
        What went wrong (e.g. the Hub error); prepended to the guidance.

    Returns
    -------
    str
        Names the ``weights=`` parameter, the environment variable and where official weights come from.
    """
    name = "DINOv2" if kind == "dinov2" else "DINOv3"
    head = f"{reason}. " if reason else f"No {name} weights were given. "
    return (
        f"{head}Pass `weights=` (a local Hugging Face model folder with config.json and *.safetensors, an official "
        f"Meta checkpoint .pth, or a Hub id when online) or set the environment variable {WEIGHTS_ENV[kind]} to one of "
        f"these. Official {name} weights come from {_SOURCES[kind]}. Set HF_HUB_OFFLINE=1 to skip network attempts."
    )


def state_dict_digest(state_dict: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 over tensor names, dtypes, shapes and raw bytes, in sorted-name order.

    Parameters
    ----------
    state_dict : Mapping[str, torch.Tensor]
        Any state dict (tensors on any device, any dtype including bfloat16).

    Returns
    -------
    str
        64 hexadecimal characters; equal state dicts give equal digests, any changed byte,
        name, shape or dtype gives another.
    """
    digest = hashlib.sha256()
    for name in sorted(state_dict):
        tensor = state_dict[name].detach()
        digest.update(f"{name}\t{str(tensor.dtype).removeprefix('torch.')}\t{tuple(tensor.shape)}\n".encode())
        flat = tensor.to("cpu").contiguous().reshape(-1)
        digest.update(flat.view(torch.uint8).numpy().tobytes() if flat.numel() else b"")
    return digest.hexdigest()


def imagenet_normalized(images: torch.Tensor) -> torch.Tensor:
    """Images as DINO sees them: channels first, ImageNet mean and standard deviation removed.

    Parameters
    ----------
    images : torch.Tensor, shape (N, H, W, 3), float in [0, 1]

    Returns
    -------
    torch.Tensor, shape (N, 3, H, W), the dtype and device of ``images``
    """
    pixels = images.permute(0, 3, 1, 2)
    mean = torch.tensor(IMAGENET_MEAN, dtype=pixels.dtype, device=pixels.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=pixels.dtype, device=pixels.device).view(1, 3, 1, 1)
    return (pixels - mean) / std


def upsample_patch_features(grid: torch.Tensor, out_size: tuple[int, int]) -> torch.Tensor:
    """Bilinearly upsample a patch grid and L2-normalise every pixel (differentiable).

    Parameters
    ----------
    grid : torch.Tensor
        (N, h, w, C) patch features, float.
    out_size : tuple of int
        (H_out, W_out).

    Returns
    -------
    torch.Tensor
        (N, H_out, W_out, C) float32, unit L2 norm along C (zero vectors stay zero). Sampling uses
        ``align_corners=False``: the centre of patch (i, j) lands at pixel ((i + 0.5) p, (j + 0.5) p).
    """
    chw = grid.float().permute(0, 3, 1, 2)
    up = F.interpolate(chw, size=tuple(out_size), mode="bilinear", align_corners=False)
    return F.normalize(up, dim=1).permute(0, 2, 3, 1)


def sample_patch_features(grid: torch.Tensor, pixels: torch.Tensor, out_size: tuple[int, int]) -> torch.Tensor:
    """`upsample_patch_features` at chosen pixels only: bilinear samples, L2-normalised (differentiable).

    Equal to ``upsample_patch_features(grid, out_size)[pixels[:, 0], pixels[:, 1], pixels[:, 2]]``
    without forming the (N, H_out, W_out, C) tensor, so training at 512 x 512 keeps only the
    foreground pixels' features in memory.

    Parameters
    ----------
    grid : torch.Tensor, shape (N, h, w, C)
        Patch features.
    pixels : torch.Tensor, shape (M, 3), int64
        (view, row, column) of each wanted pixel of the (H_out, W_out) images.
    out_size : (int, int)
        (H_out, W_out).

    Returns
    -------
    torch.Tensor, shape (M, C), float32, unit L2 norm per row (zero rows stay zero)
    """
    grid = grid.float()
    _, h, w, _ = grid.shape
    pixels = pixels.to(grid.device)
    view = pixels[:, 0]
    y0, y1, wy = _source_taps(pixels[:, 1], h, out_size[0])
    x0, x1, wx = _source_taps(pixels[:, 2], w, out_size[1])
    flat = grid.reshape(-1, grid.shape[-1])  # (N h w, C)

    # index_select, not grid[view, y, x]: the backward of advanced indexing (index_put with
    # accumulate) adds in an order that changes from run to run with several CPU threads, which
    # made training steps irreproducible; index_select's backward does not.
    def tap(y: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        return flat.index_select(0, (view * h + y) * w + x)

    top = tap(y0, x0) * (1 - wx)[:, None] + tap(y0, x1) * wx[:, None]
    bottom = tap(y1, x0) * (1 - wx)[:, None] + tap(y1, x1) * wx[:, None]
    return F.normalize(top * (1 - wy)[:, None] + bottom * wy[:, None], dim=1)


def grid_sample_patch_features(
    grid: torch.Tensor, pixels: torch.Tensor, out_size: tuple[int, int], dtype: torch.dtype = torch.float16
) -> torch.Tensor:
    """Patch features at chosen pixels as GeoLoRA and Diff3f sample them: corner-aligned grid, `grid_sample`, L2-normalised.

    Pixel ``(row, col)`` of an ``H x W`` image samples the patch grid at the normalised
    position ``x = linspace(-1, 1, W)[col]``, ``y = linspace(-1, 1, H)[row]`` (so the first and
    last pixels sit on the outer edges of the grid) with ``grid_sample(align_corners=False)``,
    zero padding, in ``dtype`` (the official code casts the tokens and the grid to float16).
    That maps pixel ``col`` to patch position ``col * w / (W - 1) - 0.5``, not to
    ``(col + 0.5) * w / W - 0.5`` as `sample_patch_features` does. Each output pixel is
    computed on its own, so sampling only the foreground pixels gives the values that the
    whole image would.

    Parameters
    ----------
    grid : torch.Tensor, shape (N, h, w, C)
        Patch features.
    pixels : torch.Tensor, shape (M, 3), int64
        (view, row, column) of each wanted pixel, in flat order.
    out_size : (int, int)
        (H, W) of the rendered images.
    dtype : torch.dtype
        Precision of the tokens, the grid and the result.

    Returns
    -------
    torch.Tensor, shape (M, C), ``dtype``, unit L2 norm per row
    """
    height, width = out_size
    pixels = pixels.to(grid.device)
    xs = torch.linspace(-1.0, 1.0, width, device=grid.device)
    ys = torch.linspace(-1.0, 1.0, height, device=grid.device)
    # contiguous: float16 grid_sample on the CPU returns wrong values (NaN among them) for a permuted
    # (channels-last) input of many channels (torch 2.13; seen with 768 channels, not with 16).
    chw = grid.to(dtype).permute(0, 3, 1, 2).contiguous()
    rows = []
    for view in range(grid.shape[0]):
        mine = pixels[:, 0] == view
        where = torch.stack((xs[pixels[mine, 2]], ys[pixels[mine, 1]]), dim=-1).to(dtype)  # (M_v, 2) as (x, y)
        sampled = F.grid_sample(chw[view : view + 1], where[None, None], align_corners=False)  # (1, C, 1, M_v)
        rows.append(F.normalize(sampled, dim=1)[0, :, 0].T)
    return torch.cat(rows) if rows else chw.new_zeros((0, grid.shape[-1]))


def _source_taps(index: torch.Tensor, n_in: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear taps of ``F.interpolate(align_corners=False)``: lower index, upper index, upper weight."""
    source = ((index.double() + 0.5) * (n_in / n_out) - 0.5).clamp(min=0.0)
    lower = source.floor().long().clamp(max=n_in - 1)
    upper = (lower + 1).clamp(max=n_in - 1)
    return lower, upper, (source - lower).float()


def _check_out_size(out_size: Sequence[int]) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in out_size)
        ok = all(int(v) == v for v in out_size)
    except (TypeError, ValueError):
        ok = False
    if not ok or h < 1 or w < 1:
        raise BackboneError(f"out_size must be two positive integers (H, W), found {out_size!r}")
    return h, w


# ----------------------------------------------------------------------------- the backbone


class DinoBackbone:
    """A frozen-by-default DINOv2 / DINOv3 transformers model with the feature recipe around it.

    Parameters
    ----------
    model : transformers.PreTrainedModel
        A ``Dinov2Model``, ``Dinov2WithRegistersModel`` or ``DINOv3ViTModel``; it is put in
        ``eval()`` mode and kept there for every feature call.
    kind : {"dinov2", "dinov3"}
    layer : int
        Block whose output is used, Python-style: -1 (default) is the last block, 0 the first.
        Every block's tokens go through the model's final LayerNorm, as the official
        ``get_intermediate_layers(norm=True)`` does.
    source : str, optional
        Where the weights came from (for messages).

    Attributes
    ----------
    model : transformers.PreTrainedModel
        The underlying module; wrap it with peft for LoRA (see `attention_projections`).
    patch_size, embed_dim, num_layers, num_prefix_tokens : int
        Patch side in pixels, channels C, number of blocks, CLS + register tokens.
    weights_digest : str
        SHA-256 of the weights as loaded (see `state_dict_digest`), computed once here.
    rope_augmentation : bool
        DINOv3 only: run the model in ``train()`` mode, in which it rescales its RoPE
        coordinates by a random factor at every forward pass (log-uniform in [1/2, 2] for the
        released ViT-B/16; torch's random generator draws it), as the official GeoLoRA training
        does. False (default): ``eval()`` mode, the same features on every call.
    """

    def __init__(self, model: PreTrainedModel, *, kind: str, layer: int = -1, source: str | None = None) -> None:
        self.kind = _check_kind(kind)
        self.model = model
        self.model.eval()
        self._rope_augmentation = False
        config = model.config
        patch = config.patch_size
        patch_hw = tuple(patch) if isinstance(patch, (list, tuple)) else (patch, patch)
        if patch_hw[0] != patch_hw[1]:
            raise BackboneError(f"only square patches are supported, found patch_size={patch!r}")
        self.patch_size = int(patch_hw[0])
        self.embed_dim = int(config.hidden_size)
        self.num_layers = int(config.num_hidden_layers)
        self.num_prefix_tokens = 1 + int(getattr(config, "num_register_tokens", 0) or 0)
        self.layer = layer
        self.source = source
        self._weights_digest = state_dict_digest(model.state_dict())

    # -- properties

    @property
    def weights_digest(self) -> str:
        """SHA-256 (hex) of the weights as loaded; part of feature cache keys."""
        return self._weights_digest

    @property
    def layer(self) -> int:
        """Block index as given (-1 = last)."""
        return self._layer

    @layer.setter
    def layer(self, value: int) -> None:
        n = self.num_layers
        expected = f"an integer block index in [{-n}, {n - 1}] for this {n}-block model"
        self._layer = check_integer(value, "layer", low=-n, high=n - 1, error=BackboneError, expected=expected)

    @property
    def rope_augmentation(self) -> bool:
        """Run DINOv3 in ``train()`` mode (random RoPE rescaling at every forward); see the class notes."""
        return self._rope_augmentation

    @rope_augmentation.setter
    def rope_augmentation(self, value: bool) -> None:
        if value and self.kind != "dinov3":
            raise BackboneError(f"RoPE augmentation is a DINOv3 training mode; this backbone is {self.kind}")
        self._rope_augmentation = bool(value)

    @property
    def device(self) -> torch.device:
        """Device of the model parameters."""
        return next(self.model.parameters()).device

    @property
    def attention_projections(self) -> tuple[str, str, str]:
        """Leaf names of the query/key/value projection modules, for ``peft.LoraConfig(target_modules=...)``.

        ``("q_proj", "k_proj", "v_proj")`` with transformers 5.x for both DINOv2 and DINOv3
        (DINOv2 releases that still use ``attention.attention.query/key/value`` give
        ``("query", "key", "value")``).
        """
        leaves = {name.rsplit(".", 1)[-1] for name, _ in self.model.named_modules()}
        for triple in (("q_proj", "k_proj", "v_proj"), ("query", "key", "value")):
            if set(triple) <= leaves:
                return triple
        raise BackboneError(f"no query/key/value projection modules found in {type(self.model).__name__}")

    def __repr__(self) -> str:
        return (
            f"DinoBackbone(kind={self.kind!r}, layer={self.layer}, patch_size={self.patch_size}, embed_dim={self.embed_dim}, "
            f"num_layers={self.num_layers}, device={self.device}, digest={self.weights_digest[:12]}...)"
        )

    # -- features

    def _pixels(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Validate (N, H, W, 3) images in [0, 1] and return ImageNet-normalised (N, 3, H, W) float32 on the model device."""
        images = torch.as_tensor(images)
        if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] < 1:
            raise BackboneError(
                f"images must have shape (N, H, W, 3) (RGB, N >= 1; add a batch axis with images[None]), found {tuple(images.shape)}"
            )
        if not images.is_floating_point():
            raise BackboneError(
                f"images must be floating point in [0, 1], found dtype {images.dtype}; for 8-bit images divide by 255"
            )
        height, width = int(images.shape[1]), int(images.shape[2])
        if height % self.patch_size or width % self.patch_size:
            raise BackboneError(
                f"image size {height}x{width} is not a multiple of the {self.kind} patch size {self.patch_size}; render at a "
                f"multiple (e.g. {max(1, round(height / self.patch_size)) * self.patch_size}x"
                f"{max(1, round(width / self.patch_size)) * self.patch_size}) or resize first (geofeat never crops silently)"
            )
        with torch.no_grad():
            lo, hi = (float(v) for v in torch.stack(torch.aminmax(images)).cpu())  # one wait on the device, not two
        if lo < -_RANGE_TOL or hi > 1 + _RANGE_TOL:
            raise BackboneError(
                f"image values must lie in [0, 1], found range [{lo:.4g}, {hi:.4g}]; for 0-255 images divide by 255"
            )
        return imagenet_normalized(images.to(self.device, torch.float32))

    def _final_norm(self) -> torch.nn.Module:
        norm = getattr(self.model, "layernorm", None)  # DINOv2
        return norm if norm is not None else self.model.norm  # DINOv3

    def _layer_tokens(self, pixels: torch.Tensor) -> torch.Tensor:
        """All tokens (N, prefix + h*w, C) of the chosen block after the final LayerNorm."""
        block = self.layer % self.num_layers
        if block == self.num_layers - 1:
            return self.model(pixel_values=pixels).last_hidden_state
        hidden = self.model(pixel_values=pixels, output_hidden_states=True).hidden_states
        return self._final_norm()(hidden[block + 1])  # hidden[0] is the embedding output

    def patch_features(self, images: torch.Tensor | np.ndarray) -> torch.Tensor:
        """Patch tokens of the chosen block on the patch grid (differentiable, no upsampling).

        Parameters
        ----------
        images : torch.Tensor or numpy.ndarray
            (N, H, W, 3) RGB, float in [0, 1]; H and W multiples of `patch_size`.

        Returns
        -------
        torch.Tensor
            (N, H / patch_size, W / patch_size, C) float32 on the model device, not normalised.
            Gradients flow when enabled (LoRA training); the model is set to ``eval()`` first
            (``train()`` with `rope_augmentation`).
        """
        pixels = self._pixels(images)
        self.model.train(self.rope_augmentation)
        tokens = self._layer_tokens(pixels)[:, self.num_prefix_tokens :, :]
        n, _, height, width = pixels.shape
        return tokens.reshape(n, height // self.patch_size, width // self.patch_size, self.embed_dim).float()

    def pixel_features(
        self, images: torch.Tensor | np.ndarray, out_size: Sequence[int] | None = None, *, batch_size: int = 8
    ) -> torch.Tensor:
        """Per-pixel features: patch tokens upsampled to ``out_size`` and L2-normalised per pixel.

        Parameters
        ----------
        images : torch.Tensor or numpy.ndarray
            (N, H, W, 3) RGB, float in [0, 1]; H and W multiples of `patch_size` (an error
            otherwise; nothing is cropped).
        out_size : (int, int), optional
            (H_out, W_out); default (H, W).
        batch_size : int
            Images per forward pass; bounds peak memory.

        Returns
        -------
        torch.Tensor
            (N, H_out, W_out, C) float32 with unit L2 norm per pixel, on the device of ``images``
            (CPU for numpy input). Computed under ``torch.no_grad()`` in ``eval()`` mode.
        """
        images = torch.as_tensor(images)
        check_integer(batch_size, "batch_size", low=1, error=BackboneError, expected="a positive integer")
        if images.ndim != 4:
            self._pixels(images)  # raises the shape error
        size = _check_out_size(out_size if out_size is not None else images.shape[1:3])
        out = torch.empty((images.shape[0], *size, self.embed_dim), dtype=torch.float32, device=images.device)
        with torch.no_grad():
            for start in range(0, images.shape[0], int(batch_size)):
                grid = self.patch_features(images[start : start + int(batch_size)])
                out[start : start + grid.shape[0]] = upsample_patch_features(grid, size).to(out.device)
        return out


# ----------------------------------------------------------------------------- loading


#: The transformers attention implementation the loaders ask for: PyTorch's fused
#: ``scaled_dot_product_attention``, which runs FlashAttention kernels on CUDA in bfloat16
#: (``"flash_attention_2"`` would need the separate flash-attn package and is no faster here).
ATTENTION = "sdpa"


def _model_class(kind: str, model_type: str) -> type:
    transformers = require_transformers()
    classes = _MODEL_CLASSES[kind]
    if model_type not in classes:
        other = next((k for k, v in _MODEL_CLASSES.items() if model_type in v), None)
        hint = f"; pass kind={other!r}" if other else ""
        raise BackboneError(
            f"kind={kind!r} expects a model of type {sorted(classes)}, but the weights are of type {model_type!r}{hint}"
        )
    return getattr(transformers, classes[model_type])


def _check_loading_info(info: Mapping[str, Any], source: str, *, strict: bool) -> None:
    missing, mismatched = sorted(info.get("missing_keys", ())), sorted(map(str, info.get("mismatched_keys", ())))
    unexpected = sorted(info.get("unexpected_keys", ()))
    if missing or mismatched or (strict and unexpected):
        raise BackboneError(
            f"the weights from {source} do not fit the model: missing {missing[:8]}, wrong shape {mismatched[:8]}, "
            f"unexpected {unexpected[:8]}; the file is truncated, of another architecture, or its config.json disagrees"
        )
    if unexpected:
        logger.warning("ignored %d tensors from %s that the model does not use: %s", len(unexpected), source, unexpected[:8])


def _from_pretrained(kind: str, name_or_path: str, source: str) -> PreTrainedModel:
    """Load a Hugging Face folder or Hub id after checking that its model type matches ``kind``."""
    transformers = require_transformers()
    try:
        config = transformers.AutoConfig.from_pretrained(name_or_path)
    except (OSError, ValueError) as exc:
        if Path(name_or_path).is_dir():
            raise BackboneError(
                f"{source} is not a Hugging Face model folder ({exc}); expected config.json and model.safetensors "
                "as written by save_pretrained"
            ) from exc
        reason = " ".join(str(exc).split())
        raise BackboneError(
            missing_weights_message(kind, f"Could not load {source!r} from the Hugging Face Hub ({reason})")
        ) from exc
    cls = _model_class(kind, config.model_type)
    try:
        model, info = cls.from_pretrained(
            name_or_path, config=config, dtype=torch.float32, attn_implementation=ATTENTION, output_loading_info=True
        )
    except (OSError, ValueError, RuntimeError) as exc:
        raise BackboneError(f"could not load the {kind} weights from {source}: {exc}") from exc
    except Exception as exc:  # safetensors' SafetensorError and pickle's UnpicklingError derive from Exception only
        if is_unsafe_pickle_error(exc):
            raise BackboneError(unsafe_pickle_message(_weights_file(name_or_path, "pytorch_model*.bin"), exc)) from exc
        if type(exc).__name__ == "SafetensorError":
            raise BackboneError(
                f"could not read the {kind} weights {_weights_file(name_or_path, '*.safetensors')} "
                f"({' '.join(str(exc).split())}): the file is truncated or damaged (an interrupted download or copy). "
                "Download or save it again (model.save_pretrained(folder))."
            ) from exc
        raise
    _check_loading_info(info, source, strict=False)
    return model


def _weights_file(name_or_path: str, pattern: str) -> str:
    """The weights file of a local model folder matching ``pattern`` (for messages), else the folder or Hub id."""
    folder = Path(name_or_path)
    found = sorted(folder.glob(pattern)) if folder.is_dir() else []
    return str(found[0]) if len(found) == 1 else f"the {pattern} file(s) of {name_or_path}"


def _from_official(kind: str, path: Path, overrides: Mapping[str, Any] | None) -> PreTrainedModel:
    """Load an official Meta ``.pth``, convert it and build the transformers model."""
    raw = load_torch_file(path, BackboneError, what="an official DINO checkpoint")
    config, state_dict = convert_official(unwrap_official_checkpoint(raw), kind, overrides)
    cls = _model_class(kind, config.model_type)
    model, info = cls.from_pretrained(
        None, config=config, state_dict=state_dict, dtype=torch.float32, attn_implementation=ATTENTION, output_loading_info=True
    )
    _check_loading_info(info, str(path), strict=True)
    return model


def _resolve_weights(weights: str | os.PathLike | None, kind: str) -> str:
    if weights is None:
        weights = os.environ.get(WEIGHTS_ENV[kind], "").strip() or None
        if weights is None:
            raise BackboneError(missing_weights_message(kind))
        logger.info("using %s weights from $%s=%s", kind, WEIGHTS_ENV[kind], weights)
    if not isinstance(weights, (str, os.PathLike)):
        raise BackboneError(f"weights must be a path, a Hub id or None, found {type(weights).__name__}")
    return os.fspath(weights)


def _load_model(kind: str, source: str, overrides: Mapping[str, Any] | None) -> PreTrainedModel:
    path = Path(source).expanduser()
    if path.is_file() and path.suffix.lower() in _OFFICIAL_SUFFIXES:
        return _from_official(kind, path, overrides)
    if overrides:
        raise BackboneError(
            "config_overrides apply only to official .pth checkpoints; a Hugging Face model carries its own config.json"
        )
    if path.is_dir():
        return _from_pretrained(kind, str(path), source)
    if path.is_file():
        raise BackboneError(
            f"{source} is a {path.suffix or 'suffix-less'} file; expected an official checkpoint (.pth/.pt) or a Hugging Face "
            "model folder (pass the folder holding config.json and the .safetensors, not a file in it)"
        )
    if _HUB_ID.match(source) and not source.lower().endswith(_FILE_SUFFIXES):
        return _from_pretrained(kind, source, source)
    raise BackboneError(missing_weights_message(kind, f"The weights path {source!r} does not exist"))


def load_backbone(
    weights: str | os.PathLike | None = None,
    kind: str = "dinov2",
    layer: int = -1,
    device: str | torch.device | None = "auto",
    *,
    config_overrides: Mapping[str, Any] | None = None,
) -> DinoBackbone:
    """Load a DINOv2 (patch 14) or DINOv3 (patch 16) backbone for feature extraction.

    Parameters
    ----------
    weights : str or os.PathLike, optional
        A local Hugging Face model folder, an official Meta ``.pth`` (converted exactly, see
        `geofeat.backbones.convert`), or a Hub id such as ``"facebook/dinov2-base"`` (tried only
        when no such path exists). None reads ``GEOFEAT_DINOV2_WEIGHTS`` / ``GEOFEAT_DINOV3_WEIGHTS``.
    kind : {"dinov2", "dinov3"}
        Model family; weights of the other family are refused.
    layer : int
        Block whose (final-LayerNorm-normalised) patch tokens are used; -1 is the last.
    device : str or torch.device
        ``"auto"`` = CUDA when present, else CPU.
    config_overrides : Mapping[str, Any], optional
        For official ``.pth`` files only: transformers config fields the state dict cannot give
        (e.g. ``{"num_attention_heads": 6}`` for a DINOv2 without 64-dim heads).

    Returns
    -------
    DinoBackbone
        Float32 model in ``eval()`` mode on ``device``.

    Raises
    ------
    BackboneError
        No weights (the message names ``weights=``, the environment variable and the official
        sources), unreadable or mismatched weights, a bad ``layer`` or ``device``.
    MissingDependencyError
        `transformers` is not installed (``pip install 'geofeat[dino]'``).
    """
    kind = _check_kind(kind)
    target = resolve_device(device)
    source = _resolve_weights(weights, kind)
    model = _load_model(kind, source, config_overrides).float()
    backbone = DinoBackbone(model, kind=kind, layer=layer, source=source)
    backbone.model.to(target)
    logger.info("loaded %s from %s (digest %s) on %s", kind, source, backbone.weights_digest[:12], target)
    return backbone
