"""Contrastive losses of GeoLoRA training: geodesic-weighted and plain PointInfoNCE.

One partial shape is matched against the full shape it was cut from. Every observed
partial vertex ``p`` with a ground-truth full vertex ``g(p)`` is a query; its logits are

* the positive: ``cos(f_p, f_g(p)) / T`` (never weighted);
* one negative per full vertex ``j`` (``g(p)`` itself included):
  ``cos(f_p, f_j) * (offset + d(g(p), j)) / T`` for the geodesic-weighted loss, or
  ``cos(f_p, f_j) / T`` for the plain loss,

and the loss is the cross-entropy with the positive as the target, averaged over the
queries. ``d`` is the geodesic distance on the full shape divided by the square root of its
surface area (the trainer's `geofeat.train.geodesics.TorchGeodesicStore`). Only the partial -> full direction is used and
every full vertex takes part (no sub-sampling).

This follows the released GeoLoRA training code (vikiehm/geo-lora: the weighted loss in
``utils/utils.py``, its call in ``train.py``, the distance normalisation in
``utils/shape_dataset.py`` and ``utils/utils.py``). Full vertices seen in no view keep a
zero feature there, so they stay among the negatives with a logit of 0; ``unseen_full="drop"``
removes them instead.

Memory: a few ``(P, F)`` float32 matrices (100 MB each for 5,000 x 5,000).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import numpy as np
import torch
import torch.nn.functional as fn

from geofeat.errors import TrainingError

__all__ = [
    "DEFAULT_OFFSET",
    "DEFAULT_TEMPERATURE",
    "geodesic_point_info_nce",
    "observed_rows",
    "point_info_nce",
]

#: Temperature of the softmax, as in the GeoLoRA release.
DEFAULT_TEMPERATURE = 0.1
#: Added to the normalised geodesic distance to give the weight of a negative logit.
DEFAULT_OFFSET = 0.5

UnseenFull = Literal["zero", "drop"]
_UNSEEN_FULL = ("zero", "drop")


def observed_rows(features: torch.Tensor) -> torch.Tensor:
    """Rows that hold a feature: the vertices seen in at least one view.

    Back-projection with ``fill="zero"`` leaves the vertices seen in no view at exactly
    zero; this recovers that mask. (The GeoLoRA code tests ``row.sum() != 0``; testing every
    entry does not mistake a row that sums to zero for an unseen one.)

    Parameters
    ----------
    features : torch.Tensor, shape (N, C), floating

    Returns
    -------
    torch.Tensor, shape (N,), bool
    """
    _check_features(features, "features")
    return (features != 0).any(dim=1)


def geodesic_point_info_nce(
    feat_partial: torch.Tensor,
    feat_full: torch.Tensor,
    gt_full_index: torch.Tensor,
    geodesic_full: torch.Tensor,
    *,
    seen_partial: torch.Tensor | None = None,
    seen_full: torch.Tensor | None = None,
    temperature: float = DEFAULT_TEMPERATURE,
    offset: float = DEFAULT_OFFSET,
    unseen_full: UnseenFull = "zero",
) -> torch.Tensor:
    """Geodesic-weighted PointInfoNCE from a partial shape to its full shape.

    Parameters
    ----------
    feat_partial : torch.Tensor, shape (P, C), floating
        Features of the partial shape (any scale: they are L2-normalised here).
    feat_full : torch.Tensor, shape (F, C), floating, same device
        Features of the full shape.
    gt_full_index : torch.Tensor, shape (P,), integer
        Ground-truth full vertex of each partial vertex, ``-1`` for none (ignored).
    geodesic_full : torch.Tensor, shape (F, F), floating
        Geodesic distances on the full shape divided by ``sqrt(area)``
        (`geofeat.train.geodesics.TorchGeodesicStore.load`). Only the rows of ground-truth vertices are read; they must
        be finite and non-negative. Any device: the rows used are moved to the features'.
    seen_partial : torch.Tensor, shape (P,), bool, optional
        Partial vertices seen in at least one view; the others are no query (their features
        are never read). Default: all seen.
    seen_full : torch.Tensor, shape (F,), bool, optional
        Full vertices seen in at least one view. Default: all seen.
    temperature : float
        Softmax temperature ``T > 0``; logits are weighted first, then divided by ``T``.
    offset : float
        Weight of a negative at geodesic distance 0 (the ground-truth vertex itself).
    unseen_full : {"zero", "drop"}
        ``"zero"`` (as in the GeoLoRA code): an unseen full vertex has a zero feature, so a
        negative logit of 0 and, as a positive, a positive logit of 0. ``"drop"``: unseen
        full vertices are no negatives, and partial vertices whose ground truth is unseen
        are no queries.

    Returns
    -------
    torch.Tensor, shape (), float32 (float64 for float64 features)
        Mean over the queries; differentiable with respect to both feature matrices.

    Raises
    ------
    TrainingError
        Bad shapes, dtypes, devices, indices, options or distances, or no query left.
    """
    _check_scalars(temperature, offset)
    batch = _prepare(feat_partial, feat_full, gt_full_index, seen_partial, seen_full, unseen_full)
    _check_geodesic(geodesic_full, feat_full.shape[0])
    weights = _negative_weights(geodesic_full, batch, offset)
    return _info_nce(batch, weights, temperature)


def point_info_nce(
    feat_partial: torch.Tensor,
    feat_full: torch.Tensor,
    gt_full_index: torch.Tensor,
    *,
    seen_partial: torch.Tensor | None = None,
    seen_full: torch.Tensor | None = None,
    temperature: float = DEFAULT_TEMPERATURE,
    unseen_full: UnseenFull = "zero",
) -> torch.Tensor:
    """Plain PointInfoNCE (the ablation): `geodesic_point_info_nce` with every weight 1.

    The logits keep the same layout (the positive, then every full vertex as a negative,
    the ground-truth vertex included), so the two losses differ only in the weights of
    the negative logits. Parameters, return value and errors are those of
    `geodesic_point_info_nce`, without ``geodesic_full`` and ``offset``.

    Returns
    -------
    torch.Tensor, shape (), float32 (float64 for float64 features)
    """
    _check_scalars(temperature, 1.0)
    batch = _prepare(feat_partial, feat_full, gt_full_index, seen_partial, seen_full, unseen_full)
    return _info_nce(batch, None, temperature)


class _Batch(NamedTuple):
    """Queries and keys after masking (``M`` queries, ``K`` keys, ``C`` channels)."""

    query: torch.Tensor  # (M, C) partial features of the queries
    keys: torch.Tensor  # (K, C) full features used as negatives
    positive: torch.Tensor  # (M, C) full features of the ground-truth vertices
    gt: torch.Tensor  # (M,) int64 ground-truth full vertex of each query
    key_index: torch.Tensor | None  # (K,) int64 full vertex of each key; None = all F in order


def _prepare(
    feat_partial: torch.Tensor,
    feat_full: torch.Tensor,
    gt: torch.Tensor,
    seen_partial: torch.Tensor | None,
    seen_full: torch.Tensor | None,
    unseen_full: str,
) -> _Batch:
    """Validate the inputs and keep the queries (seen, matched) and the keys."""
    _check_features(feat_partial, "feat_partial")
    _check_features(feat_full, "feat_full")
    n_p, n_f = feat_partial.shape[0], feat_full.shape[0]
    _check_pair(feat_partial, feat_full)
    _check_index(gt, n_p, n_f, feat_partial.device)
    seen_p = _mask(seen_partial, n_p, "seen_partial", feat_partial.device)
    seen_f = _mask(seen_full, n_f, "seen_full", feat_full.device)
    if unseen_full not in _UNSEEN_FULL:
        raise TrainingError(f"unseen_full must be one of {_UNSEEN_FULL}; found {unseen_full!r}.")
    keep = seen_p & (gt >= 0)
    if unseen_full == "drop":
        keep &= seen_f[gt.clamp(min=0)]
    rows = torch.nonzero(keep).squeeze(1)
    if rows.numel() == 0:
        raise TrainingError(
            "no partial vertex is both seen and matched to a (seen) full vertex: the loss is undefined. "
            "Skip this pair or render more views."
        )
    full = torch.where(seen_f[:, None], feat_full, torch.zeros_like(feat_full))
    gt_kept = gt[rows].long()
    query = feat_partial.index_select(0, rows)
    if unseen_full == "drop":
        key_index = torch.nonzero(seen_f).squeeze(1)
        return _Batch(query, full.index_select(0, key_index), full.index_select(0, gt_kept), gt_kept, key_index)
    return _Batch(query, full, full.index_select(0, gt_kept), gt_kept, None)


def _negative_weights(geodesic: torch.Tensor, batch: _Batch, offset: float) -> torch.Tensor:
    """``offset + d(gt(p), j)`` for every query ``p`` and key ``j``: shape (M, K), no gradient."""
    gt = batch.gt.to(geodesic.device)
    rows = geodesic.detach().index_select(0, gt)
    if batch.key_index is not None:
        rows = rows.index_select(1, batch.key_index.to(geodesic.device))
    if not torch.isfinite(rows).all() or (rows < 0).any():
        raise TrainingError(
            "geodesic_full has infinite, NaN or negative distances in the rows of ground-truth vertices; "
            "expected finite distances >= 0 on a connected full shape (see geofeat.train.geodesics.TorchGeodesicStore)."
        )
    dtype = torch.promote_types(batch.query.dtype, torch.float32)
    return rows.to(device=batch.query.device, dtype=dtype).add_(offset)


def _info_nce(batch: _Batch, weights: torch.Tensor | None, temperature: float) -> torch.Tensor:
    """Cross-entropy with the positive as the target, logits ``[pos, w * neg] / T``; mean over queries."""
    dtype = torch.promote_types(batch.query.dtype, torch.float32)
    query = fn.normalize(batch.query.to(dtype), dim=1) / temperature
    keys = fn.normalize(batch.keys.to(dtype), dim=1)
    positive = fn.normalize(batch.positive.to(dtype), dim=1)
    pos = (query * positive).sum(dim=1)  # (M,)
    neg = query @ keys.T  # (M, K)
    if weights is not None:
        neg = neg * weights
    # log-sum-exp over [pos, neg] without concatenating a (M, K + 1) matrix
    log_denominator = torch.logaddexp(pos, torch.logsumexp(neg, dim=1))
    return (log_denominator - pos).mean()


def _check_features(features: torch.Tensor, name: str) -> None:
    if not isinstance(features, torch.Tensor):
        raise TrainingError(f"{name} must be a torch.Tensor of shape (N, C); found {type(features).__name__}.")
    if features.ndim != 2 or features.shape[1] == 0:
        raise TrainingError(f"{name} must have shape (N, C) with C >= 1; found shape {tuple(features.shape)}.")
    if not features.is_floating_point():
        raise TrainingError(f"{name} must be a floating tensor; found dtype {features.dtype}.")


def _check_pair(feat_partial: torch.Tensor, feat_full: torch.Tensor) -> None:
    if feat_partial.shape[1] != feat_full.shape[1]:
        raise TrainingError(
            f"feat_partial and feat_full must have the same number of channels; "
            f"found {feat_partial.shape[1]} and {feat_full.shape[1]}."
        )
    if feat_full.shape[0] == 0:
        raise TrainingError("feat_full has no vertex (shape (0, C)); the full shape needs at least one.")
    if feat_partial.device != feat_full.device:
        raise TrainingError(
            f"feat_partial is on {feat_partial.device} but feat_full on {feat_full.device}; move both to one device."
        )


def _check_index(gt: torch.Tensor, n_p: int, n_f: int, device: torch.device) -> None:
    if not isinstance(gt, torch.Tensor) or gt.dtype.is_floating_point or gt.dtype.is_complex or gt.dtype == torch.bool:
        found = gt.dtype if isinstance(gt, torch.Tensor) else type(gt).__name__
        raise TrainingError(f"gt_full_index must be an integer torch.Tensor of shape ({n_p},); found {found}.")
    if gt.shape != (n_p,):
        raise TrainingError(f"gt_full_index must have shape ({n_p},) (one entry per partial vertex); found {tuple(gt.shape)}.")
    if gt.device != device:
        raise TrainingError(f"gt_full_index is on {gt.device} but the features on {device}; move it to {device}.")
    if n_p and (int(gt.min()) < -1 or int(gt.max()) >= n_f):
        raise TrainingError(
            f"gt_full_index values must lie in [-1, {n_f - 1}] (-1 = no counterpart); "
            f"found range [{int(gt.min())}, {int(gt.max())}]."
        )


def _mask(mask: torch.Tensor | None, n: int, name: str, device: torch.device) -> torch.Tensor:
    if mask is None:
        return torch.ones(n, dtype=torch.bool, device=device)
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool or mask.shape != (n,):
        found = f"{mask.dtype} {tuple(mask.shape)}" if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise TrainingError(f"{name} must be a bool torch.Tensor of shape ({n},); found {found}.")
    if mask.device != device:
        raise TrainingError(f"{name} is on {mask.device} but the features on {device}; move it to {device}.")
    return mask


def _check_geodesic(geodesic: torch.Tensor, n_f: int) -> None:
    if not isinstance(geodesic, torch.Tensor) or not geodesic.is_floating_point():
        found = geodesic.dtype if isinstance(geodesic, torch.Tensor) else type(geodesic).__name__
        raise TrainingError(f"geodesic_full must be a floating torch.Tensor of shape ({n_f}, {n_f}); found {found}.")
    if geodesic.shape != (n_f, n_f):
        raise TrainingError(
            f"geodesic_full must have shape ({n_f}, {n_f}) (all pairs of full vertices); found {tuple(geodesic.shape)}."
        )


def _check_scalars(temperature: float, offset: float) -> None:
    if not (isinstance(temperature, (int, float)) and np.isfinite(temperature) and temperature > 0):
        raise TrainingError(f"temperature must be a finite number > 0; found {temperature!r}.")
    if not (isinstance(offset, (int, float)) and np.isfinite(offset)):
        raise TrainingError(f"offset must be a finite number; found {offset!r}.")
