"""Torch devices: ``"auto"`` means CUDA when present, else CPU. Nothing hard-codes ``"cuda:0"``."""

from __future__ import annotations

from typing import TYPE_CHECKING

from geofeat.errors import DeviceError

if TYPE_CHECKING:
    import torch


def resolve_device(device: str | torch.device | None = "auto") -> torch.device:
    """``"auto"`` (or None) is CUDA when available, else CPU; anything else is parsed by `torch.device`.

    Raises
    ------
    DeviceError
        An unparsable device, or CUDA asked for where there is none.
    """
    import torch  # here, not at the top: the training-free pipelines never load torch

    if device is None or (isinstance(device, str) and device == "auto"):
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise DeviceError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:<index>'; found {device!r}.") from err
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise DeviceError(f"device={device!r} was requested but CUDA is not available here; use device='auto' or 'cpu'.")
    return resolved
