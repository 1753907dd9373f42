"""HDF5 feature cache: one small HDF5 file per entry, written atomically.

Layout: ``<root>/<key[:2]>/<key>.h5`` holding the dataset ``features`` and attributes
(the parts of the key, a CRC-32 checksum of the array, versions, creation time).

Why one file per entry rather than one big HDF5 file: HDF5 is not crash-safe while a file
is open for writing, and it cannot be written by several processes at once. A per-entry
file is written under a temporary name in the same directory, flushed to disk, then
renamed over its final name (``os.replace``, atomic on POSIX and Windows). Readers see
the whole entry or none; a killed writer leaves at most a temporary file, which
`FeatureCache.verify` and `FeatureCache.clear` sweep away; entries written before are
never touched. A damaged entry (bad CRC-32 checksum, unreadable file) is detected on read,
deleted and reported as a miss, so it is recomputed, never returned.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
import uuid
import zlib
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from geofeat import config
from geofeat.errors import CacheError

log = logging.getLogger(__name__)

TMP_PREFIX = ".tmp-"
#: Temporary files older than this (seconds) are taken for leftovers of killed writers.
STALE_TMP_SECONDS = 3600.0


def cache_key(mesh_hash: str, descriptor: str, params_json: str, version: str, weights_digest: str | None) -> str:
    """SHA-256 hex key of a mesh hash, descriptor name, canonical parameters, code version and weights digest."""
    parts = {"mesh": mesh_hash, "descriptor": descriptor, "params": params_json, "version": version, "weights": weights_digest}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _checksum(array: np.ndarray) -> str:
    """CRC-32 of the array's dtype, shape and bytes: catches truncation, bit rot and garbage, and is fast."""
    header = f"{array.dtype.str}{array.shape}".encode()
    return f"crc32:{zlib.crc32(np.ascontiguousarray(array).data, zlib.crc32(header)):08x}"


@dataclass(frozen=True)
class CacheInfo:
    """Summary of a cache directory."""

    root: Path
    entries: int
    bytes: int
    temporary_files: int


class FeatureCache:
    """A directory of HDF5 feature entries, safe with several processes.

    Parameters
    ----------
    root : str or PathLike, optional
        Directory of the store; default ``geofeat.config.cache_dir() / "features"``.
    """

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else config.cache_dir() / "features"

    def __repr__(self) -> str:
        return f"FeatureCache({str(self.root)!r})"

    def path(self, key: str) -> Path:
        """File of an entry."""
        return self.root / key[:2] / f"{key}.h5"

    def get(self, key: str) -> np.ndarray | None:
        """The cached features for ``key``, or None when absent or damaged (a damaged entry is deleted).

        Returns
        -------
        numpy.ndarray or None
            The stored array, shape (V, C) float32, checksum verified.
        """
        path = self.path(key)
        if not path.exists():
            return None
        problem = None
        try:
            with h5py.File(path, "r", locking=False) as fh:
                features = fh["features"][()]
                expected = fh.attrs.get("checksum")
                if fh.attrs.get("key") != key:
                    problem = "key attribute does not match the file name"
        except (OSError, KeyError, ValueError) as err:
            problem = f"unreadable ({type(err).__name__}: {err})"
        else:
            if problem is None and expected != _checksum(features):
                problem = "checksum mismatch"
        if problem is not None:
            log.warning("cache entry %s is damaged (%s); removing it, the features will be recomputed", path, problem)
            self._remove(path)
            return None
        return features

    def put(self, key: str, features: np.ndarray, meta: dict[str, str] | None = None) -> Path:
        """Store ``features`` (V, C) under ``key`` atomically; returns the entry's path.

        ``meta`` values are saved as string attributes (descriptor name, parameters, ...).
        """
        path = self.path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise CacheError(
                f"cannot create cache directory {path.parent}: {err}. Set GEOFEAT_CACHE_DIR to a writable place."
            ) from err
        tmp = path.parent / f"{TMP_PREFIX}{os.getpid()}-{uuid.uuid4().hex}.h5"
        try:
            with h5py.File(tmp, "w", locking=False) as fh:
                fh.create_dataset("features", data=features)
                fh.attrs["key"] = key
                fh.attrs["checksum"] = _checksum(features)
                fh.attrs["created"] = time.time()
                for name, value in (meta or {}).items():
                    fh.attrs[name] = "" if value is None else str(value)
                fh.flush()
            with open(tmp, "rb+") as raw:
                os.fsync(raw.fileno())
            os.replace(tmp, path)
        except BaseException:
            self._remove(tmp)
            raise
        return path

    def entries(self) -> list[Path]:
        """Paths of every complete entry."""
        if not self.root.is_dir():
            return []
        return sorted(p for p in self.root.glob("*/*.h5") if not p.name.startswith(TMP_PREFIX))

    def temporary_files(self) -> list[Path]:
        """Temporary files of writers still running or killed."""
        if not self.root.is_dir():
            return []
        return sorted(self.root.glob(f"*/{TMP_PREFIX}*"))

    def info(self) -> CacheInfo:
        """Counts and total size of the store."""
        entries = self.entries()
        return CacheInfo(self.root, len(entries), sum(p.stat().st_size for p in entries), len(self.temporary_files()))

    def verify(self, remove: bool = True) -> tuple[int, list[Path]]:
        """Check every entry's checksum.

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
        for path in self.entries():
            try:
                with h5py.File(path, "r", locking=False) as fh:
                    good = fh.attrs.get("checksum") == _checksum(fh["features"][()]) and fh.attrs.get("key") == path.stem
            except (OSError, KeyError, ValueError):
                good = False
            if good:
                n_ok += 1
            else:
                damaged.append(path)
                if remove:
                    self._remove(path)
        if remove:
            now = time.time()
            for tmp in self.temporary_files():
                if now - tmp.stat().st_mtime > STALE_TMP_SECONDS:
                    self._remove(tmp)
        return n_ok, damaged

    def clear(self) -> int:
        """Delete every entry and temporary file; returns the number of entries removed."""
        entries = self.entries()
        for path in entries + self.temporary_files():
            self._remove(path)
        return len(entries)

    @staticmethod
    def _remove(path: Path) -> None:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
