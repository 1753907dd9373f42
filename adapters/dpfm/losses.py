"""DPFM's supervision: ground-truth functional maps, the class-weighted overlap loss, the contrastive term.

`geofeat.adapters.dpfm.DPFMHead.training_loss` adds them up.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from geofeat.errors import HeadError

__all__ = ["ground_truth_fmap", "nce_loss", "template_fmap", "weighted_overlap_bce"]


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


def nce_loss(feat_x, feat_y, map_yx: np.ndarray, n_pairs: int, temperature: float, rng: np.random.Generator):
    """InfoNCE over corresponding pairs: each chosen ``x`` feature must pick its own ``y`` feature among all chosen.

    Parameters
    ----------
    feat_x : torch.Tensor, shape (V_x, C)
    feat_y : torch.Tensor, shape (V_y, C)
    map_yx : numpy.ndarray, shape (V_y,), int
        Ground-truth vertex of ``x`` for every vertex of ``y``, -1 for none (skipped).
    n_pairs : int
        Pairs drawn with ``rng`` among the vertices of ``y`` with a counterpart (all of
        them when there are fewer).
    temperature : float
        Divides the negative feature distances before the softmax.
    rng : numpy.random.Generator

    Returns
    -------
    torch.Tensor, shape ()
        Cross-entropy of the distances of the chosen ``x`` features to the chosen ``y`` ones.
    """
    valid = np.flatnonzero(map_yx >= 0)
    chosen = rng.choice(valid, n_pairs, replace=False) if len(valid) > n_pairs else valid
    index_y = torch.as_tensor(chosen, device=feat_y.device)
    index_x = torch.as_tensor(map_yx[chosen], device=feat_x.device)
    query = F.normalize(feat_x[index_x], p=2, dim=-1)
    keys = F.normalize(feat_y[index_y], p=2, dim=-1)
    logits = -torch.cdist(query, keys) / temperature
    return F.cross_entropy(logits, torch.arange(len(chosen), device=logits.device))
