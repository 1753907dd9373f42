"""EchoMatch's losses: class-balanced overlap BCE, cross- and self-NCE, and the regularised ground-truth functional map."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from geofeat.adapters.blocks.fmap_layers import resolvent_mask
from geofeat.errors import HeadError


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


def regularized_gt_fmap(
    map_yx,
    evecs_x: torch.Tensor,
    evecs_y: torch.Tensor,
    evals_x: torch.Tensor,
    evals_y: torch.Tensor,
    lambda_: float,
    gamma: float = 0.5,
    mass_y: torch.Tensor | None = None,
) -> torch.Tensor:
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
