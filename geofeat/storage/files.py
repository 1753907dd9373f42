"""Writing files and folders so that a reader never sees a half-written one.

`atomic_write` writes one file through a temporary file and a rename; `atomic_folder` writes
a whole folder through a temporary sibling folder and a rename (what `geofeat.storage.pretrained`
uses); `fsync_file`, `fsync_folder` and `fsync_tree` put files and folder entries on the
disk; `probe_writable` checks that a folder can be written before long work starts.

Reading PyTorch files safely is `geofeat.storage.safe_load`; folders of checked entry files (the
feature cache, the geodesic store) are `geofeat.storage.entry_folder`.
"""

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
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

__all__ = [
    "atomic_folder",
    "atomic_write",
    "fsync_file",
    "fsync_folder",
    "fsync_tree",
    "probe_writable",
    "remove_dead_temporary_folders",
]


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


def atomic_write(path: str | os.PathLike, write: Callable[[Path], object], *, durable: bool = True) -> Path:
    """Write through a temporary file in the same folder, then rename it over ``path``.

    Parameters
    ----------
    path : str or os.PathLike
        The final file; its folder is created when missing.
    write : callable
        ``write(tmp_path)`` writes the content to the temporary file (what it returns is ignored).
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
        and an existing ``path`` is left as it was. A folder removed while the file was
        written (a cache being cleared) is made again and the file written once more.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        return _write_and_rename(path, write, durable)
    except FileNotFoundError:
        if path.parent.is_dir():
            raise
    log.warning("%s was removed while %s was written in it; writing it again", path.parent, path.name)
    path.parent.mkdir(parents=True, exist_ok=True)
    return _write_and_rename(path, write, durable)


def _write_and_rename(path: Path, write: Callable[[Path], object], durable: bool) -> Path:
    """One try of `atomic_write` in an existing folder."""
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
#: replaces, during the swap) of `atomic_folder`.
_FOLDER_SIBLING = re.compile(r"\.(?P<name>.+)\.(?P<role>tmp|old)-(?P<pid>\d+)-[0-9a-f]+")
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
            moved: Path | None = None  # where the old folder was set aside, once it is
            if aside is not None:
                with contextlib.suppress(FileNotFoundError):  # another process set it aside meanwhile
                    os.rename(path, aside)
                    moved = aside
            try:
                os.replace(tmp, path)
                placed = True
            except OSError as err:
                if err.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                    if moved is not None:  # put the old folder back (a later cleanup does it if this fails)
                        with contextlib.suppress(OSError):
                            os.rename(moved, path)
                    raise
                placed = False  # another process put a folder there meanwhile (newer than ours): set it aside too
            if moved is not None:
                shutil.rmtree(moved, ignore_errors=True)
            if placed:
                return
        finally:
            if aside is not None:
                with _IN_FLIGHT_LOCK:
                    _IN_FLIGHT.discard(aside)
    raise OSError(errno.EEXIST, f"{path} was written by other processes {attempts} times while this one tried to replace it")
