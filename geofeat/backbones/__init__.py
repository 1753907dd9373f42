"""DINOv2 / DINOv3 backbones through Hugging Face `transformers` (the optional ``dino`` extra).

`load_backbone` gives a `DinoBackbone` from a Hugging Face model folder, an official Meta
``.pth`` (converted by `geofeat.backbones.convert`) or a Hub id; `DinoBackbone.pixel_features`
turns (N, H, W, 3) renders into per-pixel, L2-normalised features. Importing this package does
not import `transformers`; using it without `transformers` raises `MissingDependencyError`.
"""

from geofeat.backbones.convert import (
    convert_dinov2_state_dict,
    convert_dinov3_state_dict,
    convert_official,
    detect_official_kind,
    infer_dinov2_config,
    infer_dinov3_config,
    unwrap_official_checkpoint,
)
from geofeat.backbones.dino import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    KINDS,
    WEIGHTS_ENV,
    DinoBackbone,
    load_backbone,
    missing_weights_message,
    sample_patch_features,
    state_dict_digest,
    upsample_patch_features,
)
from geofeat.backbones.lora import (
    LORA_KIND,
    OFFICIAL_ALPHA,
    LoraSettings,
    add_lora,
    convert_official_lora,
    has_lora,
    load_lora,
    load_official_lora,
    loaded_lora_digest,
    lora_digest,
    lora_state_dict,
    official_lora_state_dict,
    save_lora,
    save_official_lora,
)

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "KINDS",
    "LORA_KIND",
    "OFFICIAL_ALPHA",
    "WEIGHTS_ENV",
    "DinoBackbone",
    "LoraSettings",
    "add_lora",
    "convert_dinov2_state_dict",
    "convert_dinov3_state_dict",
    "convert_official",
    "convert_official_lora",
    "detect_official_kind",
    "has_lora",
    "infer_dinov2_config",
    "infer_dinov3_config",
    "load_backbone",
    "load_lora",
    "load_official_lora",
    "loaded_lora_digest",
    "lora_digest",
    "lora_state_dict",
    "missing_weights_message",
    "official_lora_state_dict",
    "sample_patch_features",
    "save_lora",
    "save_official_lora",
    "state_dict_digest",
    "unwrap_official_checkpoint",
    "upsample_patch_features",
]
