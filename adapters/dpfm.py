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

The authors' released models (``pvnieo/DPFM``, ``dpfm/data/saved_models``) load with
`DPFMHead.release_state` (``load_head("dpfm", checkpoint=...)``); ``DPFMHead.PRESETS``
holds the settings of their code. Where that code differs from our defaults:

- input: vertex coordinates centred on their mean and scaled to unit total area, as float32
  (FAUST_r / SCAPE_r; its SHREC'16 data are used as stored), no augmentation at test;
  training augments them (``augmentation=True``: random rotation, noise and per-axis scale);
- operators: cotan Laplacian and DiffusionNet's own operator construction, 128 eigenpairs
  (``laplacian="cotan"``, ``operators="diffusionnet"``);
- attention heads: channel ``c`` belongs to head ``c % n_heads`` (``head_layout="interleaved"``;
  ours takes contiguous blocks of channels);
- interpolation of the refined features (``interpolation="reference"``): the reference meant
  the 3 nearest samples, but it reads the ranks of the 130 nearest of a 0.9-fraction
  farthest-point sample as vertex indices, and picks three of those that are samples in the
  order of torch's unstable sort (see `reference_sample_interpolation`). The presets
  reproduce this, so that a release checkpoint computes here what it computes in the
  reference code; it only touches the refined features (the overlap, and the functional map
  where ``fmap_features="refined"``). The released SHREC'16 weights evidently learned the
  intended interpolation: on the SHREC'16 cat pair shipped with the code, ``"nearest"``
  lifts the overlap ROC AUC of ``shrec_cuts.pth`` from 0.49 (the reference code's own 0.49)
  to 0.99 and cuts the geodesic error of ``shrec_holes.pth`` from 24.2 to 4.7 (x100), so
  pass ``interpolation="nearest"`` to use those checkpoints as their authors trained them;
- functional map from the DiffusionNet features on FAUST_r, SCAPE_r and SHREC'16 cuts
  (``fmap_features="extracted"``, the reference's ``robust: False``), refined on holes;
- ground-truth functional map on FAUST_r: least squares on the template points
  (``fmap_ground_truth="template_lstsq"``); the overlap loss of a one-class mask weighs 0
  (``single_class_weight=0``);
- still different (training only): the reference draws NCE pairs among all vertices of ``y``
  (its ``-1`` entries then pick the last vertex of ``x``) and its partial ground truth sends
  vertices without a counterpart to the last vertex of ``x``; ours skips them. Its optimiser
  is Adam with betas (0.9, 0.99) and step decay; the shared training loop uses torch's default
  betas.

>>> head = make_head("dpfm", descriptor="xyz", epochs=100)                 # doctest: +SKIP
>>> head.fit(load_dataset("synthetic_cuts", split="train"))                # doctest: +SKIP
>>> match = head.match(pair)  # map_yx (V_y,), overlap_y (V_y,), overlap_x (V_x,)  # doctest: +SKIP
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

from geofeat.checks import check_boolean, check_integer
from geofeat.datasets.records import ShapePair
from geofeat.errors import HeadError
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh

from .diffusion_net import DiffusionNet
from .fmap_layers import regularized_fmap
from .functional_maps import nearest_neighbors
from .heads import HeadConfig, LearnedHead, Match, check_integers, check_numbers, ground_truth_map, ground_truth_overlaps
from .operators import SurfaceOperators
from .release import ReleaseState, diffusionnet_state, state_problems

__all__ = [
    "FMAP_FEATURES",
    "FMAP_GROUND_TRUTHS",
    "HEAD_LAYOUTS",
    "INTERPOLATIONS",
    "POINTMAPS",
    "CrossAttentionRefiner",
    "DPFMConfig",
    "DPFMHead",
    "DPFMNet",
    "DPFMOutput",
    "ReferenceCandidates",
    "SampleInterpolation",
    "augment_xyz",
    "farthest_point_sampling",
    "ground_truth_fmap",
    "reference_candidates",
    "reference_sample_interpolation",
    "sample_interpolation",
    "template_fmap",
    "weighted_overlap_bce",
]

#: Which features the functional map is computed from.
FMAP_FEATURES = ("refined", "extracted")
#: How a match turns the prediction into a point map.
POINTMAPS = ("fmap", "features")
#: Which channels form an attention head: contiguous blocks (ours) or every ``n_heads``-th channel (the reference).
HEAD_LAYOUTS = ("contiguous", "interleaved")
#: How refined features reach every vertex: its nearest samples (ours) or the reference code's choice.
INTERPOLATIONS = ("nearest", "reference")
#: Ground-truth functional map of the loss: projection of the point map, or least squares on template points.
FMAP_GROUND_TRUTHS = ("projection", "template_lstsq")
#: Reference interpolation: fraction of the vertices in its farthest-point candidate list.
REFERENCE_CANDIDATE_RATIO = 0.9
#: Reference interpolation: nearest candidates kept for every vertex.
REFERENCE_CANDIDATES = 130
#: Reference augmentation (its training script): maximal rotation about x, y, z in degrees,
#: noise standard deviation and clip, per-axis scale range.
AUGMENT_ROTATION_DEGREES = (30.0, 30.0, 60.0)
AUGMENT_NOISE = (0.01, 0.05)
AUGMENT_SCALE = (0.9, 1.1)
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
    head_layout : {"contiguous", "interleaved"}
        Channels of attention head ``h``: the ``h``-th block of ``attention_dim / n_heads``
        channels, or the channels ``c`` with ``c % n_heads == h`` (the reference's layout,
        needed by its released weights).
    interpolation : {"nearest", "reference"}
        How the refined sample features reach every vertex: its ``n_interpolation`` nearest
        samples, inverse-squared-distance weighted; or the reference code's choice
        (`reference_sample_interpolation`, ``n_interpolation`` must be 3), which the
        presets reproduce (see the module notes: the released weights work better with
        ``"nearest"``).
    fmap_ground_truth : {"projection", "template_lstsq"}
        Ground truth of the functional-map loss: `ground_truth_fmap` of ``map_yx``, or
        `template_fmap`, the least-squares map between the eigenvectors at the template
        points of the pair (``pair.corr_x``, ``pair.corr_y``), as the reference's FAUST_r /
        SCAPE_r training.
    augmentation : bool
        Train on randomly rotated, noisy and rescaled coordinates (`augment_xyz`, the
        reference's training augmentation); needs ``descriptor="xyz"``.
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
    head_layout: str = "contiguous"
    interpolation: str = "nearest"
    fmap_ground_truth: str = "projection"
    augmentation: bool = False


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
    for name in ("dropout", "overlap_weighted_fmap", "augmentation"):
        setattr(c, name, check_boolean(getattr(c, name), name, owner="dpfm", error=HeadError))
    for name, valid in (
        ("head_layout", HEAD_LAYOUTS),
        ("interpolation", INTERPOLATIONS),
        ("fmap_ground_truth", FMAP_GROUND_TRUTHS),
    ):
        if getattr(c, name) not in valid:
            raise HeadError(f"dpfm: {name} must be one of {valid}; found {getattr(c, name)!r}.")
    if c.interpolation == "reference":
        if c.n_interpolation != 3:
            raise HeadError(f"dpfm: interpolation='reference' averages 3 samples; found n_interpolation={c.n_interpolation}.")
        if REFERENCE_CANDIDATE_RATIO < c.sampling_ratio < 1 or c.max_samples is not None:
            raise HeadError(
                f"dpfm: interpolation='reference' samples a fraction sampling_ratio <= {REFERENCE_CANDIDATE_RATIO} (or 1) "
                f"of the vertices without max_samples; found sampling_ratio={c.sampling_ratio}, max_samples={c.max_samples}."
            )
    if c.augmentation and c.descriptor != "xyz":
        raise HeadError(f"dpfm: augmentation transforms coordinates; it needs descriptor='xyz', found {c.descriptor!r}.")


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
    check_integer(n_samples, "n_samples", owner="farthest_point_sampling", low=1, high=n, error=HeadError)
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


class ReferenceCandidates(NamedTuple):
    """The per-shape sampling record of the DPFM reference code (what its data loader stores).

    Attributes
    ----------
    order : torch.Tensor, shape (S,), int64
        Vertices of a farthest-point sample of ``int(0.9 V)`` points, in the order chosen.
    ranks : torch.Tensor, shape (V, n), int64
        For every vertex, the positions in ``order`` of its ``n = min(130, S)`` nearest
        samples, nearest first.
    sq_dists : torch.Tensor, shape (V, n), float32
        Their squared distances, computed in float32 as ``|p|^2 - 2 p.q + |q|^2``.
    """

    order: torch.Tensor
    ranks: torch.Tensor
    sq_dists: torch.Tensor


def reference_candidates(points, seed: int = 0, block: int = 1024, order=None) -> ReferenceCandidates:
    """Candidate samples of a shape as the DPFM reference code prepares them.

    A farthest-point sample of ``int(0.9 V)`` vertices (`farthest_point_sampling`; the
    reference starts at a random vertex of torch's global generator) and, for every vertex,
    its 130 nearest samples by float32 squared distance (the reference's expansion, sorted).

    Parameters
    ----------
    points : array_like, shape (V, 3)
        Vertex positions as the reference sees them (FAUST_r: centred, unit area, float32).
    seed : int
        Seed of the first sample.
    block : int
        Rows of the distance matrix handled at a time (memory bound).
    order : array_like of int, shape (S,), optional
        Use this sample order instead of drawing one (e.g. the reference's own).

    Returns
    -------
    ReferenceCandidates
        CPU tensors.
    """
    pts = torch.as_tensor(np.asarray(points, dtype=np.float32))
    n_vertices = pts.shape[0]
    n_order = int(REFERENCE_CANDIDATE_RATIO * n_vertices)
    if n_order < 1:
        raise HeadError(f"reference_candidates: a shape of {n_vertices} vertices has no {REFERENCE_CANDIDATE_RATIO} sample.")
    if order is None:
        order = torch.from_numpy(farthest_point_sampling(pts.double().numpy(), n_order, seed))
    else:
        order = torch.as_tensor(np.asarray(order, dtype=np.int64))
    cand = pts[order]
    cand_sq = cand.square().sum(-1).view(1, -1)
    n_keep = min(REFERENCE_CANDIDATES, len(order))
    ranks, dists = [], []
    for start in range(0, n_vertices, block):
        rows = pts[start : start + block]
        d = -2 * rows @ cand.T
        d += rows.square().sum(-1).view(-1, 1)
        d += cand_sq
        d, index = d.sort(dim=-1)
        ranks.append(index[:, :n_keep].clone())
        dists.append(d[:, :n_keep].clone())
    return ReferenceCandidates(order, torch.cat(ranks), torch.cat(dists))


def reference_sample_interpolation(candidates: ReferenceCandidates, n_samples: int) -> SampleInterpolation:
    """The samples and per-vertex interpolation of the DPFM reference code, quirks included.

    The samples are the first ``n_samples`` of ``candidates.order``. The reference meant
    every vertex to average its 3 nearest samples, but it reads the candidate ranks (positions
    in ``order``) as vertex indices: a candidate counts when the vertex with the index of its
    rank is a sample, and that vertex's features are used, weighted by the candidate's
    inverse squared distance (``1 / (d^2 + 1e-8)``, normalised, float32). Of the counting
    candidates it takes the first three of ``torch.argsort(counts, descending=True)``, whose
    order among equal keys is torch's (unstable sort). Each shape gets its own scrambling,
    drawn with the random start of the farthest-point sample.

    Parameters
    ----------
    candidates : ReferenceCandidates
        From `reference_candidates` (or the reference's own ``sample_idx`` record).
    n_samples : int
        ``1 <= n_samples <= len(candidates.order)``.

    Returns
    -------
    SampleInterpolation
        CPU tensors; ``neighbours`` index the samples.

    Raises
    ------
    HeadError
        A vertex with fewer than 3 counting candidates, or a weight that is not finite
        (where the reference itself would index out of range or give NaN).
    """
    order, ranks, sq_dists = candidates
    n_vertices = ranks.shape[0]
    if not 1 <= n_samples <= len(order):
        raise HeadError(f"reference_sample_interpolation: n_samples must lie in [1, {len(order)}]; found {n_samples}.")
    samples = order[:n_samples]
    counts = torch.from_numpy(np.isin(ranks.numpy(), samples.numpy())).int()
    pick = torch.argsort(counts.unsqueeze(0), dim=-1, descending=True)[0, :, :3]
    chosen = torch.gather(ranks, 1, pick)
    if not bool(torch.gather(counts, 1, pick).all()):
        raise HeadError("reference_sample_interpolation: a vertex has fewer than 3 counting candidates; sample more vertices.")
    lookup = torch.arange(max(n_vertices, int(chosen.max()) + 1))
    lookup[samples] = torch.arange(n_samples)
    recip = 1.0 / (torch.gather(sq_dists, 1, pick) + INTERPOLATION_EPS)
    weights = recip / recip.sum(dim=1, keepdim=True)
    if not bool(torch.isfinite(weights).all()):
        raise HeadError("reference_sample_interpolation: a squared distance of -1e-8 gives an infinite weight.")
    return SampleInterpolation(samples.clone(), lookup[chosen], weights.float())


def augment_xyz(xyz: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
    """Randomly rotated, noisy and rescaled coordinates (the reference's training augmentation).

    Rotation ``R_z R_y R_x`` with angles uniform in +-`AUGMENT_ROTATION_DEGREES`, Gaussian
    noise of standard deviation ``AUGMENT_NOISE[0]`` clipped to +-``AUGMENT_NOISE[1]``, then a
    scale per axis uniform in `AUGMENT_SCALE`.

    Parameters
    ----------
    xyz : torch.Tensor, shape (V, 3)
    rng : numpy.random.Generator

    Returns
    -------
    torch.Tensor, shape (V, 3), dtype and device of ``xyz``
    """
    angles = np.radians([rng.uniform(-a, a) for a in AUGMENT_ROTATION_DEGREES])
    cx, cy, cz = np.cos(angles)
    sx, sy, sz = np.sin(angles)
    rot_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    rot_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rot_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rotation = torch.as_tensor(rot_z @ rot_y @ rot_x, dtype=xyz.dtype, device=xyz.device)
    std, clip = AUGMENT_NOISE
    noise = torch.as_tensor(np.clip(std * rng.standard_normal(tuple(xyz.shape)), -clip, clip), dtype=xyz.dtype, device=xyz.device)
    scale = torch.as_tensor(rng.uniform(*AUGMENT_SCALE, size=3), dtype=xyz.dtype, device=xyz.device)
    return (xyz @ rotation.T + noise) * scale


# ----------------------------------------------------------------------------- network


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


def template_fmap(evecs_x: torch.Tensor, evecs_y: torch.Tensor, corr_x, corr_y) -> torch.Tensor:
    """Least-squares functional map between the eigenvectors at corresponding template points.

    ``C_gt = X^T`` with ``X = argmin ||Phi_x[corr_x] X - Phi_y[corr_y]||_F`` (the ground truth
    of the DPFM reference code on FAUST_r and SCAPE_r).

    Parameters
    ----------
    evecs_x : torch.Tensor, shape (V_x, k_x)
    evecs_y : torch.Tensor, shape (V_y, k_y)
    corr_x, corr_y : array_like of int, shape (T,)
        Vertex of ``x`` and of ``y`` at each template point.

    Returns
    -------
    torch.Tensor, shape (k_y, k_x)
    """
    index_x = torch.as_tensor(np.asarray(corr_x, dtype=np.int64), device=evecs_x.device)
    index_y = torch.as_tensor(np.asarray(corr_y, dtype=np.int64), device=evecs_y.device)
    if index_x.shape != index_y.shape or index_x.ndim != 1:
        raise HeadError(
            f"template_fmap: corr_x and corr_y must be (T,) arrays of one length; found {tuple(index_x.shape)}, {tuple(index_y.shape)}."
        )
    return torch.linalg.lstsq(evecs_x[index_x], evecs_y[index_y]).solution.T


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


def _dpfm_extractor_key(ours: str) -> str:
    """The reference (original DiffusionNet) name of a key of our `DiffusionNet` state dict."""
    parts = ours.split(".")
    if parts[0] in ("first", "last"):
        return f"{parts[0]}_lin.{parts[1]}"
    block = f"block_{parts[1]}"
    if parts[2] == "diffusion":
        return f"{block}.diffusion.diffusion_time"
    if parts[2] == "gradient_features":
        return f"{block}.gradient_features.{'A_re' if parts[3] == 'a_re' else 'A_im'}.weight"
    return f"{block}.mlp.miniMLP_mlp_layer_{int(parts[3]) // 3:03d}.{parts[4]}"


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
    #: Settings of the authors' code. ``"reference"``: FAUST_r / SCAPE_r (``config/faust.yaml``,
    #: ``config/scape.yaml``, shapes at unit area, template least-squares ground truth);
    #: ``"reference_shrec16_cuts"`` / ``"reference_shrec16_holes"``: its SHREC'16 configurations
    #: (its data: full shapes at unit area, each partial shape in the frame and scale of its
    #: full shape, i.e. `normalized_pair`). Inputs are the coordinates of the prepared pair.
    #: The sizes of a release checkpoint come from its tensors.
    PRESETS = {
        "reference": {
            "descriptor": "xyz",
            "descriptor_params": {"normalize": False},
            "mesh_normalization": "unit_area",
            "laplacian": "cotan",
            "operators": "diffusionnet",
            "n_eig": 128,
            "n_fmap": 50,
            "width": 128,
            "n_blocks": 4,
            "dropout": True,
            "attention_dim": 128,
            "n_heads": 4,
            "n_attention_layers": 1,
            "sampling_ratio": 0.7,
            "max_samples": None,
            "n_interpolation": 3,
            "head_layout": "interleaved",
            "interpolation": "reference",
            "lambda_": 100.0,
            "gamma": 0.5,
            "fmap_features": "extracted",
            "overlap_weighted_fmap": False,
            "w_fmap": 1.0,
            "w_overlap": 1.0,
            "w_nce": 0.0,
            "nce_temperature": 0.07,
            "nce_pairs": 4096,
            "single_class_weight": 0.0,
            "fmap_ground_truth": "template_lstsq",
            "augmentation": True,
            "pointmap": "fmap",
            "lr": 1e-3,
        },
    }
    PRESETS["reference_shrec16_cuts"] = PRESETS["reference"] | {
        "sampling_ratio": 0.4,
        "fmap_ground_truth": "projection",
    }
    PRESETS["reference_shrec16_holes"] = PRESETS["reference_shrec16_cuts"] | {
        "n_fmap": 30,
        "sampling_ratio": 0.3,
        "fmap_features": "refined",
        "w_nce": 1.0,
        "nce_pairs": 512,
    }

    def __init__(self, config: DPFMConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        _check_config(self.config)
        self._samples: LRUCache[str, SampleInterpolation] = LRUCache(_SAMPLE_CACHE_SIZE)
        self._rng = np.random.default_rng(self.config.seed)

    def build_model(self, in_channels: int) -> DPFMNet:
        """`DPFMNet` for ``in_channels`` input features."""
        return DPFMNet(in_channels, self.config)

    @classmethod
    def release_state(cls, raw: Mapping[str, torch.Tensor], source: str = "checkpoint") -> ReleaseState:
        """Translate a state dict of the authors' ``DPFMNet`` (``dpfm/data/saved_models/*.pth``) for this head.

        Key mapping (``L`` a layer, ``P`` weight or bias; Conv1d kernel-1 weights (out, in, 1)
        become Linear weights (out, in)):

        ===========================================================  ==========================================
        reference                                                     ours
        ===========================================================  ==========================================
        ``feature_extractor.*``                                       ``extractor.*`` (`release.diffusionnet_state`, style "dpfm")
        ``feat_refiner.first_lin.P`` / ``last_lin.P``                  ``refiner.first.P`` / ``refiner.last.P``
        ``feat_refiner.layers.L.attn.proj.{0,1,2}.P``                  ``refiner.layers.L.attention.{query,key,value}.P``
        ``feat_refiner.layers.L.attn.merge.P``                         ``refiner.layers.L.attention.merge.P``
        ``feat_refiner.layers.L.mlp.0.P`` / ``mlp.3.P``                ``refiner.layers.L.hidden.P`` / ``out.P``
        ``feat_refiner.overlap_predictor.overlap_score_net.{0,2}.P``   ``overlap.net.{0,2}.P``
        ===========================================================  ==========================================

        The widths, number of blocks, attention width and layers are read from the tensors;
        the number of attention heads is not stored in them (the reference uses 4, the
        preset's ``n_heads``), and its head layout is ``"interleaved"``.

        Parameters
        ----------
        raw : mapping of str to torch.Tensor
            The loaded state dict.
        source : str
            Name of the checkpoint in error messages.

        Returns
        -------
        ReleaseState
            Settings (sizes, ``descriptor="xyz"``), our state dict, input channels (3).

        Raises
        ------
        HeadError
            A missing, unexpected or wrongly shaped key (the checkpoint's name for it).
        """
        if not isinstance(raw, Mapping) or not all(isinstance(v, torch.Tensor) for v in raw.values()):
            raise HeadError(f"{source}: expected a DPFM state dict (str -> tensor).")
        extractor_prefix, refiner_prefix = "feature_extractor.", "feat_refiner."
        outside = sorted(k for k in raw if not k.startswith((extractor_prefix, refiner_prefix)))
        if outside:
            raise HeadError(f"{source}: unexpected key(s) {outside} in a DPFM checkpoint.")
        sizes, extractor = diffusionnet_state(raw, "dpfm", prefix=extractor_prefix, what=source)
        width = sizes["width"]
        first = f"{refiner_prefix}first_lin.weight"
        if first not in raw:
            raise HeadError(f"{source}: missing key {first}.")
        attention_dim = int(raw[first].shape[0])
        layer_re = re.compile(re.escape(refiner_prefix) + r"layers\.(\d+)\.")
        layers = sorted({int(m.group(1)) for k in raw if (m := layer_re.match(k))})
        if layers != list(range(len(layers))):
            raise HeadError(f"{source}: refiner layers must be numbered 0..n-1; found {layers}.")
        mapping = {"first_lin": "first", "last_lin": "last"}
        mapping |= {f"overlap_predictor.overlap_score_net.{i}": f"overlap.net.{i}" for i in (0, 2)}
        for i in layers:
            ours_l, theirs_l = f"refiner.layers.{i}", f"layers.{i}"
            for j, name in enumerate(("query", "key", "value")):
                mapping[f"{theirs_l}.attn.proj.{j}"] = f"{ours_l}.attention.{name}"
            mapping[f"{theirs_l}.attn.merge"] = f"{ours_l}.attention.merge"
            mapping[f"{theirs_l}.mlp.0"] = f"{ours_l}.hidden"
            mapping[f"{theirs_l}.mlp.3"] = f"{ours_l}.out"
        mapping = {
            f"{refiner_prefix}{k}.{p}": (v if v.startswith(("refiner.", "overlap.")) else f"refiner.{v}") + f".{p}"
            for k, v in mapping.items()
            for p in ("weight", "bias")
        }
        settings = {
            "descriptor": "xyz",
            "descriptor_params": {"normalize": False},
            "width": width,
            "n_blocks": sizes["n_blocks"],
            "attention_dim": attention_dim,
            "n_attention_layers": len(layers),
        }
        expected = DPFMNet(3, DPFMConfig(**(cls.PRESETS["reference"] | settings))).state_dict()
        names = {f"extractor.{k}": extractor_prefix + _dpfm_extractor_key(k) for k in extractor}
        names |= {ours: theirs for theirs, ours in mapping.items()}
        state = {f"extractor.{k}": v for k, v in extractor.items()}
        unexpected = sorted(k for k in raw if k.startswith(refiner_prefix) and k not in mapping)
        for theirs, ours in mapping.items():
            if theirs in raw:
                tensor = raw[theirs]
                if tensor.ndim == 3 and tensor.shape[-1] == 1 and expected[ours].ndim == 2:
                    tensor = tensor[..., 0]  # Conv1d kernel 1 -> Linear
                state[ours] = tensor
        problems = ([f"unexpected {unexpected}"] if unexpected else []) + state_problems(expected, state, names, raw)
        if problems:
            raise HeadError(f"{source} does not fit DPFM: " + "; ".join(problems) + ".")
        return ReleaseState(settings, {k: v.detach().clone().float().contiguous() for k, v in state.items()}, 3)

    # -- per-shape data

    def n_samples(self, n_vertices: int) -> int:
        """Farthest-point samples used on a shape of ``n_vertices`` vertices."""
        n = max(1, int(self.config.sampling_ratio * n_vertices))
        if self.config.max_samples is not None:
            n = min(n, int(self.config.max_samples))
        return min(n, n_vertices)

    def samples(self, mesh: Mesh) -> SampleInterpolation:
        """Farthest-point samples of a mesh of a prepared pair and their interpolation, on the head's device (kept for 64 meshes).

        Computed on the coordinates as they are where the head normalises its pairs
        (``mesh_normalization``) or with ``interpolation="reference"`` (the reference samples
        the coordinates its network sees); else on the vertices centred and scaled to unit area.
        """
        return self._samples.get_or_compute(mesh.hash, lambda: self._sample_interpolation(mesh))

    def _sample_interpolation(self, mesh: Mesh) -> SampleInterpolation:
        c = self.config
        if c.mesh_normalization is not None or c.interpolation == "reference":
            points = mesh.verts
        else:
            points = mesh.verts - mesh.verts.mean(axis=0)
            area = 0.0
            if mesh.faces is not None:
                area = mesh.area() if callable(mesh.area) else mesh.area
            points = points / (math.sqrt(area) if area > 0 else 1.0)
        n_samples = self.n_samples(mesh.n_vertices)
        if c.interpolation == "reference" and n_samples < mesh.n_vertices:
            entry = reference_sample_interpolation(reference_candidates(points, c.seed), n_samples)
        else:
            entry = sample_interpolation(points, n_samples, c.n_interpolation, c.seed)
        return entry.to(self.device)

    def use_samples(self, mesh: Mesh, interpolation: SampleInterpolation) -> None:
        """Pin the samples and interpolation of ``mesh`` (e.g. the reference code's own record of it)."""
        if interpolation.neighbours.shape[0] != mesh.n_vertices or interpolation.weights.shape != interpolation.neighbours.shape:
            raise HeadError(
                f"dpfm: the interpolation has {interpolation.neighbours.shape[0]} rows; mesh {mesh.name!r} has {mesh.n_vertices} vertices."
            )
        self._samples.put(mesh.hash, interpolation.to(self.device))

    def forward(self, pair: ShapePair, augment: bool = False) -> DPFMOutput:
        """Run the model on a prepared pair (`Head.prepare`; gradients as the caller sets them).

        ``augment`` applies `augment_xyz` to both inputs.
        """
        model = self._ensure_model(pair.x)
        input_x, ops_x = self.shape_inputs(pair.x)
        input_y, ops_y = self.shape_inputs(pair.y)
        if input_x.shape[1] != self.in_channels or input_y.shape[1] != self.in_channels:
            raise HeadError(
                f"dpfm: the model takes {self.in_channels} input channels; pair {pair.name} has "
                f"{input_x.shape[1]} (x) and {input_y.shape[1]} (y)."
            )
        if augment:
            input_x, input_y = augment_xyz(input_x, self._rng), augment_xyz(input_y, self._rng)
        return model(input_x, input_y, ops_x, ops_y, self.samples(pair.x), self.samples(pair.y))

    # -- the interface

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """``w_fmap * ||C - C_gt||^2 + w_overlap * (BCE_x + BCE_y) + w_nce * NCE`` for one prepared pair."""
        c = self.config
        map_yx = ground_truth_map(pair)
        overlap_x, overlap_y = ground_truth_overlaps(pair)
        out = self.forward(pair, augment=c.augmentation)
        _, ops_x = self.shape_inputs(pair.x)
        _, ops_y = self.shape_inputs(pair.y)
        k = c.n_fmap
        if c.fmap_ground_truth == "template_lstsq":
            if pair.corr_x is None or pair.corr_y is None:
                raise HeadError(
                    f"dpfm: fmap_ground_truth='template_lstsq' needs template correspondences; pair {pair.name} has none."
                )
            c_gt = template_fmap(ops_x.evecs[:, :k], ops_y.evecs[:, :k], pair.corr_x, pair.corr_y)
        else:
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
        """Point map y -> x and thresholded overlaps of both shapes of a prepared pair."""
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
