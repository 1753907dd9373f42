"""Inputs of the differentiable functional-map layers and losses: tensors with an optional batch dimension.

Every function of `geofeat.adapters.blocks.fmap_layers` and `geofeat.adapters.blocks.fmap_losses`
takes torch tensors (array_likes are converted) and accepts an optional leading batch
dimension ``B``: when an input has it, the result has it, and inputs without it are shared by
every batch element. These helpers convert, batch and check those inputs.
"""

from __future__ import annotations

import numpy as np
import torch

from geofeat.checks import check_number
from geofeat.errors import FunctionalMapError

__all__ = [
    "batch_inputs",
    "batched_fmaps",
    "check_basis",
    "check_dim",
    "dtype_device",
    "positive",
    "squared_frobenius",
    "to_tensor",
    "unbatch",
]


def to_tensor(value) -> torch.Tensor:
    """A tensor as it is; an array_like as a tensor (copied when read-only, like `SpectralBasis` arrays)."""
    if isinstance(value, torch.Tensor):
        return value
    try:
        arr = np.asarray(value)
        return torch.from_numpy(arr if arr.flags.writeable else arr.copy()) if arr.dtype != object else torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as err:
        raise FunctionalMapError(f"expected a tensor or an array of numbers; found {type(value).__name__} ({err}).") from err


def dtype_device(reference) -> tuple[torch.dtype, torch.device]:
    """Floating dtype and device of the computation: those of ``reference`` (default dtype if not floating)."""
    t = to_tensor(reference)
    dtype = t.dtype if t.is_floating_point() else torch.get_default_dtype()
    return dtype, t.device


def batch_inputs(
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
        t = to_tensor(value)
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


def check_dim(t: torch.Tensor, axis: int, expected: int, name: str, what: str) -> None:
    if t.shape[axis] != expected:
        raise FunctionalMapError(
            f"{name} must have {what} = {expected}; found shape {tuple(t.shape[1:])} (batch dimension dropped)."
        )


def check_basis(evecs: torch.Tensor, mass: torch.Tensor | None, evals: torch.Tensor | None, n_vertices: int, side: str) -> None:
    """Check (B, V, k) eigenvectors, (B, V) mass and (B, k) eigenvalues against ``n_vertices``."""
    check_dim(evecs, 1, n_vertices, f"evecs_{side}", f"one row per vertex of {side}, rows")
    k = evecs.shape[2]
    if mass is not None:
        check_dim(mass, 1, n_vertices, f"mass_{side}", f"one entry per vertex of {side}, length")
    if evals is not None:
        check_dim(evals, 1, k, f"evals_{side}", f"one eigenvalue per column of evecs_{side}, length")


def positive(value: float, name: str, allow_zero: bool = False) -> float:
    return check_number(value, name, low=0, low_open=not allow_zero, error=FunctionalMapError)


def unbatch(t: torch.Tensor, batched: bool) -> torch.Tensor:
    return t if batched else t[0]


def squared_frobenius(diff: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of the squared Frobenius norm of each (B, m, n) matrix."""
    return diff.square().sum(dim=(-2, -1)).mean()


def batched_fmaps(items: dict[str, object]) -> tuple[dict[str, torch.Tensor], bool]:
    """Convert functional maps (k_rows, k_cols) or (B, k_rows, k_cols) to batched tensors of the first map's dtype."""
    dtype, device = dtype_device(next(iter(items.values())))
    return batch_inputs({name: (value, 2) for name, value in items.items()}, dtype, device)
