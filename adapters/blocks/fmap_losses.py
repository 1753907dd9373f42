"""Differentiable functional-map losses of the learned heads: bijectivity, orthogonality,
Laplacian commutativity, coupling with a soft point map, and their partial-shape forms.

Conventions are those of `geofeat.adapters.blocks.fmap_layers` (a map ``C`` of shape
``(k_y, k_x)``, an optional leading batch dimension). Each loss is a squared Frobenius norm
summed over each matrix and averaged over the batch, as ULRSSM's ``SquaredFrobeniusLoss``
(Cao et al. 2023, "Unsupervised Learning of Robust Spectral Shape Matching").
"""

from __future__ import annotations

import torch

from geofeat.adapters.blocks.fmap_inputs import (
    batch_inputs,
    batched_fmaps,
    check_dim,
    dtype_device,
    squared_frobenius,
    unbatch,
)
from geofeat.adapters.blocks.fmap_layers import pointmap_to_fmap
from geofeat.errors import FunctionalMapError

__all__ = [
    "coupling_loss",
    "fmap_bijectivity_loss",
    "fmap_orthogonality_loss",
    "laplacian_commutativity_loss",
    "partial_bijectivity_loss",
    "partial_orthogonality_loss",
    "partial_rank",
]


# ----------------------------------------------------------------------------- losses


def fmap_bijectivity_loss(C_xy, C_yx) -> torch.Tensor:
    """Bijectivity penalty ``||C_xy C_yx - I||^2 + ||C_yx C_xy - I||^2`` (SURFMNet, ULRSSM).

    Parameters
    ----------
    C_xy : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
    C_yx : torch.Tensor, shape (k_x, k_y) or (B, k_x, k_y)

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norms, averaged over the batch.
    """
    t, _ = batched_fmaps({"C_xy": C_xy, "C_yx": C_yx})
    c_xy, c_yx = t["C_xy"], t["C_yx"]
    if c_yx.shape[1:] != c_xy.shape[1:][::-1]:
        raise FunctionalMapError(
            f"C_yx must have the transposed shape of C_xy, (k_x, k_y) = {tuple(c_xy.shape[1:][::-1])}; found {tuple(c_yx.shape[1:])}."
        )
    eye_y = torch.eye(c_xy.shape[1], dtype=c_xy.dtype, device=c_xy.device)
    eye_x = torch.eye(c_xy.shape[2], dtype=c_xy.dtype, device=c_xy.device)
    return squared_frobenius(c_xy @ c_yx - eye_y) + squared_frobenius(c_yx @ c_xy - eye_x)


def fmap_orthogonality_loss(C) -> torch.Tensor:
    """Orthogonality (area preservation) penalty ``||C^T C - I||^2`` of one map.

    ULRSSM's ``SURFMNetLoss`` adds this term for both ``C_xy`` and ``C_yx``.

    Parameters
    ----------
    C : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norm of the (k_x, k_x) residual, averaged over the batch.
    """
    t, _ = batched_fmaps({"C": C})
    c = t["C"]
    eye = torch.eye(c.shape[2], dtype=c.dtype, device=c.device)
    return squared_frobenius(c.transpose(1, 2) @ c - eye)


def laplacian_commutativity_loss(C, evals_x, evals_y) -> torch.Tensor:
    """Laplacian commutativity penalty ``||C diag(evals_x) - diag(evals_y) C||^2`` of one map.

    On the raw eigenvalues, as ULRSSM's ``SURFMNetLoss`` (which adds the term for both
    directions and weights it by 1e-3 by default): the loss grows as the fourth power of
    the largest eigenvalue, so keep its weight small or the shapes at unit area.

    Parameters
    ----------
    C : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
    evals_x : array_like, shape (k_x,) or (B, k_x)
    evals_y : array_like, shape (k_y,) or (B, k_y)

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norm, averaged over the batch.
    """
    dtype, device = dtype_device(C)
    t, _ = batch_inputs({"C": (C, 2), "evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, dtype, device)
    c = t["C"]
    check_dim(t["evals_x"], 1, c.shape[2], "evals_x", "one eigenvalue per column of C (k_x), length")
    check_dim(t["evals_y"], 1, c.shape[1], "evals_y", "one eigenvalue per row of C (k_y), length")
    return squared_frobenius(c * t["evals_x"].unsqueeze(1) - t["evals_y"].unsqueeze(2) * c)


def coupling_loss(C, P, evecs_x, evecs_y, mass_y) -> torch.Tensor:
    """Coupling (alignment) penalty ``||C - Phi_y^+ P Phi_x||^2`` between a functional map and a point map.

    ULRSSM's ``align_loss`` between ``Cxy`` and ``evecs_trans_y @ Pyx @ evecs_x``; the map
    of ``P`` is `pointmap_to_fmap`. ULRSSM adds the same term for ``C_yx`` and ``P_xy``
    on full shapes (call again with the roles swapped).

    Parameters
    ----------
    C : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
    P : torch.Tensor, shape (V_y, V_x) or (B, V_y, V_x)
        Soft point map y -> x (for example from `soft_pointmap`), or integer indices.
    evecs_x : array_like, shape (V_x, k_x) or (B, V_x, k_x)
    evecs_y : array_like, shape (V_y, k_y) or (B, V_y, k_y)
    mass_y : array_like, shape (V_y,) or (B, V_y)

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norm, averaged over the batch.
    """
    c_p = pointmap_to_fmap(P, evecs_x, evecs_y, mass_y)
    t, _ = batched_fmaps({"C": C, "C_P": c_p})
    if t["C"].shape != t["C_P"].shape:
        raise FunctionalMapError(
            f"C must have shape (k_y, k_x) = {tuple(t['C_P'].shape[1:])} of the bases; found {tuple(t['C'].shape[1:])}."
        )
    return squared_frobenius(t["C"] - t["C_P"])


# ----------------------------------------------------------------------------- partial shapes


def partial_rank(evals_x, evals_y) -> torch.Tensor:
    """Estimated rank of the functional map of a partial shape ``y`` into a full shape ``x``.

    ULRSSM's ``PartialFmapsLoss``: with ``n`` the number of eigenvalues of the part ``y``
    below the largest eigenvalue of the full ``x`` (a part of relative area ``a`` has
    eigenvalues about ``1/a`` times larger, so the slope ratio of the spectra estimates the
    area ratio), the first ``r = min(n + 1, k_y)`` basis functions of ``y`` are taken as
    representable (ULRSSM puts ones on the diagonal at indices ``0 .. min(n, k - 1)``).

    Parameters
    ----------
    evals_x : array_like, shape (k_x,) or (B, k_x)
        Eigenvalues of the full shape.
    evals_y : array_like, shape (k_y,) or (B, k_y)
        Eigenvalues of the partial shape.

    Returns
    -------
    torch.Tensor, shape () or (B,), int64
        ``r`` in ``[1, k_y]``.
    """
    t, batched = batch_inputs({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    ex, ey = t["evals_x"].detach(), t["evals_y"].detach()
    n = (ey < ex.max(dim=1, keepdim=True).values).sum(dim=1)
    r = torch.clamp(n + 1, max=ey.shape[1])
    return unbatch(r, batched)


def _partial_eye(evals_x, evals_y, k_y: int, n_batch: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """(B, k_y, k_y) diagonal matrices with ``partial_rank`` leading ones."""
    r = partial_rank(evals_x, evals_y)
    r = r.reshape(-1).expand(n_batch) if r.ndim == 0 or r.shape[0] == 1 else r
    if r.shape[0] != n_batch:
        raise FunctionalMapError(f"the eigenvalues have batch size {r.shape[0]} but the functional maps {n_batch}.")
    ones = (torch.arange(k_y).unsqueeze(0) < r.unsqueeze(1)).to(dtype=dtype)
    return torch.diag_embed(ones).to(device)


def partial_orthogonality_loss(C, evals_x, evals_y) -> torch.Tensor:
    """Orthogonality penalty of a partial-to-full map: ``||C C^T - diag(1_r, 0)||^2``.

    ``y`` is the partial shape and ``x`` the full one, so the point map y -> x is defined
    everywhere and ``C`` (k_y, k_x) has (nearly) orthonormal rows for the ``r`` basis
    functions of ``y`` that the ``k_x`` functions of ``x`` can represent, and rows near zero
    beyond (the slanted diagonal of partial functional maps). ``r`` is `partial_rank`. As in
    ULRSSM's ``PartialFmapsLoss`` the whole (k_y, k_y) product is compared with that
    truncated identity.

    Parameters
    ----------
    C : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
        Map pulling functions back from the full ``x`` to the part ``y``.
    evals_x : array_like, shape (k_x,) or (B, k_x)
        Eigenvalues of the full shape.
    evals_y : array_like, shape (k_y,) or (B, k_y)
        Eigenvalues of the partial shape.

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norm, averaged over the batch.
    """
    t, _ = batched_fmaps({"C": C})
    c = t["C"]
    _check_partial_evals(c, evals_x, evals_y)
    eye = _partial_eye(evals_x, evals_y, c.shape[1], c.shape[0], c.dtype, c.device)
    return squared_frobenius(c @ c.transpose(1, 2) - eye)


def partial_bijectivity_loss(C_xy, C_yx, evals_x, evals_y) -> torch.Tensor:
    """Bijectivity penalty of a partial-to-full pair: ``||C_xy C_yx - diag(1_r, 0)||^2``.

    ULRSSM's ``PartialFmapsLoss`` bijectivity term (``C_fp C_pf``), with ``y`` the part,
    ``x`` the full shape and ``r`` from `partial_rank`.

    Parameters
    ----------
    C_xy : torch.Tensor, shape (k_y, k_x) or (B, k_y, k_x)
    C_yx : torch.Tensor, shape (k_x, k_y) or (B, k_x, k_y)
    evals_x : array_like, shape (k_x,) or (B, k_x)
        Eigenvalues of the full shape.
    evals_y : array_like, shape (k_y,) or (B, k_y)
        Eigenvalues of the partial shape.

    Returns
    -------
    torch.Tensor, shape ()
        Squared Frobenius norm, averaged over the batch.
    """
    t, _ = batched_fmaps({"C_xy": C_xy, "C_yx": C_yx})
    c_xy, c_yx = t["C_xy"], t["C_yx"]
    if c_yx.shape[1:] != c_xy.shape[1:][::-1]:
        raise FunctionalMapError(
            f"C_yx must have the transposed shape of C_xy, (k_x, k_y) = {tuple(c_xy.shape[1:][::-1])}; found {tuple(c_yx.shape[1:])}."
        )
    _check_partial_evals(c_xy, evals_x, evals_y)
    eye = _partial_eye(evals_x, evals_y, c_xy.shape[1], c_xy.shape[0], c_xy.dtype, c_xy.device)
    return squared_frobenius(c_xy @ c_yx - eye)


def _check_partial_evals(c: torch.Tensor, evals_x, evals_y) -> None:
    t, _ = batch_inputs({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    check_dim(t["evals_x"], 1, c.shape[2], "evals_x", "one eigenvalue per column of C (k_x), length")
    check_dim(t["evals_y"], 1, c.shape[1], "evals_y", "one eigenvalue per row of C (k_y), length")
