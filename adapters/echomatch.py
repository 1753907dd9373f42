"""EchoMatch (Xie, Ehm, Roetzer, El Amrani, Gao, Bernard and Cremers, CVPR 2025): partial-to-partial matching by correspondence reflection.

Both shapes go through one DiffusionNet feature extractor. Cosine similarities of the
L2-normalised features, divided by a learned temperature, give two soft point maps by a
row-wise softmax: ``P_xy`` (V_x, V_y) from ``x`` to ``y`` and ``P_yx`` (V_y, V_x) back. Their
product ``R_x = P_xy P_yx`` (V_x, V_x) is the *correspondence reflection* of ``x``: row ``i``
says where vertex ``i`` lands after a round trip through ``y``. A vertex that has a
counterpart comes back to itself or next to it; one outside the overlap echoes somewhere
else or nowhere. For each vertex the reflection is read at its nearest neighbours in space
(itself first), divided by the largest value over the shape, and a small DiffusionNet turns
these values into an overlap probability (the same network for ``y`` with ``R_y = P_yx P_xy``).

Training is supervised (``training_loss``):

- functional-map loss: ``||C - C_gt||_F^2`` between the regularised functional map of the
  features (`geofeat.adapters.fmap_layers.regularized_fmap`, first ``n_fmap`` eigenpairs;
  the features of ``y`` outside its ground-truth overlap are zeroed while training) and a
  ground-truth map fitted to the known correspondences with a strong Laplacian-mask
  regulariser (`regularized_gt_fmap`);
- overlap loss: class-balanced binary cross-entropy of both overlap predictions;
- cross-NCE: for every ground-truth pair, InfoNCE over all vertices of the other shape, in
  both directions; self-NCE: every vertex against all vertices of its own shape (spreads the
  features). Both on L2-normalised features with a fixed temperature.

Prediction (``predict``): every vertex of ``y`` goes to the vertex of ``x`` with the most
similar normalised feature (nearest neighbour), and the overlap probabilities are
thresholded.

Facts taken from the authors' code (the EchoMatch model of DeepShapeMatchingKit,
github.com/xieyizheng/DeepShapeMatchingKit: ``models/echo_match_model.py``,
``networks/echo_match_network.py``, ``networks/diffusion_a_network.py``,
``losses/echo_match_loss.py``, ``utils/fmap_util.py``, ``utils/shape_dataset_util.py``,
``options/echo_match/train/echo_match_*_xyz.yaml``), all of them the ``"reference"`` preset:
``xyz`` input; DiffusionNet operators of the cotangent Laplacian with 128 eigenpairs, its
gradient operator built as in ULRSSM's copy of the DiffusionNet code
(``operators="ulrssm"``); feature DiffusionNet with 128 output channels and width, 4
blocks, MLP hidden sizes (128, 128), dropout 0.5, gradient features with rotations;
learned temperature initialised to 0.1; 64 spatial neighbours from Euclidean distances;
overlap DiffusionNet of width 16 with 3 blocks and a sigmoid, on the shape's own operators;
functional map on the first 50 eigenpairs (mass-weighted projections) with ``lambda = 100``
and resolvent ``gamma = 0.5``; ground-truth functional map regularised with
``lambda = 1e6`` (unweighted by area); loss weights fmap 1, overlap 1, self-NCE 0.1,
cross-NCE 0.1, NCE temperature 0.07; only the features of the second shape (here ``y``)
are masked by the ground-truth overlap before the functional map while training; Adam,
learning rate 1e-3, gradient norm clipped at 1 before every step, 900 epochs; overlap
threshold 0.5; test-time map by nearest neighbour of the normalised features.

Parity (``benchmarks/parity_echomatch.py``): fed the same meshes, operators, neighbours
and random weights (copied with `EchoMatchHead.release_state`), our head and the authors'
code agree in double precision to about 1e-10 at every stage, from the features to the
gradients of one training step. In float32 the forward stages agree to a few 1e-6
(relative; the functional map to about 1e-5), the losses to about 1e-6, and the gradients
to 5e-5 to 5e-4 of the largest one, the size of the reference's own float32 error (its
float32 gradients are 5e-4 to 1.5e-3 away from its float64 ones: the functional-map loss
differentiates through the solve of ill-conditioned regularised normal equations).

Where we differ, on purpose:

- ``xyz`` input: the vertices centred on their mean and scaled to unit area (invariant to
  where and how large a shape is stored); the reference feeds the coordinates as stored,
  the same numbers on a centred unit-area mesh.
- spatial neighbours: an exact k-d tree in float64 with the vertex itself first; the
  reference takes the top-k of float32 ``cdist`` distances, which orders near-equal
  distances otherwise (0.4 to 2.5 % of the rows on FAUST_r shapes, a handful with another
  64th neighbour).
- diffusion times (in `geofeat.adapters.diffusion_net.LearnedDiffusion`): clamped at 0 with
  the gradient passed through; the reference writes ``max(t, 1e-8)`` into the parameter at
  every forward. This changes nothing once a time is above 1e-8, but at initialisation (all
  times 0) the loss differs by about 1e-6 (relative) and gradients by up to 4e-3 of a
  parameter's largest entry (activations near a ReLU kink flip), and a time pushed below
  zero by Adam stays below until its gradient brings it back, where the reference resets it
  to 1e-8.
- the overlap network outputs logits and the loss is the equivalent
  ``binary_cross_entropy_with_logits`` (the reference: a sigmoid and ``BCELoss``, whose log
  is clamped at -100);
- the ground-truth functional map is solved in float64 (the reference inverts in float32);
- one ``nce_temperature`` for both NCE terms (the reference's self-NCE hard-codes 0.07,
  its cross-NCE reads ``nce_t``, default 0.07);
- the learned temperature is learned as its logarithm (``learn_log_temperature``), so it
  stays positive and Adam moves it by a ratio, not by an amount: with the reference's raw
  ``tau`` and Adam at lr 1e-2, steps of about 0.01 took the initial 0.1 below zero within
  ten steps (soft maps onto the *least* similar points) and the overlap network learnt
  nothing on some runs (which runs depended on the BLAS thread count). The
  ``"reference"`` preset and the released checkpoints keep the raw ``tau``, clamped at
  ``1e-4`` from below (its gradient passed through);
- the reflection is evaluated only at the neighbours (`sampled_reflection`, the values of
  gathering the dense product, about ``V / k`` times cheaper);
- ``restrict_to_overlap`` (off by default) limits the nearest-neighbour search to the
  predicted overlap of ``x``; the point map is the argmax of cosine similarities (the
  reference: argmin of distances of the normalised features, the same map up to ties).

Not reproduced: the reference's random rotation (up to 30 degrees about each axis), noise
(std 0.01, clipped at 0.05) and per-axis scaling (0.9 to 1.1) of ``xyz`` inputs while
training; its Adam betas (0.9, 0.99) (ours: torch's default (0.9, 0.999); the first step is
the same) and step schedule (learning rate halved every 100 epochs); skipping a step with a
NaN loss; its second test-time point map from the functional map of the unpruned features.

>>> head = make_head("echomatch", preset="reference", epochs=5)             # doctest: +SKIP
>>> head.fit(train_pairs); match = head.match(pair)                        # doctest: +SKIP
>>> match.map_yx, match.overlap_y, match.overlap_x                         # doctest: +SKIP
>>> head = load_head("echomatch", checkpoint="echo_match_cp2p24_xyz.pth")  # doctest: +SKIP
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

from geofeat.checks import check_boolean
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh

from .diffusion_net import DiffusionNet
from .fmap_layers import regularized_fmap, resolvent_mask
from .heads import HeadConfig, check_integers, check_numbers
from .inputs import ground_truth_map, ground_truth_overlaps
from .learned import LearnedHead
from .operators import SurfaceOperators
from .release import ReleaseState, diffusionnet_state

__all__ = [
    "PRUNE_STRATEGIES",
    "EchoMatchConfig",
    "EchoMatchHead",
    "EchoMatchNet",
    "EchoMatchOutput",
    "balanced_bce_with_logits",
    "correspondence_reflection",
    "cross_nce_loss",
    "pointmap_matrix",
    "reflection_features",
    "regularized_gt_fmap",
    "round_trip_error",
    "sampled_reflection",
    "self_nce_loss",
    "spatial_neighbours",
]

#: Which features are zeroed outside the ground-truth overlap before the functional map while
#: training: those of ``y`` (the reference's default), of both shapes, or none.
PRUNE_STRATEGIES = ("y", "both", "none")
#: Lower bound of a raw learned temperature (our choice; the reference does not bound it).
MIN_TEMPERATURE = 1e-4


@dataclass
class EchoMatchConfig(HeadConfig):
    """`HeadConfig` plus the EchoMatch network and loss settings (defaults: the authors' values).

    Parameters
    ----------
    feature_channels : int
        Output channels of the feature DiffusionNet (128).
    width : int
        Width of the feature DiffusionNet (128).
    n_blocks : int
        Blocks of the feature DiffusionNet (4).
    dropout : float
        Dropout probability in the MLPs of both DiffusionNets (0.5).
    temperature_init : float
        Initial value of the learned softmax temperature of the soft point maps (0.1).
    learn_log_temperature : bool
        Our choice (default): learn the logarithm of the temperature, positive by
        construction. ``False``: the reference's raw parameter (clamped at
        `MIN_TEMPERATURE` when in use).
    n_neighbours : int
        Spatial neighbours (the vertex itself included) at which the reflection is read: the
        input width of the overlap network (64).
    overlap_width : int
        Width of the overlap DiffusionNet (16).
    overlap_blocks : int
        Blocks of the overlap DiffusionNet (3).
    n_fmap : int
        Eigenpairs of the functional map (50); at most ``n_eig`` (the operators, 128).
    fmap_lambda : float
        Laplacian-mask weight of the feature functional map (100).
    fmap_gamma : float
        Resolvent exponent of the Laplacian mask (0.5).
    gt_fmap_lambda : float
        Laplacian-mask weight of the ground-truth functional map (1e6); 0 gives
        ``Phi_y^T M_y P_yx Phi_x``.
    w_fmap, w_overlap, w_nce_self, w_nce_cross : float
        Loss weights (1, 1, 0.1, 0.1).
    nce_temperature : float
        Temperature of both NCE losses (0.07).
    prune_strategy : {"y", "both", "none"}
        Features zeroed outside the ground-truth overlap before the training functional map
        (``"y"``).
    overlap_threshold : float
        Probability above which a vertex is predicted to overlap (0.5).
    restrict_to_overlap : bool
        Our option: match ``y`` only to vertices of ``x`` predicted to overlap (all of ``x``
        when none is). Off by default, as in the reference.
    epochs, lr, grad_clip
        900, 1e-3 and 1.0 (gradient norm clipped before every step), the authors' training
        settings.
    """

    feature_channels: int = 128
    width: int = 128
    n_blocks: int = 4
    dropout: float = 0.5
    temperature_init: float = 0.1
    learn_log_temperature: bool = True
    n_neighbours: int = 64
    overlap_width: int = 16
    overlap_blocks: int = 3
    n_fmap: int = 50
    fmap_lambda: float = 100.0
    fmap_gamma: float = 0.5
    gt_fmap_lambda: float = 1e6
    w_fmap: float = 1.0
    w_overlap: float = 1.0
    w_nce_self: float = 0.1
    w_nce_cross: float = 0.1
    nce_temperature: float = 0.07
    prune_strategy: str = "y"
    overlap_threshold: float = 0.5
    restrict_to_overlap: bool = False
    epochs: int = 900
    lr: float = 1e-3
    grad_clip: float | None = 1.0

    def __post_init__(self) -> None:
        check_integers(
            "echomatch", self, ("feature_channels", "width", "n_neighbours", "overlap_width", "n_fmap", "n_eig", "epochs"), 1
        )
        check_integers("echomatch", self, ("n_blocks", "overlap_blocks"), 0)
        if self.n_fmap > self.n_eig:
            raise HeadError(
                f"echomatch: n_fmap={self.n_fmap} eigenpairs for the functional map, but the operators have only "
                f"n_eig={self.n_eig}; raise n_eig or lower n_fmap."
            )
        check_numbers(
            "echomatch", self, ("fmap_lambda", "gt_fmap_lambda", "w_fmap", "w_overlap", "w_nce_self", "w_nce_cross"), 0.0
        )
        check_numbers("echomatch", self, ("temperature_init", "nce_temperature", "lr"), 0.0, low_open=True)
        check_numbers("echomatch", self, ("fmap_gamma",), 0.0, 1.0, low_open=True)
        check_numbers("echomatch", self, ("dropout",), 0.0, 1.0, high_open=True)
        check_numbers("echomatch", self, ("overlap_threshold",), 0.0, 1.0, low_open=True, high_open=True)
        for name in ("learn_log_temperature", "restrict_to_overlap"):
            setattr(self, name, check_boolean(getattr(self, name), name, owner="echomatch", error=HeadError))
        if self.prune_strategy not in PRUNE_STRATEGIES:
            raise HeadError(f"echomatch setting prune_strategy must be one of {PRUNE_STRATEGIES}; found {self.prune_strategy!r}.")


# ----------------------------------------------------------------------------- correspondence reflection


def pointmap_matrix(map_yx, n_x: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Dense one-hot matrix of a hard point map y -> x; rows of unmatched vertices (``-1``) are zero.

    Parameters
    ----------
    map_yx : array_like of int, shape (V_y,)
        For each vertex of ``y`` a vertex of ``x``, or ``-1``.
    n_x : int
        Number of vertices of ``x``.
    dtype : torch.dtype

    Returns
    -------
    torch.Tensor, shape (V_y, n_x)
        ``P[v, map_yx[v]] = 1``.
    """
    index = torch.as_tensor(np.asarray(map_yx), dtype=torch.int64)
    if index.ndim != 1:
        raise HeadError(f"map_yx must be a 1-D integer array, shape (V_y,); found shape {tuple(index.shape)}.")
    if index.numel() and (int(index.min()) < -1 or int(index.max()) >= n_x):
        raise HeadError(
            f"map_yx must hold vertex indices in [0, {n_x - 1}] or -1; found range [{int(index.min())}, {int(index.max())}]."
        )
    matrix = torch.zeros(index.shape[0], n_x, dtype=dtype)
    rows = torch.nonzero(index >= 0).squeeze(1)
    matrix[rows, index[rows]] = 1
    return matrix


def correspondence_reflection(p_xy: torch.Tensor, p_yx: torch.Tensor) -> torch.Tensor:
    """The round trip x -> y -> x of two (soft) point maps: ``R_x = P_xy P_yx``.

    Parameters
    ----------
    p_xy : torch.Tensor, shape (V_x, V_y)
        Point map from ``x`` to ``y`` (rows are vertices of ``x``; a soft map's rows sum to one).
    p_yx : torch.Tensor, shape (V_y, V_x)
        Point map back.

    Returns
    -------
    torch.Tensor, shape (V_x, V_x)
        ``R[i, j]``: how much of vertex ``i`` comes back at vertex ``j``; the identity (on the
        overlap) for an exact pair of maps. Swap the arguments for ``R_y``.
    """
    if p_xy.ndim != 2 or p_yx.ndim != 2 or p_xy.shape[1] != p_yx.shape[0] or p_xy.shape[0] != p_yx.shape[1]:
        raise HeadError(
            f"p_xy and p_yx must have shapes (V_x, V_y) and (V_y, V_x); found {tuple(p_xy.shape)} and {tuple(p_yx.shape)}."
        )
    return p_xy @ p_yx


def spatial_neighbours(verts: np.ndarray, k: int) -> np.ndarray:
    """The ``min(k, V)`` nearest vertices of every vertex in Euclidean space, itself first.

    Parameters
    ----------
    verts : numpy.ndarray, shape (V, 3)
    k : int

    Returns
    -------
    numpy.ndarray, shape (V, min(k, V)), int64
        Sorted by distance; column 0 is the vertex itself (ties in position aside).
    """
    verts = np.asarray(verts, dtype=np.float64)
    k = min(int(k), verts.shape[0])
    _, index = cKDTree(verts).query(verts, k=k)
    index = np.asarray(index, dtype=np.int64).reshape(verts.shape[0], k)
    for row in np.flatnonzero(index[:, 0] != np.arange(verts.shape[0])):  # coincident vertices: itself first
        where = np.flatnonzero(index[row] == row)
        index[row, where[0] if where.size else k - 1] = index[row, 0]
        index[row, 0] = row
    return index


class _SampledProduct(torch.autograd.Function):
    """``out[i, j] = a[i, :] @ b[:, index[i, j]]`` without forming ``a @ b`` (a sampled matrix product)."""

    @staticmethod
    def forward(ctx, a: torch.Tensor, b: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(a, b, index)
        n, k = index.shape
        try:  # sampled dense-dense product on a CSR pattern: a few times faster than the dense product
            order = index.argsort(dim=1)
            cols = index.gather(1, order)
            crow = torch.arange(0, n * k + 1, k, device=index.device)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # "CSR support is in beta"
                pattern = torch.sparse_csr_tensor(crow, cols.reshape(-1), a.new_zeros(n * k), (n, b.shape[1]),
                                                  check_invariants=False)  # fmt: skip
                values = torch.sparse.sampled_addmm(pattern, a, b, beta=0.0).values().reshape(n, k)
            return torch.empty_like(values).scatter_(1, order, values)
        except (RuntimeError, NotImplementedError):  # a device without sampled_addmm: gather in chunks
            b_t = b.T.contiguous()
            rows = max(1, _CHUNK_ELEMENTS // max(1, k * a.shape[1]))
            out = [
                torch.einsum("im,ijm->ij", a[start : start + rows], b_t[index[start : start + rows]])
                for start in range(0, n, rows)
            ]
            return torch.cat(out) if out else a.new_zeros(index.shape)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        a, b, index = ctx.saved_tensors
        n, k = index.shape
        rows = torch.arange(n, device=index.device).repeat_interleave(k)
        # G (n, n_b): grad[i, j] at (i, index[i, j]); d/da = G b^T, d/db = (G^T a)^T
        g = torch.sparse_coo_tensor(
            torch.stack([rows, index.reshape(-1)]), grad.reshape(-1), (n, b.shape[1]), check_invariants=False
        ).coalesce()
        grad_a = torch.sparse.mm(g, b.T.contiguous()) if ctx.needs_input_grad[0] else None
        grad_b = torch.sparse.mm(g.t().coalesce(), a).T if ctx.needs_input_grad[1] else None
        return grad_a, grad_b, None


#: Elements of the largest temporary of `_SampledProduct` (16M float32: 64 MB).
_CHUNK_ELEMENTS = 1 << 24


def sampled_reflection(p_xy: torch.Tensor, p_yx: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """The entries of `correspondence_reflection` at each vertex's neighbours, without the dense product.

    ``out[i, j] = (P_xy P_yx)[i, neighbours[i, j]]``: costs ``V_x * k * V_y`` instead of
    ``V_x^2 * V_y`` and never holds a (V_x, V_x) matrix; differentiable with respect to both maps.

    Parameters
    ----------
    p_xy : torch.Tensor, shape (V_x, V_y)
    p_yx : torch.Tensor, shape (V_y, V_x)
    neighbours : torch.Tensor, shape (V_x, k), int64

    Returns
    -------
    torch.Tensor, shape (V_x, k)
    """
    if p_xy.ndim != 2 or p_yx.ndim != 2 or p_xy.shape[1] != p_yx.shape[0] or p_xy.shape[0] != p_yx.shape[1]:
        raise HeadError(
            f"p_xy and p_yx must have shapes (V_x, V_y) and (V_y, V_x); found {tuple(p_xy.shape)} and {tuple(p_yx.shape)}."
        )
    if neighbours.ndim != 2 or neighbours.shape[0] != p_xy.shape[0]:
        raise HeadError(f"neighbours must have shape ({p_xy.shape[0]}, k); found {tuple(neighbours.shape)}.")
    return _SampledProduct.apply(p_xy, p_yx, neighbours.to(torch.int64))


def reflection_features(scores: torch.Tensor, width: int | None = None) -> torch.Tensor:
    """The input of the overlap network: reflection entries at the neighbours, scaled to a maximum of one.

    Parameters
    ----------
    scores : torch.Tensor, shape (V, k)
        `sampled_reflection` (or ``torch.gather(correspondence_reflection(...), 1, neighbours)``).
    width : int, optional
        Columns of the result; zero columns are appended when ``k < width`` (a shape with
        fewer vertices than neighbours requested). Default ``k``.

    Returns
    -------
    torch.Tensor, shape (V, width)
        ``scores`` divided by their largest value over the shape.
    """
    scores = scores / scores.max().clamp_min(torch.finfo(scores.dtype).tiny)
    width = scores.shape[1] if width is None else int(width)
    if scores.shape[1] < width:
        scores = F.pad(scores, (0, width - scores.shape[1]))
    return scores


def round_trip_error(reflection: torch.Tensor, verts, mask=None) -> torch.Tensor:
    """Mean expected Euclidean distance between a vertex and where its round trip lands.

    Parameters
    ----------
    reflection : torch.Tensor, shape (V, V)
        `correspondence_reflection` (rows of a soft round trip sum to one).
    verts : array_like, shape (V, 3)
    mask : array_like of bool, shape (V,), optional
        Vertices to average over (default all).

    Returns
    -------
    torch.Tensor, shape ()
        ``mean_i sum_j R[i, j] |v_i - v_j|``: zero for an exact round trip.
    """
    v = torch.tensor(np.asarray(verts), dtype=reflection.dtype, device=reflection.device)
    dist = torch.cdist(v, v, compute_mode="donot_use_mm_for_euclid_dist")  # exact zeros on the diagonal
    per_vertex = (reflection * dist).sum(dim=1)
    if mask is not None:
        per_vertex = per_vertex[torch.as_tensor(np.asarray(mask, dtype=bool), device=reflection.device)]
    return per_vertex.mean()


# ----------------------------------------------------------------------------- losses


def balanced_bce_with_logits(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy with each class weighted by the frequency of the other one.

    Positives weigh ``1 - p`` and negatives ``p``, ``p`` the fraction of positives, averaged
    over all vertices; plain mean cross-entropy when ``target`` has a single class.

    Parameters
    ----------
    logits : torch.Tensor, shape (V,)
    target : torch.Tensor, shape (V,), bool or {0, 1}

    Returns
    -------
    torch.Tensor, shape ()
    """
    target = target.to(logits.dtype)
    loss = F.binary_cross_entropy_with_logits(logits, target, reduction="none")
    n_pos = float(target.sum())
    if n_pos == 0 or n_pos == target.numel():
        return loss.mean()
    frac = n_pos / target.numel()
    weights = torch.where(target > 0.5, target.new_tensor(1.0 - frac), target.new_tensor(frac))  # in the loss's dtype
    return (weights * loss).mean()


def cross_nce_loss(
    feat_x: torch.Tensor, feat_y: torch.Tensor, corr_x: torch.Tensor, corr_y: torch.Tensor, temperature: float
) -> torch.Tensor:
    """InfoNCE of ground-truth pairs across the shapes, both directions, on normalised features.

    Parameters
    ----------
    feat_x : torch.Tensor, shape (V_x, p)
    feat_y : torch.Tensor, shape (V_y, p)
    corr_x, corr_y : torch.Tensor, shape (n,), int64
        Corresponding vertices: ``corr_x[i]`` of ``x`` matches ``corr_y[i]`` of ``y``.
    temperature : float

    Returns
    -------
    torch.Tensor, shape ()
        Cross-entropy of ``corr_y`` over all of ``y`` for the rows ``corr_x``, plus the reverse.
    """
    fx, fy = F.normalize(feat_x, dim=-1), F.normalize(feat_y, dim=-1)
    logits = fx @ fy.T / temperature  # (V_x, V_y)
    return F.cross_entropy(logits[corr_x], corr_y) + F.cross_entropy(logits.T[corr_y], corr_x)


def self_nce_loss(feat: torch.Tensor, temperature: float) -> torch.Tensor:
    """InfoNCE of every vertex against all vertices of its own shape, on normalised features.

    Parameters
    ----------
    feat : torch.Tensor, shape (V, p)
    temperature : float

    Returns
    -------
    torch.Tensor, shape ()
    """
    f = F.normalize(feat, dim=-1)
    return F.cross_entropy(f @ f.T / temperature, torch.arange(f.shape[0], device=f.device))


def regularized_gt_fmap(map_yx, evecs_x: torch.Tensor, evecs_y: torch.Tensor, evals_x: torch.Tensor, evals_y: torch.Tensor,
                        lambda_: float, gamma: float = 0.5, mass_y: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """Ground-truth functional map (k_y, k_x) of a partial map y -> x, fitted with a Laplacian-mask regulariser.

    Minimises ``||Phi_y C - P_yx Phi_x||_F^2 + lambda_ sum_ij W_ij C_ij^2`` over the vertices
    of ``y`` (unweighted by area, as the reference), ``P_yx`` the one-hot matrix of
    ``map_yx`` (zero rows where ``-1``) and ``W`` the resolvent mask; solved column by column
    in float64. With ``lambda_ = 0`` it returns ``Phi_y^T M_y P_yx Phi_x`` instead (needs
    ``mass_y``).

    Parameters
    ----------
    map_yx : torch.Tensor, shape (V_y,), int64
    evecs_x : torch.Tensor, shape (V_x, k_x)
    evecs_y : torch.Tensor, shape (V_y, k_y)
    evals_x : torch.Tensor, shape (k_x,)
    evals_y : torch.Tensor, shape (k_y,)
    lambda_ : float
    gamma : float
    mass_y : torch.Tensor, shape (V_y,), optional

    Returns
    -------
    torch.Tensor, shape (k_y, k_x), dtype of ``evecs_x``
    """
    out_dtype = evecs_x.dtype
    ex, ey = evecs_x.detach().double(), evecs_y.detach().double()
    valid = map_yx >= 0
    pulled = torch.zeros(ey.shape[0], ex.shape[1], dtype=torch.float64, device=ex.device)
    pulled[valid] = ex[map_yx[valid]]  # P_yx Phi_x
    if lambda_ == 0:
        if mass_y is None:
            raise HeadError("regularized_gt_fmap with lambda_=0 needs mass_y.")
        return (ey.T @ (mass_y.detach().double()[:, None] * pulled)).to(out_dtype)
    gram = ey.T @ ey  # (k_y, k_y)
    rhs = ey.T @ pulled  # (k_y, k_x)
    weights = resolvent_mask(evals_x.detach().double().cpu(), evals_y.detach().double().cpu(), gamma=gamma).to(ex.device)
    systems = gram.unsqueeze(0) + lambda_ * torch.diag_embed(weights.T)  # (k_x, k_y, k_y): one per column of C
    columns = torch.linalg.solve(systems, rhs.T.unsqueeze(-1)).squeeze(-1)  # (k_x, k_y)
    return columns.T.contiguous().to(out_dtype)


# ----------------------------------------------------------------------------- network


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
        self.features = DiffusionNet(in_channels, config.feature_channels, width=config.width, n_blocks=config.n_blocks,
                                     dropout=float(config.dropout))  # fmt: skip
        self.learn_log_temperature = bool(config.learn_log_temperature)
        initial = torch.tensor([float(config.temperature_init)])
        if self.learn_log_temperature:
            self.log_temperature = nn.Parameter(initial.log())
        else:
            self.temperature = nn.Parameter(initial)
        self.overlap = DiffusionNet(self.n_neighbours, 1, width=config.overlap_width, n_blocks=config.overlap_blocks,
                                    dropout=float(config.dropout))  # fmt: skip

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

    def forward(self, in_x: torch.Tensor, ops_x: SurfaceOperators, nbrs_x: torch.Tensor,
                in_y: torch.Tensor, ops_y: SurfaceOperators, nbrs_y: torch.Tensor) -> EchoMatchOutput:  # fmt: skip
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


# ----------------------------------------------------------------------------- head


class EchoMatchHead(LearnedHead):
    """EchoMatch: learned features, overlap prediction by correspondence reflection, nearest-neighbour map."""

    name = "echomatch"
    config_class = EchoMatchConfig
    #: ``"reference"``: the conventions of the authors' code (DeepShapeMatchingKit,
    #: ``options/echo_match/train/echo_match_*_xyz.yaml``): vertex coordinates in, the
    #: DiffusionNet reference operators on the cotangent Laplacian, 128 eigenpairs for the
    #: networks and 50 for the functional maps, gradient norm clipped at 1.
    PRESETS = {
        "reference": {
            "descriptor": "xyz",
            "laplacian": "cotan",
            "operators": "ulrssm",
            "n_eig": 128,
            "n_fmap": 50,
            "feature_channels": 128,
            "width": 128,
            "n_blocks": 4,
            "dropout": 0.5,
            "temperature_init": 0.1,
            "learn_log_temperature": False,
            "n_neighbours": 64,
            "overlap_width": 16,
            "overlap_blocks": 3,
            "fmap_lambda": 100.0,
            "fmap_gamma": 0.5,
            "gt_fmap_lambda": 1e6,
            "w_fmap": 1.0,
            "w_overlap": 1.0,
            "w_nce_self": 0.1,
            "w_nce_cross": 0.1,
            "nce_temperature": 0.07,
            "prune_strategy": "y",
            "overlap_threshold": 0.5,
            "restrict_to_overlap": False,
            "epochs": 900,
            "lr": 1e-3,
            "grad_clip": 1.0,
        }
    }

    def __init__(self, config: EchoMatchConfig | None = None, **settings):
        super().__init__(config, **settings)
        self._neighbours: LRUCache[str, torch.Tensor] = LRUCache(64)

    @classmethod
    def release_state(cls, raw: dict, source: str = "checkpoint") -> ReleaseState:
        """Translate a checkpoint of the authors' EchoMatch model for this head.

        The layout is DeepShapeMatchingKit's ``{"networks": {"echo_match_net": state}}`` (or
        the bare ``state``): ``feature_extractor.*`` and ``overlap_diffusion_net.*`` are
        DiffusionNets with DPFM's key spelling (`release.diffusionnet_state` with
        ``style="dpfm"``), ``permutation_network.tau`` the learned temperature. A
        ``module.`` prefix (DataParallel) is dropped, as the reference does when it resumes.
        The sizes come from the tensors; only ``xyz`` inputs (3 channels) are supported.

        Returns
        -------
        ReleaseState
            Settings (``feature_channels``, ``width``, ``n_blocks``, ``n_neighbours``,
            ``overlap_width``, ``overlap_blocks``, ``descriptor``), our state dict (the same
            tensor objects) and the input width.

        Raises
        ------
        HeadError
            Another layout, a missing, unexpected or wrongly shaped key (named), or sizes
            our `EchoMatchNet` does not have.
        """
        networks = raw.get("networks", raw)
        state = networks.get("echo_match_net", networks) if isinstance(networks, dict) else None
        if not isinstance(state, dict) or "permutation_network.tau" not in {k.replace("module.", "") for k in state}:
            raise HeadError(
                f"{source}: expected the EchoMatch layout {{'networks': {{'echo_match_net': state_dict}}}} with "
                "'feature_extractor.*', 'permutation_network.tau' and 'overlap_diffusion_net.*'."
            )
        state = {k.replace("module.", ""): v for k, v in state.items()}
        ours: dict[str, torch.Tensor] = {}
        sizes = {}
        for ref_prefix, our_prefix in (("feature_extractor.", "features."), ("overlap_diffusion_net.", "overlap.")):
            sizes[our_prefix], part = diffusionnet_state(state, "dpfm", prefix=ref_prefix, what=source)
            ours.update({our_prefix + k: v for k, v in part.items()})
        ours["temperature"] = state["permutation_network.tau"]
        unexpected = sorted(
            k for k in state if not k.startswith(("feature_extractor.", "overlap_diffusion_net.", "permutation_network.tau"))
        )
        if unexpected:
            raise HeadError(f"{source}: unexpected key(s) {unexpected} in the EchoMatch network.")
        feat, over = sizes["features."], sizes["overlap."]
        for name, s in (("feature", feat), ("overlap", over)):
            if s["mlp_hidden"] != [s["width"]] * 2 or not s["with_gradient_rotations"]:
                raise HeadError(
                    f"{source}: the {name} DiffusionNet's block MLPs {s['mlp_hidden']} / gradient rotations differ from EchoMatch's."
                )
        if over["out_channels"] != 1:
            raise HeadError(f"{source}: the overlap DiffusionNet has {over['out_channels']} outputs instead of 1.")
        if feat["in_channels"] != 3:
            raise HeadError(
                f"{source}: the feature DiffusionNet takes {feat['in_channels']} input channels; only xyz checkpoints "
                "(3 channels) are supported (the DINO ones need the reference's own DINO features)."
            )
        settings = {
            "descriptor": "xyz",
            "descriptor_params": {},
            "feature_channels": feat["out_channels"],
            "width": feat["width"],
            "n_blocks": feat["n_blocks"],
            "n_neighbours": over["in_channels"],
            "overlap_width": over["width"],
            "overlap_blocks": over["n_blocks"],
            "learn_log_temperature": False,  # the checkpoint holds the raw temperature
        }
        return ReleaseState(settings, ours, feat["in_channels"])

    def build_model(self, in_channels: int) -> EchoMatchNet:
        """`EchoMatchNet` for ``in_channels`` input features, sized by the config."""
        return EchoMatchNet(in_channels, self.config)

    def neighbours(self, mesh: Mesh) -> torch.Tensor:
        """`spatial_neighbours` of ``mesh`` on the head's device, (V, min(n_neighbours, V)) int64 (kept for 64 meshes)."""
        return self._neighbours.get_or_compute(
            mesh.hash, lambda: torch.as_tensor(spatial_neighbours(mesh.verts, self.config.n_neighbours), device=self.device)
        )

    def network_outputs(self, pair: ShapePair) -> tuple[EchoMatchOutput, SurfaceOperators, SurfaceOperators]:
        """Run the network on a pair; also returns the operators of ``x`` and ``y``."""
        model = self._ensure_model(pair.x)
        in_x, ops_x = self.shape_inputs(pair.x)
        in_y, ops_y = self.shape_inputs(pair.y)
        for mesh, feats in ((pair.x, in_x), (pair.y, in_y)):
            if feats.shape[1] != self.in_channels:
                raise HeadError(
                    f"head {self.name!r} was built for {self.in_channels} input channels, but {mesh.name!r} has "
                    f"{feats.shape[1]} with descriptor {self.config.descriptor!r}."
                )
        out = model(in_x, ops_x, self.neighbours(pair.x), in_y, ops_y, self.neighbours(pair.y))
        return out, ops_x, ops_y

    def loss_terms(self, pair: ShapePair) -> dict[str, torch.Tensor]:
        """The weighted loss terms of one pair: ``"fmap"``, ``"overlap"``, ``"nce_cross"``, ``"nce_self"``.

        Raises
        ------
        HeadError
            A malformed ground truth, or a pair without any correspondence.
        """
        c = self.config
        map_np = ground_truth_map(pair)
        overlap_x_np, overlap_y_np = ground_truth_overlaps(pair)
        out, ops_x, ops_y = self.network_outputs(pair)
        device = out.feat_x.device
        map_yx = torch.as_tensor(map_np, device=device)
        overlap_x = torch.as_tensor(overlap_x_np, device=device)
        overlap_y = torch.as_tensor(overlap_y_np, device=device)

        k = c.n_fmap
        evecs_x, evecs_y = ops_x.evecs[:, :k], ops_y.evecs[:, :k]
        evals_x, evals_y = ops_x.evals[:k], ops_y.evals[:k]
        use_x, use_y = out.feat_x, out.feat_y
        if c.prune_strategy in ("y", "both"):
            use_y = use_y * overlap_y[:, None].to(use_y.dtype)
        if c.prune_strategy == "both":
            use_x = use_x * overlap_x[:, None].to(use_x.dtype)
        c_pred = regularized_fmap(use_x, use_y, evecs_x, evecs_y, ops_x.mass, ops_y.mass, evals_x, evals_y,
                                  lambda_=c.fmap_lambda, gamma=c.fmap_gamma)  # fmt: skip
        c_gt = regularized_gt_fmap(map_yx, evecs_x, evecs_y, evals_x, evals_y, c.gt_fmap_lambda, c.fmap_gamma, ops_y.mass)

        corr_y = torch.nonzero(map_yx >= 0).squeeze(1)
        corr_x = map_yx[corr_y]
        bce_x = balanced_bce_with_logits(out.overlap_logits_x, overlap_x)
        bce = bce_x + balanced_bce_with_logits(out.overlap_logits_y, overlap_y)
        nce_self = self_nce_loss(out.feat_x, c.nce_temperature) + self_nce_loss(out.feat_y, c.nce_temperature)
        return {
            "fmap": c.w_fmap * (c_pred - c_gt).square().sum(),
            "overlap": c.w_overlap * bce,
            "nce_cross": c.w_nce_cross * cross_nce_loss(out.feat_x, out.feat_y, corr_x, corr_y, c.nce_temperature),
            "nce_self": c.w_nce_self * nce_self,
        }

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """Sum of `loss_terms`: functional map + overlap BCE + cross-NCE + self-NCE."""
        return sum(self.loss_terms(pair).values())

    def overlap_probabilities(self, pair: ShapePair) -> tuple[np.ndarray, np.ndarray]:
        """Predicted overlap probabilities ``(x (V_x,), y (V_y,))`` float32 (network in eval mode, no gradients)."""
        self._ensure_model(pair.x).eval()
        with torch.no_grad():
            out, _, _ = self.network_outputs(pair)
        return (torch.sigmoid(out.overlap_logits_x).cpu().numpy().astype(np.float32),
                torch.sigmoid(out.overlap_logits_y).cpu().numpy().astype(np.float32))  # fmt: skip

    def predict(self, pair: ShapePair) -> Match:
        """Nearest neighbour of the normalised features and overlaps above ``overlap_threshold``.

        Returns
        -------
        Match
            ``map_yx`` (V_y,) int64, ``overlap_y`` (V_y,) bool, ``overlap_x`` (V_x,) bool.
        """
        out, _, _ = self.network_outputs(pair)
        threshold = self.config.overlap_threshold
        prob_x, prob_y = torch.sigmoid(out.overlap_logits_x), torch.sigmoid(out.overlap_logits_y)
        overlap_x, overlap_y = prob_x > threshold, prob_y > threshold
        fx, fy = F.normalize(out.feat_x, dim=-1), F.normalize(out.feat_y, dim=-1)
        candidates = torch.arange(fx.shape[0], device=fx.device)
        if self.config.restrict_to_overlap and bool(overlap_x.any()):
            candidates = torch.nonzero(overlap_x).squeeze(1)
        map_yx = candidates[_nearest(fx[candidates], fy)]
        return Match(
            map_yx.cpu().numpy().astype(np.int64), overlap_y.cpu().numpy(), overlap_x.cpu().numpy(),
            prob_y.cpu().numpy().astype(np.float32), prob_x.cpu().numpy().astype(np.float32),
        )  # fmt: skip


def _nearest(fx: torch.Tensor, fy: torch.Tensor, block: int = 4096) -> torch.Tensor:
    """For every row of ``fy`` (unit vectors) the row of ``fx`` with the largest dot product (= nearest)."""
    return torch.cat([(fy[start : start + block] @ fx.T).argmax(dim=1) for start in range(0, fy.shape[0], block)])
