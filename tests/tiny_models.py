"""Tiny randomly initialised transformers backbones, in place of real DINO weights."""

from __future__ import annotations

import torch


def randomized(model, seed: int = 1, scale: float = 0.2):
    """Fill every parameter with N(0, scale^2) noise (seeded) and return the model in eval mode."""
    torch.manual_seed(seed)
    with torch.no_grad():
        for param in model.parameters():
            param.copy_(torch.randn_like(param) * scale)
    return model.eval()


def tiny_dinov3(hidden: int = 32, layers: int = 2, heads: int = 2, registers: int = 2, seed: int = 1):
    """A DINOv3 ViT (patch 16) with random weights."""
    from transformers import DINOv3ViTConfig, DINOv3ViTModel

    torch.manual_seed(0)
    config = DINOv3ViTConfig(
        hidden_size=hidden,
        intermediate_size=2 * hidden,
        num_hidden_layers=layers,
        num_attention_heads=heads,
        patch_size=16,
        image_size=32,
        num_register_tokens=registers,
    )
    return randomized(DINOv3ViTModel(config), seed)


def tiny_dinov2(hidden: int = 32, layers: int = 2, heads: int = 2, seed: int = 1):
    """A DINOv2 ViT (patch 14) with random weights."""
    from transformers import Dinov2Config, Dinov2Model

    torch.manual_seed(0)
    config = Dinov2Config(
        hidden_size=hidden, num_hidden_layers=layers, num_attention_heads=heads, mlp_ratio=2, patch_size=14, image_size=28
    )
    return randomized(Dinov2Model(config), seed)
