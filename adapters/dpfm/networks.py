"""DPFM's trainable network: DiffusionNet features, cross-attention refinement, overlap prediction.

`DPFMNet` runs the feature extractor (`geofeat.adapters.blocks.diffusion_net.DiffusionNet`) on both
shapes, refines the features by cross-attention between their farthest-point samples
(`CrossAttentionRefiner`, interpolated back with `geofeat.adapters.dpfm.sampling.SampleInterpolation`),
predicts the overlap of every vertex, and solves the regularised functional map
(`geofeat.adapters.blocks.fmap_layers.regularized_fmap`). The head around it is
`geofeat.adapters.dpfm.DPFMHead`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from geofeat.adapters.blocks.diffusion_net import DiffusionNet
from geofeat.adapters.blocks.fmap_layers import regularized_fmap
from geofeat.adapters.blocks.operators import SurfaceOperators
from geofeat.adapters.dpfm.config import DPFMConfig
from geofeat.adapters.dpfm.sampling import SampleInterpolation

__all__ = ["INSTANCE_NORM_EPS", "CrossAttentionRefiner", "DPFMNet", "DPFMOutput"]

#: Variance floor of the instance normalisation in the message MLPs (torch's InstanceNorm1d default).
INSTANCE_NORM_EPS = 1e-5


def _instance_norm(h: torch.Tensor) -> torch.Tensor:
    """Normalise every channel of (N, C) over the N points (no affine part)."""
    mean = h.mean(dim=0, keepdim=True)
    var = h.var(dim=0, unbiased=False, keepdim=True)
    return (h - mean) / torch.sqrt(var + INSTANCE_NORM_EPS)


class _MultiHeadAttention(nn.Module):
    """Scaled dot-product attention of queries (N, d) over keys and values (M, d), ``n_heads`` heads."""

    def __init__(self, dim: int, n_heads: int, layout: str = "contiguous") -> None:
        super().__init__()
        self.n_heads, self.head_dim, self.layout = n_heads, dim // n_heads, layout
        self.query, self.key, self.value, self.merge = (nn.Linear(dim, dim) for _ in range(4))

    def _split(self, t: torch.Tensor) -> torch.Tensor:
        """(N, d) -> (h, N, d/h) in the channel layout of the heads."""
        if self.layout == "interleaved":  # channel c = i * h + head
            return t.reshape(t.shape[0], self.head_dim, self.n_heads).permute(2, 0, 1)
        return t.reshape(t.shape[0], self.n_heads, self.head_dim).transpose(0, 1)

    def _merge(self, t: torch.Tensor) -> torch.Tensor:
        """(h, N, d/h) -> (N, d), the inverse of `_split`."""
        if self.layout == "interleaved":
            return t.permute(1, 2, 0).reshape(t.shape[1], -1)
        return t.transpose(0, 1).reshape(t.shape[1], -1)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        q, k, v = self._split(self.query(x)), self._split(self.key(source)), self._split(self.value(source))
        scores = q @ k.transpose(1, 2) / math.sqrt(self.head_dim)  # (h, N, M)
        out = torch.softmax(scores, dim=-1) @ v  # (h, N, d/h)
        return self.merge(self._merge(out))


class _AttentionalPropagation(nn.Module):
    """The update of ``x`` from ``source``: an MLP of ``[x, attention(x, source)]`` (add it to ``x``)."""

    def __init__(self, dim: int, n_heads: int, layout: str = "contiguous") -> None:
        super().__init__()
        self.attention = _MultiHeadAttention(dim, n_heads, layout)
        self.hidden = nn.Linear(2 * dim, 2 * dim)
        self.out = nn.Linear(2 * dim, dim)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        h = torch.cat([x, self.attention(x, source)], dim=-1)
        return self.out(torch.relu(_instance_norm(self.hidden(h))))


class CrossAttentionRefiner(nn.Module):
    """Cross-attention between the farthest-point samples of two shapes, interpolated back to every vertex.

    Parameters
    ----------
    width : int
        Channels of the features in and out.
    attention_dim : int
        Channels inside.
    n_heads : int
        Attention heads (divides ``attention_dim``).
    n_layers : int
        Rounds of cross-attention (one `_AttentionalPropagation` each, shared by both directions).
    head_layout : {"contiguous", "interleaved"}
        Channels of each attention head (see `DPFMConfig`).
    """

    def __init__(self, width: int, attention_dim: int, n_heads: int, n_layers: int, head_layout: str = "contiguous") -> None:
        super().__init__()
        self.first = nn.Linear(width, attention_dim)
        self.layers = nn.ModuleList(_AttentionalPropagation(attention_dim, n_heads, head_layout) for _ in range(n_layers))
        self.last = nn.Linear(attention_dim, width)

    def forward(
        self, feat_x: torch.Tensor, feat_y: torch.Tensor, interp_x: SampleInterpolation, interp_y: SampleInterpolation
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Refine (V_x, width) and (V_y, width) features; returns the same shapes."""
        hx, hy = self.first(feat_x), self.first(feat_y)
        all_x = len(interp_x.samples) == hx.shape[0]
        all_y = len(interp_y.samples) == hy.shape[0]
        for layer in self.layers:
            sx = hx if all_x else hx[interp_x.samples]
            sy = hy if all_y else hy[interp_y.samples]
            sx = sx + layer(sx, sy)
            sy = sy + layer(sy, sx)
            hx = sx if all_x else interp_x.interpolate(sx)
            hy = sy if all_y else interp_y.interpolate(sy)
        return self.last(hx), self.last(hy)


class _OverlapPredictor(nn.Module):
    """Overlap logit of every vertex from its L2-normalised features."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, 1))

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return self.net(F.normalize(feat, p=2, dim=-1)).squeeze(-1)


class DPFMOutput(NamedTuple):
    """What `DPFMNet` predicts for a pair.

    Attributes
    ----------
    fmap : torch.Tensor, shape (n_fmap, n_fmap)
        ``C`` (k_y, k_x): ``coeffs_y = C @ coeffs_x``.
    overlap_logits_x : torch.Tensor, shape (V_x,)
    overlap_logits_y : torch.Tensor, shape (V_y,)
        Logits of the overlap probabilities (``sigmoid`` gives them).
    feat_x : torch.Tensor, shape (V_x, width)
    feat_y : torch.Tensor, shape (V_y, width)
        The features the functional map was computed from.
    """

    fmap: torch.Tensor
    overlap_logits_x: torch.Tensor
    overlap_logits_y: torch.Tensor
    feat_x: torch.Tensor
    feat_y: torch.Tensor


class DPFMNet(nn.Module):
    """DiffusionNet feature extractor, cross-attention refiner and overlap predictor (the trainable part of DPFM).

    Parameters
    ----------
    in_channels : int
        Input feature channels.
    config : DPFMConfig
        Sizes and functional-map settings.
    """

    def __init__(self, in_channels: int, config: DPFMConfig) -> None:
        super().__init__()
        c = config
        self.config = c
        self.extractor = DiffusionNet(in_channels, c.width, width=c.width, n_blocks=c.n_blocks, dropout=c.dropout)
        self.refiner = CrossAttentionRefiner(c.width, c.attention_dim, c.n_heads, c.n_attention_layers, c.head_layout)
        self.overlap = _OverlapPredictor(c.width)

    def forward(
        self,
        input_x: torch.Tensor,
        input_y: torch.Tensor,
        ops_x: SurfaceOperators,
        ops_y: SurfaceOperators,
        interp_x: SampleInterpolation,
        interp_y: SampleInterpolation,
    ) -> DPFMOutput:
        """Predict the functional map and overlaps of ``y`` to ``x`` from input features (V, C_in)."""
        c = self.config
        ext_x, ext_y = self.extractor(input_x, ops_x), self.extractor(input_y, ops_y)
        ref_x, ref_y = self.refiner(ext_x, ext_y, interp_x, interp_y)
        logits_x, logits_y = self.overlap(ref_x), self.overlap(ref_y)
        use_x, use_y = (ref_x, ref_y) if c.fmap_features == "refined" else (ext_x, ext_y)
        fx, fy = use_x, use_y
        if c.overlap_weighted_fmap:
            fx, fy = fx * torch.sigmoid(logits_x).unsqueeze(-1), fy * torch.sigmoid(logits_y).unsqueeze(-1)
        k = c.n_fmap
        fmap = regularized_fmap(
            fx,
            fy,
            ops_x.evecs[:, :k],
            ops_y.evecs[:, :k],
            ops_x.mass,
            ops_y.mass,
            ops_x.evals[:k],
            ops_y.evals[:k],
            lambda_=c.lambda_,
            gamma=c.gamma,
        )
        return DPFMOutput(fmap, logits_x, logits_y, use_x, use_y)
