"""Writing files so that a reader never sees a half-written one, and reading PyTorch files safely."""

from __future__ import annotations

import errno
import logging
import os
import tempfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.errors import GeofeatError

log = logging.getLogger(__name__)

__all__ = ["atomic_write", "fsync_file", "fsync_folder", "fsync_tree", "load_torch_file", "unsafe_pickle_message"]


def fsync_file(path: str | os.PathLike) -> None:
    """Flush a file's content to the disk (``os.fsync``)."""
    with open(path, "rb") as handle:
        os.fsync(handle.fileno())


def fsync_folder(path: str | os.PathLike) -> None:
    """Flush a folder's entries (names created, renamed or removed in it) to the disk.

    Without it a rename can be lost in a power cut even though the renamed file was
    synced. A no-op where folders cannot be opened (Windows).
    """
    if os.name == "nt":
        return
    handle = os.open(path, os.O_RDONLY)
    try:
        os.fsync(handle)
    except OSError as err:  # some file systems (network, FUSE) cannot sync a folder
        if err.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
        log.debug("cannot fsync the folder %s: %s", path, err)
    finally:
        os.close(handle)


def fsync_tree(folder: str | os.PathLike) -> None:
    """``fsync`` every file below ``folder``, then every folder from the deepest up to ``folder`` itself."""
    folder = Path(folder)
    folders = [folder]
    for path in sorted(folder.rglob("*")):
        if path.is_symlink():
            continue
        if path.is_dir():
            folders.append(path)
        elif path.is_file():
            fsync_file(path)
    for path in sorted(folders, key=lambda p: len(p.parts), reverse=True):
        fsync_folder(path)


def atomic_write(path: str | os.PathLike, write: Callable[[Path], None], *, durable: bool = True) -> Path:
    """Write through a temporary file in the same folder, then rename it over ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The final file; its folder is created when missing.
    write : callable
        ``write(tmp_path)`` writes the content to the temporary file.
    durable : bool
        ``fsync`` the temporary file before the rename and the folder after it, so that
        after a crash or power cut ``path`` holds either the old or the whole new content.
        ``False`` skips both (a 100 MB file: tens of milliseconds of waiting for the disk
        saved): other processes still see the old or the whole new content, but a power
        cut may leave ``path`` empty or partly written. Only for files whose readers detect
        that (a checksum) and can make them again.

    Returns
    -------
    pathlib.Path
        ``path``. On any failure (an interruption included) the temporary file is removed
        and an existing ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(handle)
    try:
        write(Path(tmp))
        if durable:
            fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    if durable:
        fsync_folder(path.parent)
    return path


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

    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as exc:  # pickle, zip, EOF and OS errors have no common base class
        if is_unsafe_pickle_error(exc):
            raise error(unsafe_pickle_message(path, exc)) from exc
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise (damaged_error or error)(
            f"could not read {path} as {what}: {reason}. The file is missing, truncated (an interrupted copy or "
            "write) or not written by torch.save; copy or write it again."
        ) from exc


def array_crc32(array: np.ndarray) -> int:
    """CRC-32 of an array's dtype, shape and bytes (C order): catches truncation, bit rot and garbage, and is fast."""
    header = f"{array.dtype.str}{array.shape}".encode()
    return zlib.crc32(np.ascontiguousarray(array).data, zlib.crc32(header))
