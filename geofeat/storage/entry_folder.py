"""Folders of checked entry files written atomically (`EntryFolder`): what the feature cache and the geodesic store share.

An entry is one file written by `geofeat.storage.files.atomic_write` and checked on read (a CRC-32
of its array, `array_crc32`); `EntryFolder` counts, verifies and clears the entries of a
folder and sweeps away the temporary files of killed writers.
"""

from __future__ import annotations

import logging
import time
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geofeat.errors import StoreError

log = logging.getLogger(__name__)

__all__ = ["STALE_TMP_SECONDS", "EntryFolder", "StoreInfo", "array_crc32"]

#: Temporary files older than this (seconds) are taken for leftovers of killed writers.
STALE_TMP_SECONDS = 3600.0


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

    def _contents(self) -> tuple[list[Path], list[Path], list[Path]]:
        """`_scan` of the folder (nothing when it does not exist yet); `error` when ``root`` is not a folder."""
        if self.root.exists() and not self.root.is_dir():
            raise self.error(
                f"{self.label} {self.root} is a file, not a folder; give the path of a folder (it is created when missing)."
            )
        return self._scan()

    def entries(self) -> list[Path]:
        """Paths of every complete entry."""
        return self._contents()[0]

    def temporary_files(self) -> list[Path]:
        """Temporary files of writers still running or killed."""
        return self._contents()[1]

    def other_paths(self) -> list[Path]:
        """What the folder holds that is neither an entry nor a temporary file (skipped by `verify` and `clear`)."""
        return self._contents()[2]

    def info(self) -> StoreInfo:
        """Counts and total size of the folder (entries only; see ``StoreInfo.other_paths``)."""
        entries, temporary, other = self._contents()
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
        entries, temporary, other = self._contents()
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
        entries, temporary, _ = self._contents()
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
