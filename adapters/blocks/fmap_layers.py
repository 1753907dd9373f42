"""Differentiable (torch) functional-map layers and losses for learned matching heads.

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

Losses are squared Frobenius norms summed over each matrix and averaged over the batch, as
ULRSSM's ``SquaredFrobeniusLoss`` (Cao et al. 2023, "Unsupervised Learning of Robust
Spectral Shape Matching").
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from geofeat.adapters.blocks.functional_maps import MASK_KINDS, laplacian_mask
from geofeat.checks import check_number
from geofeat.errors import FunctionalMapError

__all__ = [
    "RegularizedFMap",
    "coupling_loss",
    "fmap_bijectivity_loss",
    "fmap_orthogonality_loss",
    "fmap_to_pointmap_soft",
    "laplacian_commutativity_loss",
    "partial_bijectivity_loss",
    "partial_orthogonality_loss",
    "partial_rank",
    "pointmap_to_fmap",
    "regularized_fmap",
    "resolvent_mask",
    "soft_pointmap",
    "soft_pointmaps",
]


# ----------------------------------------------------------------------------- input handling


def _to_tensor(value) -> torch.Tensor:
    """A tensor as it is; an array_like as a tensor (copied when read-only, like `SpectralBasis` arrays)."""
    if isinstance(value, torch.Tensor):
        return value
    try:
        arr = np.asarray(value)
        return torch.from_numpy(arr if arr.flags.writeable else arr.copy()) if arr.dtype != object else torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as err:
        raise FunctionalMapError(f"expected a tensor or an array of numbers; found {type(value).__name__} ({err}).") from err


def _dtype_device(reference) -> tuple[torch.dtype, torch.device]:
    """Floating dtype and device of the computation: those of ``reference`` (default dtype if not floating)."""
    t = _to_tensor(reference)
    dtype = t.dtype if t.is_floating_point() else torch.get_default_dtype()
    return dtype, t.device


def _batched(
    items: dict[str, tuple[object, int]],
    dtype: torch.dtype,
    device: torch.device,
    integer: tuple[str, ...] = (),
    host: tuple[str, ...] = (),
) -> tuple[dict[str, torch.Tensor], bool]:
    """Convert inputs to tensors with a leading batch dimension shared by all.

    ``items`` maps a name to ``(value, core_ndim)``: a value with ``core_ndim`` dimensions is
    unbatched (it is expanded to the common batch size), one with ``core_ndim + 1`` is batched.
    The items named in ``host`` go to the CPU instead of ``device`` (they are read there).
    Returns the tensors, shape ``(B, *core)``, and whether any input was batched.
    """
    tensors: dict[str, torch.Tensor] = {}
    batch_sizes: dict[str, int] = {}
    for name, (value, core_ndim) in items.items():
        t = _to_tensor(value)
        target = torch.device("cpu") if name in host else device
        if name in integer and not t.is_floating_point():
            t = t.to(device=target, dtype=torch.int64)
        else:
            if t.is_complex() or t.dtype == torch.bool:
                raise FunctionalMapError(f"{name} must hold real numbers; found dtype {t.dtype}.")
            t = t.to(device=target, dtype=dtype)
        if t.ndim == core_ndim:
            t = t.unsqueeze(0)
        elif t.ndim == core_ndim + 1:
            batch_sizes[name] = t.shape[0]
        else:
            raise FunctionalMapError(
                f"{name} must have {core_ndim} dimensions, or {core_ndim + 1} with a leading batch dimension; "
                f"found shape {tuple(t.shape)}."
            )
        tensors[name] = t
    sizes = set(batch_sizes.values())
    if len(sizes) > 1:
        found = ", ".join(f"{name}: {size}" for name, size in batch_sizes.items())
        raise FunctionalMapError(f"batched inputs must have the same batch size; found {found}.")
    size = sizes.pop() if sizes else 1
    for name, t in tensors.items():
        if t.shape[0] != size:
            tensors[name] = t.expand(size, *t.shape[1:])
    return tensors, bool(batch_sizes)


def _check_dim(t: torch.Tensor, axis: int, expected: int, name: str, what: str) -> None:
    if t.shape[axis] != expected:
        raise FunctionalMapError(
            f"{name} must have {what} = {expected}; found shape {tuple(t.shape[1:])} (batch dimension dropped)."
        )


def _check_basis(evecs: torch.Tensor, mass: torch.Tensor | None, evals: torch.Tensor | None, n_vertices: int, side: str) -> None:
    """Check (B, V, k) eigenvectors, (B, V) mass and (B, k) eigenvalues against ``n_vertices``."""
    _check_dim(evecs, 1, n_vertices, f"evecs_{side}", f"one row per vertex of {side}, rows")
    k = evecs.shape[2]
    if mass is not None:
        _check_dim(mass, 1, n_vertices, f"mass_{side}", f"one entry per vertex of {side}, length")
    if evals is not None:
        _check_dim(evals, 1, k, f"evals_{side}", f"one eigenvalue per column of evecs_{side}, length")


def _positive(value: float, name: str, allow_zero: bool = False) -> float:
    return check_number(value, name, low=0, low_open=not allow_zero, error=FunctionalMapError)


def _unbatch(t: torch.Tensor, batched: bool) -> torch.Tensor:
    return t if batched else t[0]


def _squared_frobenius(diff: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of the squared Frobenius norm of each (B, m, n) matrix."""
    return diff.square().sum(dim=(-2, -1)).mean()


def _fmaps(items: dict[str, object]) -> tuple[dict[str, torch.Tensor], bool]:
    """Convert functional maps (k_rows, k_cols) or (B, k_rows, k_cols) to batched tensors of the first map's dtype."""
    dtype, device = _dtype_device(next(iter(items.values())))
    return _batched({name: (value, 2) for name, value in items.items()}, dtype, device)


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
    dtype, device = _dtype_device(evals_x)
    if kind not in MASK_KINDS:
        raise FunctionalMapError(f"mask kind must be one of {MASK_KINDS}; found {kind!r}.")
    t, batched = _batched({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    ex, ey = t["evals_x"].detach().numpy(), t["evals_y"].detach().numpy()
    masks = np.stack([laplacian_mask(ex[b], ey[b], kind=kind, gamma=gamma) for b in range(ex.shape[0])])
    return _unbatch(torch.as_tensor(masks, dtype=dtype, device=device), batched)


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
    lambda_ = _positive(lambda_, "lambda_", allow_zero=True)
    dtype, device = _dtype_device(feat_x)
    t, batched = _batched(
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
    _check_basis(t["evecs_x"], t["mass_x"], t["evals_x"], fx.shape[1], "x")
    _check_basis(t["evecs_y"], t["mass_y"], t["evals_y"], fy.shape[1], "y")
    host_weights = resolvent_mask(t["evals_x"], t["evals_y"], gamma=gamma, kind=mask)  # (B, k_y, k_x), on the CPU
    _check_not_singular(host_weights, lambda_, fx.shape[2])
    if bidirectional:
        _check_not_singular(host_weights.transpose(1, 2), lambda_, fx.shape[2])
    weights = host_weights.to(device)
    a = t["evecs_x"].transpose(1, 2) @ (t["mass_x"].unsqueeze(-1) * fx)  # (B, k_x, p)
    b = t["evecs_y"].transpose(1, 2) @ (t["mass_y"].unsqueeze(-1) * fy)  # (B, k_y, p)
    c_xy = _unbatch(_solve_fmap(a, b, weights, lambda_), batched)
    if not bidirectional:
        return c_xy
    c_yx = _solve_fmap(b, a, weights.transpose(1, 2), lambda_)
    return c_xy, _unbatch(c_yx, batched)


class RegularizedFMap(nn.Module):
    """`regularized_fmap` as a module (no parameters), for heads built from ``nn.Module`` parts.

    Parameters
    ----------
    lambda_, gamma, mask, bidirectional
        As in `regularized_fmap`.
    """

    def __init__(self, lambda_: float = 100.0, gamma: float = 0.5, mask: str = "resolvent", bidirectional: bool = False):
        super().__init__()
        self.lambda_ = _positive(lambda_, "lambda_", allow_zero=True)
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
    temperature = _positive(temperature, "temperature")
    dtype, device = _dtype_device(feat_x)
    t, batched = _batched({"feat_x": (feat_x, 2), "feat_y": (feat_y, 2)}, dtype, device)
    fx, fy = t["feat_x"], t["feat_y"]
    if fx.shape[2] != fy.shape[2]:
        raise FunctionalMapError(
            f"feat_x and feat_y must have the same number of channels; found {fx.shape[2]} and {fy.shape[2]}."
        )
    if normalize:
        fx, fy = F.normalize(fx, p=2, dim=-1), F.normalize(fy, p=2, dim=-1)
    similarity = fy @ fx.transpose(1, 2)  # (B, V_y, V_x)
    return _unbatch(torch.softmax(similarity / temperature, dim=-1), batched)


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
    temperature = _positive(temperature, "temperature")
    dtype, device = _dtype_device(feat_x)
    t, batched = _batched({"feat_x": (feat_x, 2), "feat_y": (feat_y, 2)}, dtype, device)
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
    return _unbatch(p_yx, batched), _unbatch(p_xy, batched)


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
    p_in = _to_tensor(P)
    hard = not p_in.is_floating_point()
    if hard:
        dtype, device = _dtype_device(evecs_x)
    else:
        dtype, device = _dtype_device(p_in)
    t, batched = _batched(
        {"P": (p_in, 1 if hard else 2), "evecs_x": (evecs_x, 2), "evecs_y": (evecs_y, 2), "mass_y": (mass_y, 1)},
        dtype,
        device,
        integer=("P",),
    )
    p, ex, ey = t["P"], t["evecs_x"], t["evecs_y"]
    n_y = ey.shape[1]
    _check_dim(p, 1, n_y, "P", "one row per vertex of y, rows")
    _check_basis(ey, t["mass_y"], None, n_y, "y")
    if hard:
        if p.numel() and (int(p.min()) < 0 or int(p.max()) >= ex.shape[1]):
            raise FunctionalMapError(
                f"a hard point map must hold vertex indices of x in [0, {ex.shape[1] - 1}]; found range [{int(p.min())}, {int(p.max())}]."
            )
        pulled = torch.gather(ex, 1, p.unsqueeze(-1).expand(-1, -1, ex.shape[2]))  # (B, V_y, k_x)
    else:
        _check_dim(p, 2, ex.shape[1], "P", "one column per vertex of x, columns")
        pulled = p @ ex
    return _unbatch(ey.transpose(1, 2) @ (t["mass_y"].unsqueeze(-1) * pulled), batched)


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
    temperature = _positive(temperature, "temperature")
    dtype, device = _dtype_device(C)
    t, batched = _batched({"C": (C, 2), "evecs_x": (evecs_x, 2), "evecs_y": (evecs_y, 2)}, dtype, device)
    c = t["C"]
    _check_dim(t["evecs_x"], 2, c.shape[2], "evecs_x", "one column per column of C (k_x), columns")
    _check_dim(t["evecs_y"], 2, c.shape[1], "evecs_y", "one column per row of C (k_y), columns")
    emb_x, emb_y = t["evecs_x"] @ c.transpose(1, 2), t["evecs_y"]  # (B, V_x, k_y), (B, V_y, k_y)
    # |a - b|^2 = |a|^2 + |b|^2 - 2 a.b, without the square root (smooth where distances vanish)
    sq_dist = emb_y.square().sum(-1, keepdim=True) + emb_x.square().sum(-1).unsqueeze(1) - 2.0 * emb_y @ emb_x.transpose(1, 2)
    return _unbatch(torch.softmax(-sq_dist / temperature, dim=-1), batched)


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
    t, _ = _fmaps({"C_xy": C_xy, "C_yx": C_yx})
    c_xy, c_yx = t["C_xy"], t["C_yx"]
    if c_yx.shape[1:] != c_xy.shape[1:][::-1]:
        raise FunctionalMapError(
            f"C_yx must have the transposed shape of C_xy, (k_x, k_y) = {tuple(c_xy.shape[1:][::-1])}; found {tuple(c_yx.shape[1:])}."
        )
    eye_y = torch.eye(c_xy.shape[1], dtype=c_xy.dtype, device=c_xy.device)
    eye_x = torch.eye(c_xy.shape[2], dtype=c_xy.dtype, device=c_xy.device)
    return _squared_frobenius(c_xy @ c_yx - eye_y) + _squared_frobenius(c_yx @ c_xy - eye_x)


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
    t, _ = _fmaps({"C": C})
    c = t["C"]
    eye = torch.eye(c.shape[2], dtype=c.dtype, device=c.device)
    return _squared_frobenius(c.transpose(1, 2) @ c - eye)


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
    dtype, device = _dtype_device(C)
    t, _ = _batched({"C": (C, 2), "evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, dtype, device)
    c = t["C"]
    _check_dim(t["evals_x"], 1, c.shape[2], "evals_x", "one eigenvalue per column of C (k_x), length")
    _check_dim(t["evals_y"], 1, c.shape[1], "evals_y", "one eigenvalue per row of C (k_y), length")
    return _squared_frobenius(c * t["evals_x"].unsqueeze(1) - t["evals_y"].unsqueeze(2) * c)


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
    t, _ = _fmaps({"C": C, "C_P": c_p})
    if t["C"].shape != t["C_P"].shape:
        raise FunctionalMapError(
            f"C must have shape (k_y, k_x) = {tuple(t['C_P'].shape[1:])} of the bases; found {tuple(t['C'].shape[1:])}."
        )
    return _squared_frobenius(t["C"] - t["C_P"])


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
    t, batched = _batched({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    ex, ey = t["evals_x"].detach(), t["evals_y"].detach()
    n = (ey < ex.max(dim=1, keepdim=True).values).sum(dim=1)
    r = torch.clamp(n + 1, max=ey.shape[1])
    return _unbatch(r, batched)


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
    t, _ = _fmaps({"C": C})
    c = t["C"]
    _check_partial_evals(c, evals_x, evals_y)
    eye = _partial_eye(evals_x, evals_y, c.shape[1], c.shape[0], c.dtype, c.device)
    return _squared_frobenius(c @ c.transpose(1, 2) - eye)


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
    t, _ = _fmaps({"C_xy": C_xy, "C_yx": C_yx})
    c_xy, c_yx = t["C_xy"], t["C_yx"]
    if c_yx.shape[1:] != c_xy.shape[1:][::-1]:
        raise FunctionalMapError(
            f"C_yx must have the transposed shape of C_xy, (k_x, k_y) = {tuple(c_xy.shape[1:][::-1])}; found {tuple(c_yx.shape[1:])}."
        )
    _check_partial_evals(c_xy, evals_x, evals_y)
    eye = _partial_eye(evals_x, evals_y, c_xy.shape[1], c_xy.shape[0], c_xy.dtype, c_xy.device)
    return _squared_frobenius(c_xy @ c_yx - eye)


def _check_partial_evals(c: torch.Tensor, evals_x, evals_y) -> None:
    t, _ = _batched({"evals_x": (evals_x, 1), "evals_y": (evals_y, 1)}, torch.float64, torch.device("cpu"))
    _check_dim(t["evals_x"], 1, c.shape[2], "evals_x", "one eigenvalue per column of C (k_x), length")
    _check_dim(t["evals_y"], 1, c.shape[1], "evals_y", "one eigenvalue per row of C (k_y), length")
