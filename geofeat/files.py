"""Writing files so that a reader never sees a half-written one, folders of such checked entries (`EntryFolder`), and reading PyTorch files safely."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import secrets
import shutil
import tempfile
import threading
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
    "atomic_folder",
    "atomic_write",
    "fsync_file",
    "fsync_folder",
    "fsync_tree",
    "load_torch_file",
    "probe_writable",
    "remove_dead_temporary_folders",
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


#: ``.<name>.tmp-<pid>-<token>`` (a folder being written) and ``.<name>.old-<pid>-<token>`` (the folder it
#: replaces, during the swap) of `atomic_folder`; ``.<name>.tmp-<pid>`` is the older trainer's temporary folder.
_FOLDER_SIBLING = re.compile(r"\.(?P<name>.+)\.(?P<role>tmp|old)-(?P<pid>\d+)(?:-[0-9a-f]+)?")
#: Sibling folders this process is writing now (other threads' saves are not leftovers).
_IN_FLIGHT: set[Path] = set()
_IN_FLIGHT_LOCK = threading.Lock()


def _sibling(path: Path, role: str) -> Path:
    """A fresh ``.<name>.<role>-<pid>-<token>`` path beside ``path`` (not created)."""
    return path.with_name(f".{path.name}.{role}-{os.getpid()}-{secrets.token_hex(4)}")


def _writer_alive(pid: int, folder: Path) -> bool:
    """Whether the process that named ``folder`` may still be writing it.

    This process: only while the folder is in `_IN_FLIGHT` (a leftover with our process
    id comes from an earlier, killed process that had the same id). Another process: while
    the id exists (a process of another user counts as alive).
    """
    if pid == os.getpid():
        with _IN_FLIGHT_LOCK:
            return folder in _IN_FLIGHT
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    except OSError:
        return False
    return True


def remove_dead_temporary_folders(parent: str | os.PathLike, name: str | None = None) -> list[Path]:
    """Clean up after `atomic_folder` calls whose process was killed.

    A temporary folder (``.<name>.tmp-<pid>-...``) of a dead process is deleted. A folder set
    aside during a swap (``.<name>.old-<pid>-...``) is deleted when ``<name>`` exists, and
    renamed back to ``<name>`` when the kill came between the two renames of the swap, so the
    old content is never lost.

    Parameters
    ----------
    parent : str or os.PathLike
        The folder holding the written folders; a missing one holds nothing.
    name : str, optional
        Only the leftovers of ``<parent>/<name>``; default: of every folder in ``parent``.

    Returns
    -------
    list of pathlib.Path
        The leftovers deleted or restored, sorted.
    """
    parent = Path(parent)
    if not parent.is_dir():
        return []
    cleaned = []
    for path in sorted(parent.iterdir()):
        match = _FOLDER_SIBLING.fullmatch(path.name)
        if not match or (name is not None and match["name"] != name) or not path.is_dir() or path.is_symlink():
            continue
        if _writer_alive(int(match["pid"]), path):
            continue
        final = parent / match["name"]
        if match["role"] == "old" and not final.exists():
            try:
                os.rename(path, final)
            except OSError as err:  # another process restored or wrote it meanwhile
                log.debug("could not restore %s to %s: %s", path, final, err)
                continue
            log.warning("restored %s from %s, set aside by a save that was killed", final, path.name)
        else:
            shutil.rmtree(path, ignore_errors=True)
        cleaned.append(path)
    return cleaned


def atomic_folder(path: str | os.PathLike, write: Callable[[Path], None], *, durable: bool = True) -> Path:
    """Write a whole folder through a temporary sibling folder, then rename it into place.

    ``write`` fills ``.<name>.tmp-<pid>-<token>`` beside ``path``; every file and folder in it
    is ``fsync``-ed, then it is renamed to ``path``. An existing ``path`` is first renamed
    to ``.<name>.old-<pid>-<token>`` and deleted after the swap. Readers see the old folder
    or the whole new one, apart from the instant between the two renames, when ``path`` is
    missing; a process killed in that instant leaves the old folder set aside, and
    `remove_dead_temporary_folders` (called here before each write, and by the trainer
    when it resumes) puts it back.

    Parameters
    ----------
    path : str or os.PathLike
        The final folder; its parent is created when missing. What was there is replaced
        whole (callers check first that it may be).
    write : callable
        ``write(tmp_folder)`` writes the content into the (existing, empty) temporary folder.
    durable : bool
        ``fsync`` the files and folders before the rename and the parent after it, so that
        after a power cut ``path`` holds the old or the whole new content.

    Returns
    -------
    pathlib.Path
        ``path``. On any failure (an interruption included) the temporary folder is removed
        and an existing ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_dead_temporary_folders(path.parent, path.name)
    tmp = _sibling(path, "tmp")
    with _IN_FLIGHT_LOCK:
        _IN_FLIGHT.add(tmp)
    try:
        tmp.mkdir()
        write(tmp)
        if durable:
            fsync_tree(tmp)
        _swap_into_place(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        with _IN_FLIGHT_LOCK:
            _IN_FLIGHT.discard(tmp)
    if durable:
        fsync_folder(path.parent)
    return path


def _swap_into_place(tmp: Path, path: Path, attempts: int = 5) -> None:
    """Rename ``tmp`` to ``path``, setting an existing ``path`` aside first and deleting it after.

    An interruption between the two renames leaves the old folder set aside
    (``.<name>.old-<pid>-<token>``), where `remove_dead_temporary_folders` finds it.
    """
    for _ in range(attempts):
        aside = None
        if path.is_symlink() or path.is_file():
            path.unlink()
        elif path.exists():
            aside = _sibling(path, "old")
            with _IN_FLIGHT_LOCK:
                _IN_FLIGHT.add(aside)
        try:
            moved = False
            if aside is not None:
                with contextlib.suppress(FileNotFoundError):  # another process set it aside meanwhile
                    os.rename(path, aside)
                    moved = True
            try:
                os.replace(tmp, path)
                placed = True
            except OSError as err:
                if err.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    if moved:  # put the old folder back (a later cleanup does it if this fails)
                        with contextlib.suppress(OSError):
                            os.rename(aside, path)
                    raise
                placed = False  # another process put a folder there meanwhile (newer than ours): set it aside too
            if moved:
                shutil.rmtree(aside, ignore_errors=True)
            if placed:
                return
        finally:
            if aside is not None:
                with _IN_FLIGHT_LOCK:
                    _IN_FLIGHT.discard(aside)
    raise OSError(errno.EEXIST, f"{path} was written by other processes {attempts} times while this one tried to replace it")


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
