"""EchoMatch's network: the feature DiffusionNet, the learned temperature and the overlap DiffusionNet."""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from geofeat.adapters.blocks.diffusion_net import DiffusionNet
from geofeat.adapters.blocks.operators import SurfaceOperators
from geofeat.adapters.echomatch.config import MIN_TEMPERATURE, EchoMatchConfig
from geofeat.adapters.echomatch.reflection import reflection_features, sampled_reflection


class EchoMatchOutput(NamedTuple):
    """What `EchoMatchNet` computes for a pair.

    Attributes
    ----------
    feat_x : torch.Tensor, shape (V_x, p)
    feat_y : torch.Tensor, shape (V_y, p)
        Raw (unnormalised) features.
    p_xy : torch.Tensor, shape (V_x, V_y)
    p_yx : torch.Tensor, shape (V_y, V_x)
        Soft point maps (rows sum to one).
    overlap_logits_x : torch.Tensor, shape (V_x,)
    overlap_logits_y : torch.Tensor, shape (V_y,)
        Logits of the overlap probabilities.
    """

    feat_x: torch.Tensor
    feat_y: torch.Tensor
    p_xy: torch.Tensor
    p_yx: torch.Tensor
    overlap_logits_x: torch.Tensor
    overlap_logits_y: torch.Tensor


class EchoMatchNet(nn.Module):
    """Feature DiffusionNet, learned temperature and overlap DiffusionNet of EchoMatch.

    Parameters
    ----------
    in_channels : int
        Input features per vertex.
    config : EchoMatchConfig
        Sizes (``feature_channels``, ``width``, ``n_blocks``, ``dropout``,
        ``temperature_init``, ``n_neighbours``, ``overlap_width``, ``overlap_blocks``).
    """

    def __init__(self, in_channels: int, config: EchoMatchConfig) -> None:
        super().__init__()
        self.n_neighbours = int(config.n_neighbours)
        self.features = DiffusionNet(
            in_channels, config.feature_channels, width=config.width, n_blocks=config.n_blocks, dropout=float(config.dropout)
        )
        self.learn_log_temperature = bool(config.learn_log_temperature)
        initial = torch.tensor([float(config.temperature_init)])
        if self.learn_log_temperature:
            self.log_temperature = nn.Parameter(initial.log())
        else:
            self.temperature = nn.Parameter(initial)
        self.overlap = DiffusionNet(
            self.n_neighbours, 1, width=config.overlap_width, n_blocks=config.overlap_blocks, dropout=float(config.dropout)
        )

    def temperature_value(self) -> torch.Tensor:
        """The temperature in use, shape (1,).

        ``exp(log_temperature)``, or the raw parameter clamped at `MIN_TEMPERATURE` (its
        gradient passed through unchanged) when ``learn_log_temperature`` is off.
        """
        if self.learn_log_temperature:
            return self.log_temperature.exp()
        clamped = self.temperature.clamp_min(MIN_TEMPERATURE)
        return self.temperature + (clamped - self.temperature).detach()

    def soft_maps(self, feat_x: torch.Tensor, feat_y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``P_xy`` (V_x, V_y) and ``P_yx`` (V_y, V_x): softmax of cosine similarities over the learned temperature."""
        similarity = F.normalize(feat_x, dim=-1) @ F.normalize(feat_y, dim=-1).T
        scaled = similarity / self.temperature_value()
        return torch.softmax(scaled, dim=1), torch.softmax(scaled.T, dim=1)

    def forward(
        self,
        in_x: torch.Tensor,
        ops_x: SurfaceOperators,
        nbrs_x: torch.Tensor,
        in_y: torch.Tensor,
        ops_y: SurfaceOperators,
        nbrs_y: torch.Tensor,
    ) -> EchoMatchOutput:
        """Features, soft maps and overlap logits of a pair.

        Parameters
        ----------
        in_x, in_y : torch.Tensor, shapes (V_x, C) and (V_y, C)
            Input features.
        ops_x, ops_y : SurfaceOperators
        nbrs_x, nbrs_y : torch.Tensor, shapes (V_x, k_x) and (V_y, k_y), int64
            `spatial_neighbours` of each shape (``k <= n_neighbours``).

        Returns
        -------
        EchoMatchOutput
        """
        feat_x, feat_y = self.features(in_x, ops_x), self.features(in_y, ops_y)
        p_xy, p_yx = self.soft_maps(feat_x, feat_y)
        scores_x = reflection_features(sampled_reflection(p_xy, p_yx, nbrs_x), self.n_neighbours)
        scores_y = reflection_features(sampled_reflection(p_yx, p_xy, nbrs_y), self.n_neighbours)
        logits_x = self.overlap(scores_x, ops_x).squeeze(-1)
        logits_y = self.overlap(scores_y, ops_y).squeeze(-1)
        return EchoMatchOutput(feat_x, feat_y, p_xy, p_yx, logits_x, logits_y)
