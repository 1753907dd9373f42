"""Writing files so that a reader never sees a half-written one, folders of such checked entries (`EntryFolder`), and reading PyTorch files safely."""

from __future__ import annotations

import errno
import logging
import os
import tempfile
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.errors import GeofeatError, StoreError

log = logging.getLogger(__name__)

__all__ = [
    "EntryFolder",
    "StoreInfo",
    "atomic_write",
    "fsync_file",
    "fsync_folder",
    "fsync_tree",
    "load_torch_file",
    "unsafe_pickle_message",
]

#: Temporary files older than this (seconds) are taken for leftovers of killed writers.
STALE_TMP_SECONDS = 3600.0


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


def probe_writable(folder: str | os.PathLike, prefix: str, suffix: str = "") -> None:
    """Create ``folder`` when missing, then create and remove one empty file there.

    The probe is named ``<prefix>...<suffix>``, so that a store that classifies its files by
    name sees one left behind by a killed process as a temporary file.

    Raises
    ------
    OSError
        Read-only file system, no permission, no space, or ``folder`` is not a folder.
    """
    Path(folder).mkdir(parents=True, exist_ok=True)
    handle, probe = tempfile.mkstemp(prefix=prefix, suffix=suffix, dir=folder)
    os.close(handle)
    os.unlink(probe)


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


def array_crc32(array: np.ndarray) -> int:
    """CRC-32 of an array's dtype, shape and bytes (C order): catches truncation, bit rot and garbage, and is fast."""
    header = f"{array.dtype.str}{array.shape}".encode()
    return zlib.crc32(np.ascontiguousarray(array).data, zlib.crc32(header))


@dataclass(frozen=True)
class StoreInfo:
    """Summary of a store folder; ``other_paths`` are what it holds that is not an entry or temporary file."""

    root: Path
    entries: int
    bytes: int
    temporary_files: int
    other_paths: tuple[Path, ...] = ()


class EntryFolder:
    """A folder of checked entry files written atomically: what the feature cache and the geodesic store share.

    Subclasses say which files are entries (`_scan`) and whether an entry is sound
    (`_is_sound`); this class counts, verifies and clears them. Temporary files are those of
    writers still running or killed; anything else in the folder is never touched.

    Attributes
    ----------
    root : pathlib.Path
        The folder.
    label : str
        What the folder is, for messages (``"the feature cache"``).
    error : type
        The `StoreError` subclass raised when the folder cannot be cleared.
    """

    root: Path
    label = "the store"
    error: type[StoreError] = StoreError

    def _scan(self) -> tuple[list[Path], list[Path], list[Path]]:
        """Entry files, temporary files and everything else, each sorted."""
        raise NotImplementedError

    def _is_sound(self, path: Path) -> bool:
        """Whether the entry file ``path`` reads back whole and passes its checksum."""
        raise NotImplementedError

    def entries(self) -> list[Path]:
        """Paths of every complete entry."""
        return self._scan()[0]

    def temporary_files(self) -> list[Path]:
        """Temporary files of writers still running or killed."""
        return self._scan()[1]

    def other_paths(self) -> list[Path]:
        """What the folder holds that is neither an entry nor a temporary file (skipped by `verify` and `clear`)."""
        return self._scan()[2]

    def info(self) -> StoreInfo:
        """Counts and total size of the folder (entries only; see ``StoreInfo.other_paths``)."""
        entries, temporary, other = self._scan()
        size = 0
        for path in entries:
            try:
                size += path.stat().st_size
            except FileNotFoundError:  # removed by another process meanwhile
                pass
        return StoreInfo(self.root, len(entries), size, len(temporary), tuple(other))

    def verify(self, remove: bool = True) -> tuple[int, list[Path]]:
        """Check every entry.

        Paths that are not entry files (`other_paths`) are skipped. On a read-only folder
        damaged entries are reported but stay (a warning says so).

        Parameters
        ----------
        remove : bool
            Delete damaged entries and stale temporary files (older than an hour).

        Returns
        -------
        n_ok : int
            Entries that passed.
        damaged : list of Path
            Entries that did not.
        """
        n_ok, damaged = 0, []
        entries, temporary, other = self._scan()
        if other:
            log.warning("skipped %d path(s) in %s that are not entries: %s", len(other), self.root, [str(p) for p in other[:5]])
        for path in entries:
            if self._is_sound(path):
                n_ok += 1
                continue
            damaged.append(path)
            if remove:
                self._remove(path)
        if remove:
            now = time.time()
            for tmp in temporary:
                try:
                    stale = now - tmp.stat().st_mtime > STALE_TMP_SECONDS
                except FileNotFoundError:
                    continue
                if stale:
                    self._remove(tmp)
        return n_ok, damaged

    def clear(self) -> int:
        """Delete every entry and temporary file; returns the number of entries removed.

        Paths that are not entry files (`other_paths`) are left where they are.

        Raises
        ------
        StoreError
            (`error`) A file cannot be deleted (read-only file system, no permission); the
            message says how many entries were removed before.
        """
        entries, temporary, _ = self._scan()
        for done, path in enumerate(entries + temporary):
            try:
                path.unlink()
            except FileNotFoundError:
                pass
            except OSError as err:
                raise self.error(
                    f"cannot clear {self.label} {self.root}: deleting {path} failed ({err}); "
                    f"{min(done, len(entries))} of {len(entries)} entries were removed before. The store is read-only "
                    "or not yours: clear it as its owner, or set GEOFEAT_CACHE_DIR to another folder."
                ) from err
        return len(entries)

    @staticmethod
    def _remove(path: Path) -> None:
        """Delete a file; a failure (read-only store, no permission) is logged, not raised."""
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        except OSError as err:
            log.warning("could not delete %s (%s); it stays in the store", path, err)
