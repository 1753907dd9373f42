"""Reading PyTorch files with ``torch.load(..., weights_only=True)`` and messages that say what to do.

A pickle that holds Python objects other than tensors and plain containers is refused (loading
it could run arbitrary code), with a message that tells how to save the weights instead; a
truncated or foreign file gets a message of its own (and may raise another error type).
"""

from __future__ import annotations

import os
from typing import Any

from geofeat.errors import GeofeatError

__all__ = ["is_unsafe_pickle_error", "load_torch_file", "unsafe_pickle_message"]


def unsafe_pickle_message(path: str | os.PathLike, exc: BaseException) -> str:
    """Why a PyTorch pickle refused by ``torch.load(..., weights_only=True)`` is not loaded, and what to use instead."""
    detail = next((line.strip() for line in str(exc).splitlines() if "WeightsUnpickler error" in line), "")
    detail = detail.replace("WeightsUnpickler error: ", "").split(". ")[0].rstrip(".")
    return (
        f"{path} was refused for safety: it is a pickle that holds Python objects other than tensors and plain "
        f"containers{f' ({detail})' if detail else ''}, and unpickling those can run arbitrary code. geofeat loads "
        "only weights: save the tensors as safetensors (safetensors.torch.save_file(state_dict, 'model.safetensors'); "
        "a Hugging Face folder: model.save_pretrained(folder)) or as a plain state dict of tensors "
        "(torch.save(model.state_dict(), path)), converting the file where you trust its source."
    )


def is_unsafe_pickle_error(exc: BaseException) -> bool:
    """True when ``exc`` is ``torch.load(..., weights_only=True)`` refusing a pickle's Python objects.

    Garbage and truncated pickles fail the same unpickler with other messages (``Unsupported
    operand``); only a refused global or class counts here.
    """
    import pickle

    text = str(exc)
    refused = ("GLOBAL", "add_safe_globals", "allowlist")
    return isinstance(exc, pickle.UnpicklingError) and "Weights only load failed" in text and any(r in text for r in refused)


def _is_plain_pickle_with_objects(path: str | os.PathLike) -> bool:
    """True when ``path`` is a whole pickle (not torch's zip format) that names Python globals.

    ``pickle.dump`` writes such files; the weights-only unpickler fails on them with messages
    that read like damage (``Unsupported operand``). The opcodes are only read, never run.
    """
    import pickletools
    import zipfile

    try:
        if zipfile.is_zipfile(path):
            return False
        with open(path, "rb") as fh:
            if fh.read(1) != b"\x80":  # PROTO: pickle protocol 2 or later
                return False
            fh.seek(0)
            names = {op.name for op, _, _ in pickletools.genops(fh)}
    except Exception:  # a truncated or garbled pickle: damaged, not refused
        return False
    return bool(names & {"GLOBAL", "STACK_GLOBAL", "INST", "OBJ"})


def load_torch_file(
    path: str | os.PathLike,
    error: type[GeofeatError] = GeofeatError,
    *,
    damaged_error: type[GeofeatError] | None = None,
    what: str = "a PyTorch checkpoint",
    map_location: Any = "cpu",
) -> Any:
    """``torch.load(path, weights_only=True)`` with clear errors.

    Parameters
    ----------
    path : str or os.PathLike
        A file written by ``torch.save``.
    error : type
        Raised when the file is refused for safety (a pickle holding arbitrary Python objects).
    damaged_error : type, optional
        Raised when the file cannot be read (missing, truncated, not a PyTorch file); default ``error``.
    what : str
        What the file should be, for the message.
    map_location : Any
        As for ``torch.load``.

    Returns
    -------
    Any
        What the file holds (tensors, numbers, strings and containers of them).
    """
    import torch

    if os.path.isdir(path):
        raise (damaged_error or error)(f"{path} is a folder; expected {what}, a file written by torch.save.")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # pickle, zip, EOF and OS errors have no common base class
        if is_unsafe_pickle_error(exc) or _is_plain_pickle_with_objects(path):
            raise error(unsafe_pickle_message(path, exc)) from exc
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise (damaged_error or error)(
            f"could not read {path} as {what}: {reason}. The file is missing, truncated (an interrupted copy or "
            "write) or not written by torch.save; copy or write it again."
        ) from exc
