"""Differentiable (torch) functional-map layers for learned matching heads: regularised maps and soft point maps.

Convention (that of `geofeat.adapters.blocks.functional_maps`): a functional map ``C`` has shape
``(k_y, k_x)`` and pulls functions back from ``x`` to ``y``, ``coeffs_y = C @ coeffs_x``;
it is the matrix of a point map y -> x, ``C = Phi_y^T M_y P_yx Phi_x``, where ``P_yx``
(V_y, V_x) has one row per vertex of ``y`` (rows of a soft map sum to one). ULRSSM calls
this matrix ``Cxy`` and its soft point map ``Pyx``. A map in the other direction,
``C_yx`` (k_x, k_y), pulls functions back from ``y`` to ``x``.

Every function takes torch tensors (array_likes are converted) and accepts an optional
leading batch dimension ``B``: when an input has it, the result has it, and inputs without
it are shared by every batch element. Computations use the floating dtype and device of the
first feature or map argument; spectral data are converted to them. Eigenvalues are treated
as constants (no gradient flows to them through the Laplacian mask).

The losses built on these layers are `geofeat.adapters.blocks.fmap_losses`; the conversion
and checks of the inputs are `geofeat.adapters.blocks.fmap_inputs`.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from geofeat.adapters.blocks.fmap_inputs import (
    batch_inputs,
    check_basis,
    check_dim,
    dtype_device,
    positive,
    to_tensor,
    unbatch,
)
from geofeat.adapters.blocks.functional_maps import MASK_KINDS, laplacian_mask
from geofeat.errors import FunctionalMapError

__all__ = [
    "RegularizedFMap",
    "fmap_to_pointmap_soft",
    "pointmap_to_fmap",
    "regularized_fmap",
    "resolvent_mask",
    "soft_pointmap",
    "soft_pointmaps",
]


# ----------------------------------------------------------------------------- regularised functional map


def resolvent_mask(evals_x, evals_y, gamma: float = 0.5, kind: str = "resolvent") -> torch.Tensor:
    """Laplacian commutativity weights ``W`` (k_y, k_x) of `regularized_fmap`, as a tensor.

    The torch face of `geofeat.adapters.blocks.functional_maps.laplacian_mask`. For
    ``kind="resolvent"`` (DPFM's and ULRSSM's ``get_mask``): both spectra are divided by
    their common largest eigenvalue, raised to ``gamma`` (``t = lambda^gamma``), and
    ``W_ij = |r(mu_i) - r(lambda_j)|^2`` with ``r(t) = 1 / (t - i)``, i.e.
    ``Re r = t / (t^2 + 1)`` and ``Im r = 1 / (t^2 + 1)``; ``mu`` are the eigenvalues of
    ``y`` (rows), ``lambda`` those of ``x`` (columns). Absolute values are taken first, so a
    slightly negative first eigenvalue is harmless.

    Parameters
    ----------
    evals_x : array_like, shape (k_x,) or (B, k_x)
    evals_y : array_like, shape (k_y,) or (B, k_y)
    gamma : float
        Resolvent exponent in (0, 1].
    kind : {"resolvent", "squared"}
        ``"squared"``: ``(mu_i - lambda_j)^2`` on the raw eigenvalues.

    Returns
    -------
    torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
        Constant (no gradient); dtype and device of ``evals_x`` (float64 for arrays).
    """
    dtype, device = dtype_device(evals_x)
    if kind not in MASK_KINDS:
        raise FunctionalMapError(f"mask kind must be one of {MASK_KINDS}; found {kind!r}.")
    t, batched = batch_inputs({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    ex, ey = t["evals_x"].detach().numpy(), t["evals_y"].detach().numpy()
    masks = np.stack([laplacian_mask(ex[b], ey[b], kind=kind, gamma=gamma) for b in range(ex.shape[0])])
    return unbatch(torch.as_tensor(masks, dtype=dtype, device=device), batched)


def _solve_fmap(a: torch.Tensor, b: torch.Tensor, weights: torch.Tensor, lambda_: float) -> torch.Tensor:
    """Row-wise closed form ``C_i (A A^T + lambda diag(W_i)) = B_i A^T``.

    Parameters
    ----------
    a : torch.Tensor, shape (B, k_x, p)
    b : torch.Tensor, shape (B, k_y, p)
    weights : torch.Tensor, shape (B, k_y, k_x)
        On the device of ``a``; already checked by `_check_not_singular`.
    lambda_ : float

    Returns
    -------
    torch.Tensor, shape (B, k_y, k_x)

    Notes
    -----
    A system that the solver finds singular raises `FunctionalMapError`, except on a GPU
    while gradients are recorded (a training step), where reading the solver's report would
    wait for the device: a system singular only up to rounding (the singular-by-construction
    ones are caught before) then gives non-finite entries, and the training loop refuses
    the non-finite loss they lead to (`geofeat.adapters.learned.LearnedHead.fit`).
    """
    gram = a @ a.transpose(1, 2)  # (B, k_x, k_x)
    rhs = b @ a.transpose(1, 2)  # (B, k_y, k_x)
    systems = gram.unsqueeze(1) + lambda_ * torch.diag_embed(weights)  # (B, k_y, k_x, k_x), symmetric
    solution, info = torch.linalg.solve_ex(systems, rhs.unsqueeze(-1))
    if (solution.device.type == "cpu" or not torch.is_grad_enabled()) and bool(info.any()):
        raise FunctionalMapError(
            f"the functional map system is singular (the solver found {int((info > 0).sum())} singular row system(s)): "
            "the features do not determine C. Use more feature channels, fewer basis functions or a positive lambda_."
        )
    return solution.squeeze(-1)


def _check_not_singular(weights: torch.Tensor, lambda_: float, n_channels: int) -> None:
    """Raise `FunctionalMapError` when a row system is singular by construction.

    Row ``i`` solves with ``A A^T + lambda diag(W_i)``, with ``A`` (k_x, p) of rank at most
    p. Where ``lambda W_i`` is zero, only ``A A^T`` acts, so the system is singular as soon as
    more such coordinates than feature channels remain (``#{j : lambda W_ij = 0} > p``). This
    is decided from the shapes and the mask, not from whether a particular LAPACK kernel
    happens to raise on a matrix that is singular only up to rounding; other numerically
    singular systems are left to the solver.

    Parameters
    ----------
    weights : torch.Tensor, shape (B, k_y, k_x)
        The Laplacian mask, on the CPU (read here without waiting for a device).
    lambda_ : float
    n_channels : int
        Feature channels p.
    """
    free = (lambda_ * weights <= 0).sum(dim=-1)  # (B, k_y): coordinates without regularisation
    bad = free > n_channels
    if bool(bad.any()):
        rows = torch.nonzero(bad)[:, -1].unique().tolist()
        raise FunctionalMapError(
            f"the functional map system is singular for {len(rows)} row(s) of C (first {rows[:5]}): "
            f"{int(free.max())} of the {weights.shape[-1]} basis coefficients are unregularised but the features have only "
            f"{n_channels} channel(s), so they do not determine C. "
            "Use more feature channels, fewer basis functions or a positive lambda_."
        )


def regularized_fmap(
    feat_x,
    feat_y,
    evecs_x,
    evecs_y,
    mass_x,
    mass_y,
    evals_x,
    evals_y,
    lambda_: float = 100.0,
    gamma: float = 0.5,
    mask: str = "resolvent",
    bidirectional: bool = False,
) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """Functional map from features by regularised least squares, solved row by row in closed form.

    Minimises, over ``C`` of shape (k_y, k_x), ``||C A - B||_F^2 + lambda_ sum_ij W_ij C_ij^2``
    with ``A = Phi_x^T M_x feat_x`` (k_x, p), ``B = Phi_y^T M_y feat_y`` (k_y, p) and ``W`` the
    Laplacian mask (`resolvent_mask`). The problem splits into one ridge regression per row:
    ``C_i = B_i A^T (A A^T + lambda_ diag(W_i))^-1``, the layer ``RegularizedFMNet`` of DPFM
    and ULRSSM (there ``Cxy``), and the torch twin of
    `geofeat.adapters.blocks.functional_maps.fmap_from_descriptors` with ``descr_weight=1``,
    ``lap_weight=lambda_`` and ``normalize_descriptors=False``. Differentiable with respect
    to the features (and the bases); the eigenvalues are constants.

    Parameters
    ----------
    feat_x : torch.Tensor, shape (V_x, p) or (B, V_x, p)
        Features of the target ``x``.
    feat_y : torch.Tensor, shape (V_y, p) or (B, V_y, p)
        Features of the source ``y`` (same channels).
    evecs_x : array_like, shape (V_x, k_x) or (B, V_x, k_x)
        Mass-orthonormal eigenvectors of ``x`` (pass ``evecs[:, :k]`` to use ``k``).
    evecs_y : array_like, shape (V_y, k_y) or (B, V_y, k_y)
    mass_x : array_like, shape (V_x,) or (B, V_x)
        Lumped vertex areas of ``x``.
    mass_y : array_like, shape (V_y,) or (B, V_y)
    evals_x : array_like, shape (k_x,) or (B, k_x)
        Eigenvalues of ``x``, matching the columns of ``evecs_x``. They are read on the
        host (the mask is built there): CPU tensors or arrays spare a copy from the device,
        which would wait for it.
    evals_y : array_like, shape (k_y,) or (B, k_y)
    lambda_ : float
        Weight of the Laplacian term (ULRSSM's default 100; DPFM's code defaults to 1e-3).
        It trades off against the scale of the features: the descriptor term grows with
        their norm, the resolvent mask lies in [0, 1).
    gamma : float
        Resolvent exponent in (0, 1].
    mask : {"resolvent", "squared"}
        Laplacian penalty, see `resolvent_mask`.
    bidirectional : bool
        Also return ``C_yx`` (k_x, k_y), the same solve with the roles of ``x`` and ``y``
        swapped (ULRSSM's ``bidirectional=True``), which `fmap_bijectivity_loss` needs.

    Returns
    -------
    C_xy : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
        ``coeffs_y = C_xy @ coeffs_x``: pulls functions back from ``x`` to ``y``.
    C_yx : torch.Tensor, shape (k_x, k_y) or (B, k_x, k_y)
        Only if ``bidirectional``: ``coeffs_x = C_yx @ coeffs_y``.
    """
    lambda_ = positive(lambda_, "lambda_", allow_zero=True)
    dtype, device = dtype_device(feat_x)
    t, batched = batch_inputs(
        {
            "feat_x": (feat_x, 2),
            "feat_y": (feat_y, 2),
            "evecs_x": (evecs_x, 2),
            "evecs_y": (evecs_y, 2),
            "mass_x": (mass_x, 1),
            "mass_y": (mass_y, 1),
            "evals_x": (evals_x, 1),
            "evals_y": (evals_y, 1),
        },
        dtype,
        device,
        host=("evals_x", "evals_y"),
    )
    fx, fy = t["feat_x"], t["feat_y"]
    if fx.shape[2] != fy.shape[2]:
        raise FunctionalMapError(
            f"feat_x and feat_y must have the same number of channels; found {fx.shape[2]} and {fy.shape[2]}."
        )
    check_basis(t["evecs_x"], t["mass_x"], t["evals_x"], fx.shape[1], "x")
    check_basis(t["evecs_y"], t["mass_y"], t["evals_y"], fy.shape[1], "y")
    host_weights = resolvent_mask(t["evals_x"], t["evals_y"], gamma=gamma, kind=mask)  # (B, k_y, k_x), on the CPU
    _check_not_singular(host_weights, lambda_, fx.shape[2])
    if bidirectional:
        _check_not_singular(host_weights.transpose(1, 2), lambda_, fx.shape[2])
    weights = host_weights.to(device)
    a = t["evecs_x"].transpose(1, 2) @ (t["mass_x"].unsqueeze(-1) * fx)  # (B, k_x, p)
    b = t["evecs_y"].transpose(1, 2) @ (t["mass_y"].unsqueeze(-1) * fy)  # (B, k_y, p)
    c_xy = unbatch(_solve_fmap(a, b, weights, lambda_), batched)
    if not bidirectional:
        return c_xy
    c_yx = _solve_fmap(b, a, weights.transpose(1, 2), lambda_)
    return c_xy, unbatch(c_yx, batched)


class RegularizedFMap(nn.Module):
    """`regularized_fmap` as a module (no parameters), for heads built from ``nn.Module`` parts.

    Parameters
    ----------
    lambda_, gamma, mask, bidirectional
        As in `regularized_fmap`.
    """

    def __init__(self, lambda_: float = 100.0, gamma: float = 0.5, mask: str = "resolvent", bidirectional: bool = False):
        super().__init__()
        self.lambda_ = positive(lambda_, "lambda_", allow_zero=True)
        if mask not in MASK_KINDS:
            raise FunctionalMapError(f"mask must be one of {MASK_KINDS}; found {mask!r}.")
        self.gamma, self.mask, self.bidirectional = gamma, mask, bidirectional

    def forward(self, feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y):
        """Return ``C_xy`` (k_y, k_x), or ``(C_xy, C_yx)`` if ``bidirectional``; see `regularized_fmap`."""
        return regularized_fmap(
            feat_x,
            feat_y,
            evecs_x,
            evecs_y,
            mass_x,
            mass_y,
            evals_x,
            evals_y,
            lambda_=self.lambda_,
            gamma=self.gamma,
            mask=self.mask,
            bidirectional=self.bidirectional,
        )

    def extra_repr(self) -> str:
        return f"lambda_={self.lambda_}, gamma={self.gamma}, mask={self.mask!r}, bidirectional={self.bidirectional}"


# ----------------------------------------------------------------------------- soft point maps


def soft_pointmap(feat_x, feat_y, temperature: float = 0.07, normalize: bool = True) -> torch.Tensor:
    """Soft point map y -> x: row-wise softmax of feature similarities divided by a temperature.

    ``P_yx[v, u] = softmax_u(<feat_y[v], feat_x[u]> / temperature)``, ULRSSM's ``Pyx`` (its
    ``Similarity`` module, ``tau = 0.07`` in its configurations). Swap the arguments for
    ``P_xy``.

    Parameters
    ----------
    feat_x : torch.Tensor, shape (V_x, p) or (B, V_x, p)
    feat_y : torch.Tensor, shape (V_y, p) or (B, V_y, p)
    temperature : float
        > 0; lower is sharper.
    normalize : bool
        L2-normalise every feature vector first, so similarities are cosines in [-1, 1].

    Returns
    -------
    torch.Tensor, shape (V_y, V_x) or (B, V_y, V_x)
        Non-negative, rows sum to one. Dense: memory grows as ``V_y * V_x``.
    """
    temperature = positive(temperature, "temperature")
    dtype, device = dtype_device(feat_x)
    t, batched = batch_inputs({"feat_x": (feat_x, 2), "feat_y": (feat_y, 2)}, dtype, device)
    fx, fy = t["feat_x"], t["feat_y"]
    if fx.shape[2] != fy.shape[2]:
        raise FunctionalMapError(
            f"feat_x and feat_y must have the same number of channels; found {fx.shape[2]} and {fy.shape[2]}."
        )
    if normalize:
        fx, fy = F.normalize(fx, p=2, dim=-1), F.normalize(fy, p=2, dim=-1)
    similarity = fy @ fx.transpose(1, 2)  # (B, V_y, V_x)
    return unbatch(torch.softmax(similarity / temperature, dim=-1), batched)


def soft_pointmaps(feat_x, feat_y, temperature: float = 0.07, normalize: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """Both soft point maps ``P_yx`` and ``P_xy`` of `soft_pointmap`, from one similarity matrix.

    ``P_xy`` is the row-wise softmax of the transposed similarities of ``P_yx`` (as
    ULRSSM's code computes it): one product of the features instead of two, forward and
    backward. Equal to two calls of `soft_pointmap` up to rounding.

    Parameters
    ----------
    feat_x : torch.Tensor, shape (V_x, p) or (B, V_x, p)
    feat_y : torch.Tensor, shape (V_y, p) or (B, V_y, p)
    temperature : float
        > 0; lower is sharper.
    normalize : bool
        L2-normalise every feature vector first, so similarities are cosines in [-1, 1].

    Returns
    -------
    P_yx : torch.Tensor, shape (V_y, V_x) or (B, V_y, V_x)
        Soft map y -> x, rows sum to one.
    P_xy : torch.Tensor, shape (V_x, V_y) or (B, V_x, V_y)
        Soft map x -> y, rows sum to one.
    """
    temperature = positive(temperature, "temperature")
    dtype, device = dtype_device(feat_x)
    t, batched = batch_inputs({"feat_x": (feat_x, 2), "feat_y": (feat_y, 2)}, dtype, device)
    fx, fy = t["feat_x"], t["feat_y"]
    if fx.shape[2] != fy.shape[2]:
        raise FunctionalMapError(
            f"feat_x and feat_y must have the same number of channels; found {fx.shape[2]} and {fy.shape[2]}."
        )
    if normalize:
        fx, fy = F.normalize(fx, p=2, dim=-1), F.normalize(fy, p=2, dim=-1)
    similarity = fy @ fx.transpose(1, 2)  # (B, V_y, V_x)
    p_yx = torch.softmax(similarity / temperature, dim=-1)
    p_xy = torch.softmax(similarity.transpose(1, 2) / temperature, dim=-1)  # (B, V_x, V_y)
    return unbatch(p_yx, batched), unbatch(p_xy, batched)


def pointmap_to_fmap(P, evecs_x, evecs_y, mass_y) -> torch.Tensor:
    """Functional map of a (soft) point map y -> x: ``C = Phi_y^+ P Phi_x`` with ``Phi_y^+ = Phi_y^T M_y``.

    ``Phi_y^T M_y`` is the mass-weighted pseudo-inverse of the mass-orthonormal ``Phi_y``
    (ULRSSM's ``evecs_trans``). For a hard map this is
    `geofeat.adapters.blocks.functional_maps.fmap_from_pointmap`.

    Parameters
    ----------
    P : torch.Tensor, shape (V_y, V_x) or (B, V_y, V_x), or integer, shape (V_y,) or (B, V_y)
        Soft point map (rows index vertices of ``y``), or the indices ``map_yx`` of a hard one.
    evecs_x : array_like, shape (V_x, k_x) or (B, V_x, k_x)
    evecs_y : array_like, shape (V_y, k_y) or (B, V_y, k_y)
    mass_y : array_like, shape (V_y,) or (B, V_y)

    Returns
    -------
    torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
        Differentiable with respect to a soft ``P`` (and the bases).
    """
    p_in = to_tensor(P)
    hard = not p_in.is_floating_point()
    if hard:
        dtype, device = dtype_device(evecs_x)
    else:
        dtype, device = dtype_device(p_in)
    t, batched = batch_inputs(
        {"P": (p_in, 1 if hard else 2), "evecs_x": (evecs_x, 2), "evecs_y": (evecs_y, 2), "mass_y": (mass_y, 1)},
        dtype,
        device,
        integer=("P",),
    )
    p, ex, ey = t["P"], t["evecs_x"], t["evecs_y"]
    n_y = ey.shape[1]
    check_dim(p, 1, n_y, "P", "one row per vertex of y, rows")
    check_basis(ey, t["mass_y"], None, n_y, "y")
    if hard:
        if p.numel() and (int(p.min()) < 0 or int(p.max()) >= ex.shape[1]):
            raise FunctionalMapError(
                f"a hard point map must hold vertex indices of x in [0, {ex.shape[1] - 1}]; found range [{int(p.min())}, {int(p.max())}]."
            )
        pulled = torch.gather(ex, 1, p.unsqueeze(-1).expand(-1, -1, ex.shape[2]))  # (B, V_y, k_x)
    else:
        check_dim(p, 2, ex.shape[1], "P", "one column per vertex of x, columns")
        pulled = p @ ex
    return unbatch(ey.transpose(1, 2) @ (t["mass_y"].unsqueeze(-1) * pulled), batched)


def fmap_to_pointmap_soft(C, evecs_x, evecs_y, temperature: float = 1.0) -> torch.Tensor:
    """Soft point map y -> x encoded by a functional map: a softmax over spectral-embedding distances.

    ``P_yx[v, u] = softmax_u(-||Phi_y[v] - (Phi_x C^T)[u]||^2 / temperature)``, the
    differentiable relaxation of the nearest-neighbour conversion
    `geofeat.adapters.blocks.functional_maps.pointmap_from_fmap` (its argmax per row).

    Parameters
    ----------
    C : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
    evecs_x : array_like, shape (V_x, k_x) or (B, V_x, k_x)
    evecs_y : array_like, shape (V_y, k_y) or (B, V_y, k_y)
    temperature : float
        > 0, in units of squared embedding distance. Mass-orthonormal eigenvectors scale
        as ``area^-1/2``, so a temperature fits shapes of one area; the default suits
        shapes of unit area.

    Returns
    -------
    torch.Tensor, shape (V_y, V_x) or (B, V_y, V_x)
        Rows sum to one; differentiable with respect to ``C``. Dense.
    """
    temperature = positive(temperature, "temperature")
    dtype, device = dtype_device(C)
    t, batched = batch_inputs({"C": (C, 2), "evecs_x": (evecs_x, 2), "evecs_y": (evecs_y, 2)}, dtype, device)
    c = t["C"]
    check_dim(t["evecs_x"], 2, c.shape[2], "evecs_x", "one column per column of C (k_x), columns")
    check_dim(t["evecs_y"], 2, c.shape[1], "evecs_y", "one column per row of C (k_y), columns")
    emb_x, emb_y = t["evecs_x"] @ c.transpose(1, 2), t["evecs_y"]  # (B, V_x, k_y), (B, V_y, k_y)
    # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b, without the square root (smooth where distances vanish)
    sq_dist = emb_y.square().sum(-1, keepdim=True) + emb_x.square().sum(-1).unsqueeze(1) - 2.0 * emb_y @ emb_x.transpose(1, 2)
    return unbatch(torch.softmax(-sq_dist / temperature, dim=-1), batched)
