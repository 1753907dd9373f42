"""DPFM (Attaiki, Pai and Ovsjanikov 2021, "DPFM: Deep Partial Functional Maps"), a supervised partial matcher.

The network has four parts:

1. a feature extractor: `DiffusionNet` from the input features (any geofeat descriptor, or
   ``"xyz"`` as in the paper) to ``width`` channels on each shape;
2. a cross-attention refinement: on farthest-point samples of both shapes (a fraction
   ``sampling_ratio`` of the vertices), a linear lift to ``attention_dim`` channels, then
   ``n_attention_layers`` rounds in which the samples of ``x`` attend to those of ``y`` and
   then the samples of ``y`` to the updated ones of ``x`` (multi-head attention, a message
   MLP with instance normalisation, residual updates); after each round every vertex gets
   the inverse-squared-distance weighted mean of its 3 nearest samples (Euclidean, in
   coordinates normalised to unit area), and a linear layer maps back to ``width`` channels;
3. an overlap predictor: a small MLP on the L2-normalised refined features giving, for
   every vertex of both shapes, the probability that it has a counterpart on the other;
4. a regularised functional map (`geofeat.adapters.fmap_layers.regularized_fmap`, resolvent
   mask, ``lambda_`` and ``gamma``) in the first ``n_fmap`` eigenfunctions, from the refined
   features (or those of the extractor, ``fmap_features="extracted"``).

Training is supervised: the squared Frobenius distance to the ground-truth functional map
``Phi_y^T M_y P_yx Phi_x`` (rows of vertices of ``y`` without a counterpart are zero),
class-weighted binary cross-entropy of the overlap of both shapes, and optionally a
contrastive (InfoNCE) term on corresponding features. A match converts the functional map to
a point map (nearest neighbours of spectral embeddings, or of features with
``pointmap="features"``) and thresholds the overlap probabilities.

>>> head = make_head("dpfm", descriptor="xyz", epochs=100)                 # doctest: +SKIP
>>> head.fit(load_dataset("synthetic_cuts", split="train"))                # doctest: +SKIP
>>> match = head.match(pair)  # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,)  # doctest: +SKIP
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

from geofeat.datasets.records import ShapePair
from geofeat.mesh import Mesh

from .diffusion_net import DiffusionNet
from .fmap_layers import regularized_fmap
from .functional_maps import nearest_neighbors
from .heads import (
    HeadConfig,
    HeadError,
    LearnedHead,
    Match,
    check_integers,
    check_numbers,
    ground_truth_map,
    ground_truth_overlaps,
)
from .operators import SurfaceOperators

__all__ = [
    "FMAP_FEATURES",
    "POINTMAPS",
    "CrossAttentionRefiner",
    "DPFMConfig",
    "DPFMHead",
    "DPFMNet",
    "DPFMOutput",
    "SampleInterpolation",
    "farthest_point_sampling",
    "ground_truth_fmap",
    "sample_interpolation",
    "weighted_overlap_bce",
]

#: Which features the functional map is computed from.
FMAP_FEATURES = ("refined", "extracted")
#: How a match turns the prediction into a point map.
POINTMAPS = ("fmap", "features")
#: Added to squared distances before inverting them into interpolation weights (as the reference).
INTERPOLATION_EPS = 1e-8
#: Variance floor of the instance normalisation in the message MLPs (torch's InstanceNorm1d default).
INSTANCE_NORM_EPS = 1e-5
_SAMPLE_CACHE_SIZE = 64


# ----------------------------------------------------------------------------- configuration


@dataclass
class DPFMConfig(HeadConfig):
    """`HeadConfig` plus the DPFM sizes, functional map, losses and matching.

    Defaults are the reference configuration for SHREC'16 cuts where it sets a value.

    Parameters
    ----------
    width : int
        Channels of the DiffusionNet blocks and of its output features (128).
    n_blocks : int
        DiffusionNet blocks (4).
    dropout : bool
        Dropout (p = 0.5) in the DiffusionNet block MLPs (True).
    attention_dim : int
        Channels inside the cross-attention refinement (128).
    n_heads : int
        Attention heads (4); must divide ``attention_dim``.
    n_attention_layers : int
        Cross-attention rounds (1); 0 skips the refinement (then only the two linear layers
        act per vertex).
    sampling_ratio : float
        Fraction of the vertices of each shape sampled by farthest-point sampling for the
        attention, in (0, 1] (0.4; 1 attends over all vertices, no interpolation).
    max_samples : int or None
        Upper bound on the samples per shape (None: no bound), for small machines.
    n_interpolation : int
        Nearest samples averaged to bring refined features back to every vertex (3).
    n_fmap : int
        Eigenfunctions of the functional map on each shape (50), ``<= n_eig``.
    lambda_ : float
        Weight of the resolvent Laplacian term of the functional map (100).
    gamma : float
        Resolvent exponent in (0, 1] (0.5).
    fmap_features : {"refined", "extracted"}
        Compute the functional map (and the NCE term) from the refined features (the
        reference's ``robust: True``, its HOLES setting) or from the DiffusionNet output
        (``robust: False``, its CUTS setting). With ``"extracted"`` only the overlap loss
        trains the cross-attention refiner.
    overlap_weighted_fmap : bool
        Multiply the features by the predicted overlap probability before the functional map
        (not in the reference code, which uses the overlap only in the loss; off by default).
    w_fmap : float
        Weight of the functional-map loss (1).
    w_overlap : float
        Weight of the overlap loss of each shape (1).
    w_nce : float
        Weight of the contrastive loss (0.1, the default of the reference's loss class; its
        configurations use 0 for cuts and 1 for holes).
    nce_temperature : float
        Temperature of the contrastive loss (0.07).
    nce_pairs : int
        Corresponding vertex pairs drawn for the contrastive loss per step (4096).
    single_class_weight : float
        Weight of every vertex in the overlap loss of a shape whose ground-truth mask holds
        a single class (the partial shape of a P2F pair is all overlap). The reference's
        class weights (the fraction of the other class) are 0 there, so it never trains
        that side; 0 reproduces it, the default 0.5 teaches the all-overlap answer.
    pointmap : {"fmap", "features"}
        Point map of a match: nearest neighbours of spectral embeddings under the predicted
        functional map, or of the (L2-normalised) functional-map features.
    overlap_threshold : float
        Probability above which a vertex is predicted to overlap, in (0, 1) (0.5).
    """

    width: int = 128
    n_blocks: int = 4
    dropout: bool = True
    attention_dim: int = 128
    n_heads: int = 4
    n_attention_layers: int = 1
    sampling_ratio: float = 0.4
    max_samples: int | None = None
    n_interpolation: int = 3
    n_fmap: int = 50
    lambda_: float = 100.0
    gamma: float = 0.5
    fmap_features: str = "refined"
    overlap_weighted_fmap: bool = False
    w_fmap: float = 1.0
    w_overlap: float = 1.0
    w_nce: float = 0.1
    nce_temperature: float = 0.07
    nce_pairs: int = 4096
    single_class_weight: float = 0.5
    pointmap: str = "fmap"
    overlap_threshold: float = 0.5


def _check_config(c: DPFMConfig) -> None:
    """Raise `HeadError` for any setting outside its range."""

    check_integers("dpfm", c, ("width", "n_heads", "n_interpolation", "n_fmap", "nce_pairs", "attention_dim", "n_eig"), 1)
    check_integers("dpfm", c, ("n_blocks", "n_attention_layers"), 0)
    if c.attention_dim % c.n_heads:
        raise HeadError(f"dpfm: n_heads ({c.n_heads}) must divide attention_dim ({c.attention_dim}).")
    if c.n_fmap > c.n_eig:
        raise HeadError(f"dpfm: n_fmap ({c.n_fmap}) cannot exceed n_eig ({c.n_eig}); raise n_eig or lower n_fmap.")
    if c.max_samples is not None:
        check_integers("dpfm", c, ("max_samples",), 1)
    check_numbers("dpfm", c, ("sampling_ratio", "gamma"), 0.0, 1.0, low_open=True)
    check_numbers("dpfm", c, ("overlap_threshold",), 0.0, 1.0, low_open=True, high_open=True)
    check_numbers("dpfm", c, ("nce_temperature",), 0.0, low_open=True)
    check_numbers("dpfm", c, ("lambda_", "w_fmap", "w_overlap", "w_nce", "single_class_weight"), 0.0)
    if c.fmap_features not in FMAP_FEATURES:
        raise HeadError(f"dpfm: fmap_features must be one of {FMAP_FEATURES}; found {c.fmap_features!r}.")
    if c.pointmap not in POINTMAPS:
        raise HeadError(f"dpfm: pointmap must be one of {POINTMAPS}; found {c.pointmap!r}.")
    if not isinstance(c.dropout, bool) or not isinstance(c.overlap_weighted_fmap, bool):
        raise HeadError(
            f"dpfm: dropout and overlap_weighted_fmap must be booleans; found {c.dropout!r}, {c.overlap_weighted_fmap!r}."
        )


# ----------------------------------------------------------------------------- sampling


def farthest_point_sampling(points, n_samples: int, seed: int | np.random.Generator = 0) -> np.ndarray:
    """Indices of ``n_samples`` points spread by greedy farthest-point sampling (Euclidean).

    Starts from a point drawn with ``seed``; each next sample is the point farthest from all
    samples so far (the first on ties). Any prefix of the result is itself a farthest-point
    sample.

    Parameters
    ----------
    points : array_like, shape (N, D)
    n_samples : int
        ``1 <= n_samples <= N``.
    seed : int or numpy.random.Generator
        Chooses the first sample.

    Returns
    -------
    numpy.ndarray, shape (n_samples,), int64
        Distinct indices into ``points``, in the order they were chosen.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[0] == 0 or not np.isfinite(pts).all():
        raise HeadError(f"farthest_point_sampling: points must be a finite (N, D) array with N >= 1; found shape {pts.shape}.")
    n = pts.shape[0]
    if not isinstance(n_samples, (int, np.integer)) or isinstance(n_samples, bool) or not 1 <= n_samples <= n:
        raise HeadError(f"farthest_point_sampling: n_samples must be an integer in [1, {n}]; found {n_samples!r}.")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    chosen = np.empty(int(n_samples), dtype=np.int64)
    chosen[0] = rng.integers(n)
    nearest = np.full(n, np.inf)
    for i in range(1, int(n_samples)):
        diff = pts - pts[chosen[i - 1]]
        np.minimum(nearest, np.einsum("nd,nd->n", diff, diff), out=nearest)
        chosen[i] = int(np.argmax(nearest))
    return chosen


class SampleInterpolation(NamedTuple):
    """Farthest-point samples of a shape and how every vertex averages them.

    Attributes
    ----------
    samples : torch.Tensor, shape (S,), int64
        Sampled vertex indices.
    neighbours : torch.Tensor, shape (V, n), int64
        For every vertex its ``n`` nearest samples, as positions in ``samples``.
    weights : torch.Tensor, shape (V, n), float32
        Inverse squared distances, normalised to sum to one per vertex (a sample's own
        weight is 1 up to ``INTERPOLATION_EPS``).
    """

    samples: torch.Tensor
    neighbours: torch.Tensor
    weights: torch.Tensor

    def to(self, device: torch.device) -> SampleInterpolation:
        return SampleInterpolation(*(t.to(device) for t in self))

    def interpolate(self, sampled: torch.Tensor) -> torch.Tensor:
        """Per-vertex features (V, C) from per-sample features (S, C)."""
        return (sampled[self.neighbours] * self.weights.unsqueeze(-1)).sum(dim=1)


def sample_interpolation(points, n_samples: int, n_neighbours: int = 3, seed: int = 0) -> SampleInterpolation:
    """Farthest-point samples of ``points`` and inverse-squared-distance interpolation weights.

    Parameters
    ----------
    points : array_like, shape (V, 3)
        Vertex positions (the head passes them centred and scaled to unit area).
    n_samples : int
        ``1 <= n_samples <= V``.
    n_neighbours : int
        Samples averaged per vertex (clipped to ``n_samples``).
    seed : int
        Seed of `farthest_point_sampling`.

    Returns
    -------
    SampleInterpolation
        CPU tensors.
    """
    pts = np.asarray(points, dtype=np.float64)
    samples = farthest_point_sampling(pts, n_samples, seed)
    k = max(1, min(int(n_neighbours), len(samples)))
    dist, nbr = cKDTree(pts[samples]).query(pts, k=k)
    dist, nbr = dist.reshape(len(pts), k), nbr.reshape(len(pts), k)
    inv = 1.0 / (np.square(dist) + INTERPOLATION_EPS)
    weights = inv / inv.sum(axis=1, keepdims=True)
    return SampleInterpolation(
        torch.from_numpy(samples),
        torch.from_numpy(nbr.astype(np.int64)),
        torch.from_numpy(weights.astype(np.float32)),
    )


# ----------------------------------------------------------------------------- network


def _instance_norm(h: torch.Tensor) -> torch.Tensor:
    """Normalise every channel of (N, C) over the N points (no affine part)."""
    mean = h.mean(dim=0, keepdim=True)
    var = h.var(dim=0, unbiased=False, keepdim=True)
    return (h - mean) / torch.sqrt(var + INSTANCE_NORM_EPS)


class _MultiHeadAttention(nn.Module):
    """Scaled dot-product attention of queries (N, d) over keys and values (M, d), ``n_heads`` heads."""

    def __init__(self, dim: int, n_heads: int) -> None:
        super().__init__()
        self.n_heads, self.head_dim = n_heads, dim // n_heads
        self.query, self.key, self.value, self.merge = (nn.Linear(dim, dim) for _ in range(4))

    def forward(self, x: torch.Tensor, source: torch.Tensor) -> torch.Tensor:
        def heads(t: torch.Tensor) -> torch.Tensor:  # (N, d) -> (h, N, d/h)
            return t.reshape(t.shape[0], self.n_heads, self.head_dim).transpose(0, 1)

        q, k, v = heads(self.query(x)), heads(self.key(source)), heads(self.value(source))
        scores = q @ k.transpose(1, 2) / math.sqrt(self.head_dim)  # (h, N, M)
        out = torch.softmax(scores, dim=-1) @ v  # (h, N, d/h)
        return self.merge(out.transpose(0, 1).reshape(x.shape[0], -1))


class _AttentionalPropagation(nn.Module):
    """The update of ``x`` from ``source``: an MLP of ``[x, attention(x, source)]`` (add it to ``x``)."""

    def __init__(self, dim: int, n_heads: int) -> None:
        super().__init__()
        self.attention = _MultiHeadAttention(dim, n_heads)
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
    """

    def __init__(self, width: int, attention_dim: int, n_heads: int, n_layers: int) -> None:
        super().__init__()
        self.first = nn.Linear(width, attention_dim)
        self.layers = nn.ModuleList(_AttentionalPropagation(attention_dim, n_heads) for _ in range(n_layers))
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
        self.refiner = CrossAttentionRefiner(c.width, c.attention_dim, c.n_heads, c.n_attention_layers)
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
            fx, fy, ops_x.evecs[:, :k], ops_y.evecs[:, :k], ops_x.mass, ops_y.mass, ops_x.evals[:k], ops_y.evals[:k],
            lambda_=c.lambda_, gamma=c.gamma,
        )  # fmt: skip
        return DPFMOutput(fmap, logits_x, logits_y, use_x, use_y)


# ----------------------------------------------------------------------------- supervision


def ground_truth_fmap(map_yx, evecs_x: torch.Tensor, evecs_y: torch.Tensor, mass_y: torch.Tensor) -> torch.Tensor:
    """``C_gt = Phi_y^T M_y P_yx Phi_x`` of a possibly partial point map (rows of ``-1`` vertices are zero).

    Parameters
    ----------
    map_yx : array_like of int, shape (V_y,)
        Vertex of ``x`` for every vertex of ``y``, ``-1`` for none.
    evecs_x : torch.Tensor, shape (V_x, k_x)
    evecs_y : torch.Tensor, shape (V_y, k_y)
    mass_y : torch.Tensor, shape (V_y,)

    Returns
    -------
    torch.Tensor, shape (k_y, k_x)
    """
    index = torch.as_tensor(np.array(map_yx, dtype=np.int64), device=evecs_x.device)
    valid = (index >= 0).to(evecs_x.dtype)
    pulled = evecs_x[index.clamp(min=0)] * valid.unsqueeze(-1)  # (V_y, k_x)
    return evecs_y.T @ (mass_y.unsqueeze(-1) * pulled)


def weighted_overlap_bce(logits: torch.Tensor, target: torch.Tensor, single_class_weight: float = 0.5) -> torch.Tensor:
    """Class-weighted binary cross-entropy of overlap predictions (DPFM's weighted BCE).

    With ``p`` the fraction of positive vertices, positives weigh ``1 - p`` and negatives
    ``p``, so both classes contribute equally; the loss is the mean of the weighted terms.
    When ``target`` holds one class only, every vertex weighs ``single_class_weight``.

    Parameters
    ----------
    logits : torch.Tensor, shape (V,)
    target : torch.Tensor, shape (V,), bool or {0, 1}
    single_class_weight : float

    Returns
    -------
    torch.Tensor, shape ()
    """
    target = target.to(logits.dtype)
    p = target.mean()
    if float(p) in (0.0, 1.0):
        weights = torch.full_like(target, float(single_class_weight))
    else:
        weights = torch.where(target >= 0.5, 1.0 - p, p)
    return (weights * F.binary_cross_entropy_with_logits(logits, target, reduction="none")).mean()


def _nce_loss(feat_x, feat_y, map_yx: np.ndarray, n_pairs: int, temperature: float, rng: np.random.Generator):
    """InfoNCE over corresponding pairs: each chosen ``x`` feature must pick its own ``y`` feature among all chosen."""
    valid = np.flatnonzero(map_yx >= 0)
    chosen = rng.choice(valid, n_pairs, replace=False) if len(valid) > n_pairs else valid
    index_y = torch.as_tensor(chosen, device=feat_y.device)
    index_x = torch.as_tensor(map_yx[chosen], device=feat_x.device)
    query = F.normalize(feat_x[index_x], p=2, dim=-1)
    keys = F.normalize(feat_y[index_y], p=2, dim=-1)
    logits = -torch.cdist(query, keys) / temperature
    return F.cross_entropy(logits, torch.arange(len(chosen), device=logits.device))


# ----------------------------------------------------------------------------- head


class DPFMHead(LearnedHead):
    """DPFM as a geofeat head: supervised training on pairs with ground truth, overlap-aware matches.

    Settings are those of `DPFMConfig`; bad ones raise `geofeat.adapters.heads.HeadError`.
    """

    name = "dpfm"
    config_class = DPFMConfig

    def __init__(self, config: DPFMConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        _check_config(self.config)
        self._samples: OrderedDict[str, SampleInterpolation] = OrderedDict()
        self._rng = np.random.default_rng(self.config.seed)

    def build_model(self, in_channels: int) -> DPFMNet:
        """`DPFMNet` for ``in_channels`` input features."""
        return DPFMNet(in_channels, self.config)

    # -- per-shape data

    def n_samples(self, n_vertices: int) -> int:
        """Farthest-point samples used on a shape of ``n_vertices`` vertices."""
        n = max(1, int(self.config.sampling_ratio * n_vertices))
        if self.config.max_samples is not None:
            n = min(n, int(self.config.max_samples))
        return min(n, n_vertices)

    def samples(self, mesh: Mesh) -> SampleInterpolation:
        """Farthest-point samples of ``mesh`` and their interpolation, on the head's device (kept for 64 meshes)."""
        key = mesh.hash
        if key in self._samples:
            self._samples.move_to_end(key)
            return self._samples[key]
        points = mesh.verts - mesh.verts.mean(axis=0)
        area = 0.0
        if mesh.faces is not None:
            area = mesh.area() if callable(mesh.area) else mesh.area
        points = points / (math.sqrt(area) if area > 0 else 1.0)
        entry = sample_interpolation(points, self.n_samples(mesh.n_vertices), self.config.n_interpolation, self.config.seed)
        entry = entry.to(self.device)
        self._samples[key] = entry
        while len(self._samples) > _SAMPLE_CACHE_SIZE:
            self._samples.popitem(last=False)
        return entry

    def forward(self, pair: ShapePair) -> DPFMOutput:
        """Run the model on a pair (gradients as the caller sets them)."""
        model = self._ensure_model(pair.x)
        input_x, ops_x = self.shape_inputs(pair.x)
        input_y, ops_y = self.shape_inputs(pair.y)
        if input_x.shape[1] != self.in_channels or input_y.shape[1] != self.in_channels:
            raise HeadError(
                f"dpfm: the model takes {self.in_channels} input channels; pair {pair.name} has "
                f"{input_x.shape[1]} (x) and {input_y.shape[1]} (y)."
            )
        return model(input_x, input_y, ops_x, ops_y, self.samples(pair.x), self.samples(pair.y))

    # -- the interface

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """``w_fmap * ||C - C_gt||^2 + w_overlap * (BCE_x + BCE_y) + w_nce * NCE`` for one pair."""
        c = self.config
        map_yx = ground_truth_map(pair)
        overlap_x, overlap_y = ground_truth_overlaps(pair)
        out = self.forward(pair)
        _, ops_x = self.shape_inputs(pair.x)
        _, ops_y = self.shape_inputs(pair.y)
        k = c.n_fmap
        c_gt = ground_truth_fmap(map_yx, ops_x.evecs[:, :k], ops_y.evecs[:, :k], ops_y.mass)
        loss = c.w_fmap * (out.fmap - c_gt).square().sum()
        device = out.fmap.device
        target_x = torch.as_tensor(overlap_x, device=device)
        target_y = torch.as_tensor(overlap_y, device=device)
        loss = loss + c.w_overlap * (
            weighted_overlap_bce(out.overlap_logits_x, target_x, c.single_class_weight)
            + weighted_overlap_bce(out.overlap_logits_y, target_y, c.single_class_weight)
        )
        if c.w_nce > 0:
            loss = loss + c.w_nce * _nce_loss(out.feat_x, out.feat_y, map_yx, c.nce_pairs, c.nce_temperature, self._rng)
        return loss

    def predict(self, pair: ShapePair) -> Match:
        """Point map y -> x and thresholded overlaps of both shapes."""
        c = self.config
        out = self.forward(pair)
        if c.pointmap == "fmap":
            _, ops_x = self.shape_inputs(pair.x)
            _, ops_y = self.shape_inputs(pair.y)
            k = c.n_fmap
            emb_x = (ops_x.evecs[:, :k] @ out.fmap.T).cpu().numpy()
            emb_y = ops_y.evecs[:, :k].cpu().numpy()
            map_yx = nearest_neighbors(emb_x, emb_y, device=self.device)
        else:
            fx = F.normalize(out.feat_x, p=2, dim=-1).cpu().numpy()
            fy = F.normalize(out.feat_y, p=2, dim=-1).cpu().numpy()
            map_yx = nearest_neighbors(fx, fy, device=self.device)
        prob_x = torch.sigmoid(out.overlap_logits_x).cpu().numpy().astype(np.float32)
        prob_y = torch.sigmoid(out.overlap_logits_y).cpu().numpy().astype(np.float32)
        threshold = c.overlap_threshold
        return Match(np.asarray(map_yx, dtype=np.int64), prob_y > threshold, prob_x > threshold, prob_y, prob_x)
