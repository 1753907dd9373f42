"""Evaluation metrics for shape correspondence: geodesic error, PCK, overlap IoU, chirality.

Every function takes explicit arrays. Point maps follow the in-memory convention of
`geofeat.datasets.ShapePair`: ``map_yx[i]`` is the 0-based vertex of the target ``x`` matched
to vertex ``i`` of the source ``y``, ``-1`` for "no counterpart". Geodesic distance
matrices are on the target ``x`` and already normalised the way the protocol wants
(usually divided by the square root of the surface area of ``x``); these functions do no
normalisation of their own.

Conventions, as in the published evaluations (ULRSSM ``metrics/geodist_metric.py``, DPFM and
its re-implementation ``models/partial_base_model.py``):

* the geodesic error of a vertex is ``dist_x[gt, pred]``; the mean is taken over all evaluated
  vertices of all pairs pooled together (not a mean of per-pair means) and reported x100;
* the PCK curve counts errors ``<=`` each threshold and its area is normalised by the
  threshold range, so a perfect map has area 1;
* mIoU is the mean over pairs of the per-pair IoU of boolean overlap masks.

Where the target is too large for its (V_x, V_x) matrix, ``dist_x`` may instead be a
`DistanceEntries`: an object that gives only the entries read (``dist_x[rows, cols]``) and the
worst case of some rows (`geofeat.geometry.geodesic_memory.GeodesicEntries`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from typing import Protocol, runtime_checkable

import numpy as np

from geofeat.errors import MetricError

log = logging.getLogger(__name__)


#: Default PCK thresholds (normalised geodesic distance): 0 to 0.25 in steps of 0.0025.
DEFAULT_PCK_THRESHOLDS = np.linspace(0.0, 0.25, 101)
#: Policies for a prediction of -1 where the ground truth has a counterpart.
UNMATCHED_POLICIES = ("max", "raise")


@runtime_checkable
class DistanceEntries(Protocol):
    """Some entries of a (V, V) distance matrix, read without the matrix (the metrics accept it as ``dist_x``).

    Attributes
    ----------
    shape : tuple of int
        ``(V, V)``.
    """

    shape: tuple[int, int]

    def __getitem__(self, key: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """``dist[rows, cols]``: the entries at integer arrays of one shape, an array of that shape."""

    def worst_case(self, rows: np.ndarray) -> np.ndarray:
        """Largest finite distance from each of ``rows`` (0 where none), shape (len(rows),) float64."""


# ----------------------------------------------------------------------------- validation


def _as_index_map(values, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise MetricError(f"{name} must be a 1-D array of vertex indices, shape (V_y,); found shape {arr.shape}.")
    if arr.size and arr.dtype.kind not in "iu":
        raise MetricError(f"{name} must hold integer vertex indices; found dtype {arr.dtype}. Convert with .astype(np.int64).")
    return arr.astype(np.int64, copy=False)


def _check_range(arr: np.ndarray, n_x: int, name: str) -> None:
    if arr.size and (arr.min() < -1 or arr.max() >= n_x):
        raise MetricError(
            f"{name} must hold 0-based indices into the target in [0, {n_x - 1}], or -1 for 'no counterpart'; "
            f"found range [{arr.min()}, {arr.max()}]. 1-based indices? Subtract 1."
        )


def _as_distance_matrix(dist_x) -> np.ndarray | DistanceEntries:
    if isinstance(dist_x, DistanceEntries) and not isinstance(dist_x, np.ndarray):
        if len(dist_x.shape) != 2 or dist_x.shape[0] != dist_x.shape[1]:
            raise MetricError(f"dist_x must stand for a square (V_x, V_x) matrix; found shape {dist_x.shape}.")
        return dist_x
    arr = np.asarray(dist_x)
    if arr.ndim != 2 or arr.shape[0] != arr.shape[1]:
        raise MetricError(
            f"dist_x must be a square (V_x, V_x) matrix of geodesic distances on the target; found shape {arr.shape}."
        )
    if arr.dtype.kind not in "fiu":
        raise MetricError(f"dist_x must be a real numeric matrix; found dtype {arr.dtype}.")
    return arr


def _as_mask(mask, n: int, name: str) -> np.ndarray:
    arr = np.asarray(mask)
    if arr.dtype != bool:
        raise MetricError(
            f"{name} must be a boolean array; found dtype {arr.dtype}. Threshold scores first (for example score > 0.5)."
        )
    if arr.shape != (n,):
        raise MetricError(f"{name} must have shape ({n},); found shape {arr.shape}.")
    return arr


def _maps_and_distances(map_pred_yx, map_gt_yx, dist_x) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dist = _as_distance_matrix(dist_x)
    pred = _as_index_map(map_pred_yx, "map_pred_yx")
    gt = _as_index_map(map_gt_yx, "map_gt_yx")
    if pred.shape != gt.shape:
        raise MetricError(f"map_pred_yx and map_gt_yx must both have shape (V_y,); found {pred.shape} and {gt.shape}.")
    _check_range(pred, dist.shape[0], "map_pred_yx")
    _check_range(gt, dist.shape[0], "map_gt_yx")
    return pred, gt, dist


def _evaluated(gt: np.ndarray, eval_mask) -> np.ndarray:
    keep = gt >= 0
    if eval_mask is not None:
        keep &= _as_mask(eval_mask, gt.shape[0], "eval_mask")
    return keep


# ----------------------------------------------------------------------------- geodesic error


def geodesic_errors(map_pred_yx, map_gt_yx, dist_x, eval_mask=None, unmatched: str = "max") -> np.ndarray:
    """Geodesic error of every evaluated vertex of the source shape.

    Parameters
    ----------
    map_pred_yx : array_like of int, shape (V_y,)
        Predicted map, 0-based indices into the target, ``-1`` where nothing was predicted.
    map_gt_yx : array_like of int, shape (V_y,)
        Ground-truth map, ``-1`` where the vertex has no counterpart (not evaluated).
    dist_x : array_like, shape (V_x, V_x), or DistanceEntries
        Geodesic distances on the target, already normalised (for example by
        ``sqrt(area(x))``).
    eval_mask : array_like of bool, shape (V_y,), optional
        Evaluate only these vertices (and only where the ground truth exists).
    unmatched : {"max", "raise"}
        What a prediction of ``-1`` on an evaluated vertex counts as. ``"max"`` (default):
        the worst error possible at that vertex, the largest finite distance from its true
        counterpart (a missing match is never better than any match, and is not dropped);
        ``"raise"``: raise `MetricError`.

    Returns
    -------
    numpy.ndarray, shape (n_eval,), float64
        ``dist_x[gt[i], pred[i]]`` for the evaluated vertices ``i`` in increasing order, in
        the units of ``dist_x``. Non-finite distances (a prediction in another connected
        component) are replaced by the same worst-case value as an unmatched vertex, with
        a logged warning. Empty when no vertex is evaluated.
    """
    if unmatched not in UNMATCHED_POLICIES:
        raise MetricError(f"unmatched must be one of {UNMATCHED_POLICIES}; found {unmatched!r}.")
    pred, gt, dist = _maps_and_distances(map_pred_yx, map_gt_yx, dist_x)
    keep = _evaluated(gt, eval_mask)
    pred, gt = pred[keep], gt[keep]
    missing = pred < 0
    if missing.any() and unmatched == "raise":
        raise MetricError(
            f"{int(missing.sum())} evaluated vertex(es) have no predicted match (-1), first at evaluated position "
            f"{np.flatnonzero(missing)[:5].tolist()}; predict a full map or pass unmatched='max'."
        )
    errors = dist[gt, np.where(missing, 0, pred)].astype(np.float64)
    bad = missing | ~np.isfinite(errors)
    if bad.any():
        n_infinite = int((bad & ~missing).sum())
        if n_infinite:
            log.warning("%d geodesic error(s) are not finite (match in another component); counted as the worst case", n_infinite)
        errors[bad] = _worst_case(dist, gt[bad])
    return errors


def at_template_points(map_pred_yx, corr_y) -> np.ndarray:
    """The predicted map read at the template points of ``y``.

    Parameters
    ----------
    map_pred_yx : array_like of int, shape (V_y,)
        Predicted map, ``-1`` where nothing was predicted.
    corr_y : array_like of int, shape (T,)
        Vertex of ``y`` at each template point, ``-1`` where none.

    Returns
    -------
    numpy.ndarray, shape (T,), int64
        ``map_pred_yx[corr_y[t]]``, ``-1`` where ``corr_y[t]`` is ``-1``.
    """
    pred = _as_index_map(map_pred_yx, "map_pred_yx")
    corr_y = _as_index_map(corr_y, "corr_y")
    _check_range(corr_y, pred.size, "corr_y")
    return np.where(corr_y >= 0, pred[np.maximum(corr_y, 0)], -1)


def template_geodesic_errors(map_pred_yx, corr_x, corr_y, dist_x, unmatched: str = "max") -> np.ndarray:
    """Geodesic error at every template point: the protocol of the ULRSSM and DPFM references on FAUST_r / SCAPE_r.

    Parameters
    ----------
    map_pred_yx : array_like of int, shape (V_y,)
        Predicted map.
    corr_x, corr_y : array_like of int, shape (T,)
        Vertex of ``x`` and of ``y`` at each template point (``-1``: none; such points are
        not evaluated).
    dist_x : array_like, shape (V_x, V_x)
        Geodesic distances on ``x`` (the references: Dijkstra on the edge graph of the
        unit-area shape, i.e. ``geodesic_matrix(x, "dijkstra", normalize=True)``).
    unmatched : {"max", "raise"}
        See `geodesic_errors`.

    Returns
    -------
    numpy.ndarray, shape (n_eval,), float64
        ``dist_x[corr_x[t], map_pred_yx[corr_y[t]]]`` for the evaluated template points.
        A vertex hit by several template points counts once per point, and vertices hit by
        none are not evaluated: unlike `geodesic_errors`, which evaluates every vertex of
        ``y`` that has a counterpart once.
    """
    gt = _as_index_map(corr_x, "corr_x")
    pred = at_template_points(map_pred_yx, corr_y)
    if gt.shape != pred.shape:
        raise MetricError(f"corr_x and corr_y must have the same shape (T,); found {gt.shape} and {pred.shape}.")
    gt = np.where(_as_index_map(corr_y, "corr_y") >= 0, gt, -1)
    return geodesic_errors(pred, gt, dist_x, unmatched=unmatched)


def _worst_case(dist: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Largest finite distance from each source vertex, shape (len(sources),) float64."""
    if isinstance(dist, DistanceEntries) and not isinstance(dist, np.ndarray):
        return np.asarray(dist.worst_case(sources), dtype=np.float64)
    rows = np.asarray(dist[sources], dtype=np.float64)
    return np.where(np.isfinite(rows), rows, -np.inf).max(axis=1).clip(min=0.0)


def _pooled(errors) -> np.ndarray:
    """One float64 vector from an array or a sequence of per-pair arrays."""
    if isinstance(errors, np.ndarray):
        parts = [errors]
    elif isinstance(errors, Iterable) and not isinstance(errors, (str, bytes)):
        parts = [np.asarray(e) for e in errors]
    else:
        raise MetricError(f"errors must be an array or a sequence of per-pair arrays; found {type(errors).__name__}.")
    for part in parts:
        if part.ndim != 1 or part.dtype.kind not in "fiu":
            raise MetricError(
                f"every error array must be 1-D and numeric, shape (n_eval,); found shape {part.shape}, dtype {part.dtype}."
            )
    pooled = np.concatenate(parts).astype(np.float64) if parts else np.zeros(0)
    if pooled.size == 0:
        raise MetricError("no evaluated vertices: every error array is empty.")
    if np.isnan(pooled).any():
        raise MetricError("errors contain NaN; compute them with geodesic_errors, which never returns NaN.")
    return pooled


def mean_geodesic_error(errors, scale: float = 100.0) -> float:
    """Mean geodesic error pooled over all evaluated vertices of all pairs, as published tables report it.

    Parameters
    ----------
    errors : array_like or sequence of array_like
        One `geodesic_errors` vector, shape (n_eval,), or a sequence of them (one per pair,
        of any lengths). They are concatenated before averaging, so pairs with more
        evaluated vertices weigh more (this is not the mean of per-pair means).
    scale : float
        Multiplier of the result (100 reports the error x100, the published convention).

    Returns
    -------
    float
    """
    return float(_pooled(errors).mean() * scale)


# ----------------------------------------------------------------------------- PCK


def _as_thresholds(thresholds) -> np.ndarray:
    arr = DEFAULT_PCK_THRESHOLDS if thresholds is None else np.asarray(thresholds, dtype=np.float64)
    if arr.ndim != 1 or arr.size < 2:
        raise MetricError(f"thresholds must be a 1-D array of at least two values; found shape {arr.shape}.")
    if not np.all(np.diff(arr) > 0) or not np.isfinite(arr).all():
        raise MetricError("thresholds must be finite and strictly increasing.")
    return arr


def pck_curve(errors, thresholds=None) -> tuple[np.ndarray, np.ndarray]:
    """Percentage of correct keypoints: the fraction of errors within each threshold.

    Parameters
    ----------
    errors : array_like or sequence of array_like
        Geodesic errors (same units as the thresholds), one vector or one per pair (pooled).
    thresholds : array_like, shape (T,), optional
        Strictly increasing thresholds; default `DEFAULT_PCK_THRESHOLDS` (0 to 0.25, 101 values).

    Returns
    -------
    thresholds : numpy.ndarray, shape (T,), float64
    fractions : numpy.ndarray, shape (T,), float64
        ``mean(errors <= t)`` for each threshold ``t``, in [0, 1], non-decreasing.
    """
    pooled = np.sort(_pooled(errors))
    grid = _as_thresholds(thresholds)
    fractions = np.searchsorted(pooled, grid, side="right") / pooled.size
    return grid, fractions


def pck_auc(errors, thresholds=None) -> float:
    """Area under the PCK curve normalised by the threshold range, in [0, 1].

    Parameters
    ----------
    errors, thresholds
        As for `pck_curve`.

    Returns
    -------
    float
        Trapezoidal area of the curve divided by ``thresholds[-1] - thresholds[0]``; 1 for a
        perfect map. On evenly spaced thresholds this equals ULRSSM's AUC.
    """
    grid, fractions = pck_curve(errors, thresholds)
    area = np.sum(0.5 * (fractions[1:] + fractions[:-1]) * np.diff(grid))
    return float(area / (grid[-1] - grid[0]))


# ----------------------------------------------------------------------------- overlap


def overlap_iou(pred_mask, gt_mask) -> float:
    """Intersection over union of a predicted and a ground-truth overlap mask.

    Parameters
    ----------
    pred_mask, gt_mask : array_like of bool, shape (V,)
        Which vertices lie in the overlap region (threshold predicted scores first,
        usually at 0.5).

    Returns
    -------
    float
        ``|pred & gt| / |pred | gt|`` in [0, 1]; 1 when both masks are empty (they agree).
    """
    gt = np.asarray(gt_mask)
    if gt.ndim != 1:
        raise MetricError(f"gt_mask must be a 1-D boolean array, shape (V,); found shape {gt.shape}.")
    gt = _as_mask(gt, gt.shape[0], "gt_mask")
    pred = _as_mask(pred_mask, gt.shape[0], "pred_mask")
    union = np.count_nonzero(pred | gt)
    return 1.0 if union == 0 else np.count_nonzero(pred & gt) / union


def mean_iou(pairs: Iterable[tuple]) -> float:
    """Mean over pairs of `overlap_iou` (each pair counts once, whatever its size).

    Parameters
    ----------
    pairs : iterable of (pred_mask, gt_mask)
        Boolean masks, shape (V_i,) each.

    Returns
    -------
    float
    """
    ious = [overlap_iou(pred, gt) for pred, gt in pairs]
    if not ious:
        raise MetricError("mean_iou needs at least one (pred_mask, gt_mask) pair; found none.")
    return float(np.mean(ious))


# ----------------------------------------------------------------------------- chirality


def chirality_accuracy(map_pred_yx, map_gt_yx, map_gt_sym_yx, dist_x, eval_mask=None) -> float:
    """Fraction of vertices matched on the correct side of a left-right symmetric shape.

    A vertex is on the correct side when its predicted match lies geodesically closer to
    its true counterpart than to the mirror image of that counterpart.

    Parameters
    ----------
    map_pred_yx : array_like of int, shape (V_y,)
        Predicted map, ``-1`` where nothing was predicted.
    map_gt_yx : array_like of int, shape (V_y,)
        Ground truth, ``-1`` where undefined.
    map_gt_sym_yx : array_like of int, shape (V_y,)
        Mirror image of the true counterpart, ``-1`` where undefined.
    dist_x : array_like, shape (V_x, V_x)
        Geodesic distances on the target (any normalisation: only comparisons are made).
    eval_mask : array_like of bool, shape (V_y,), optional
        Evaluate only these vertices.

    Returns
    -------
    float
        In [0, 1]. Evaluated vertices: both ground truths defined, different from each other
        (vertices on the symmetry plane, whose counterpart is its own mirror image, have no
        side and are skipped) and inside ``eval_mask``. Each scores 1 when
        ``d(pred, gt) < d(pred, sym)``, 0 when greater, 1/2 on an exact tie (so a map with
        no side preference scores about 1/2), and 0 when the prediction is ``-1``.
    """
    pred, gt, dist = _maps_and_distances(map_pred_yx, map_gt_yx, dist_x)
    sym = _as_index_map(map_gt_sym_yx, "map_gt_sym_yx")
    if sym.shape != gt.shape:
        raise MetricError(f"map_gt_sym_yx must have the shape of map_gt_yx, {gt.shape}; found {sym.shape}.")
    _check_range(sym, dist.shape[0], "map_gt_sym_yx")
    keep = _evaluated(gt, eval_mask) & (sym >= 0) & (sym != gt)
    if not keep.any():
        raise MetricError("no vertex has both a counterpart and a distinct mirror counterpart: chirality is undefined.")
    pred, gt, sym = pred[keep], gt[keep], sym[keep]
    safe = np.where(pred < 0, 0, pred)
    to_true, to_mirror = dist[gt, safe], dist[sym, safe]
    scores = np.where(to_true < to_mirror, 1.0, np.where(to_true > to_mirror, 0.0, 0.5))
    scores[pred < 0] = 0.0
    return float(scores.mean())


def overlap_auc(scores, gt_mask) -> float | None:
    """Area under the ROC curve of predicted overlap scores against a ground-truth mask.

    The probability that a random overlapping vertex scores higher than a random
    non-overlapping one (ties count half): 1 is a perfect ranking, 0.5 chance. It does not
    depend on a threshold, unlike `overlap_iou`.

    Parameters
    ----------
    scores : array_like of float, shape (V,)
        Predicted overlap probabilities (or any increasing score).
    gt_mask : array_like of bool, shape (V,)

    Returns
    -------
    float or None
        None when the ground truth holds one class only (the ranking is undefined).
    """
    gt = np.asarray(gt_mask)
    if gt.ndim != 1:
        raise MetricError(f"gt_mask must be a 1-D boolean array, shape (V,); found shape {gt.shape}.")
    gt = _as_mask(gt, gt.shape[0], "gt_mask")
    values = np.asarray(scores, dtype=np.float64)
    if values.shape != gt.shape or not np.isfinite(values).all():
        raise MetricError(f"scores must be finite numbers of shape {gt.shape}; found shape {values.shape}.")
    n_pos = int(gt.sum())
    n_neg = gt.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return None
    from scipy.stats import rankdata  # imported here: scipy.stats takes a second or two to import

    ranks = rankdata(values)  # average ranks: ties count half
    return float((ranks[gt].sum() - n_pos * (n_pos + 1) / 2) / (n_pos * n_neg))
