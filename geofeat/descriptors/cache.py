"""HDF5 feature cache: one small HDF5 file per entry, written atomically.

Layout: ``<root>/<key[:2]>/<key>.h5`` holding the dataset ``features`` and attributes
(the parts of the key, a CRC-32 checksum of the array, versions, creation time).

Why one file per entry rather than one big HDF5 file: HDF5 is not crash-safe while a file
is open for writing, and it cannot be written by several processes at once. A per-entry
file is written under a temporary name in the same directory, flushed to disk, then
renamed over its final name (`geofeat.storage.files.atomic_write`: ``os.replace``, atomic on POSIX
and Windows). Readers see the whole entry or none; a killed writer leaves at most a
temporary file (``.<key>.h5.<random>.tmp`` beside the entry), which
`FeatureCache.verify` and `FeatureCache.clear` sweep away; entries written before are
never touched. A damaged entry (bad CRC-32 checksum, unreadable file) is detected on read,
deleted and reported as a miss, so it is recomputed, never returned. The file is flushed
and ``fsync``-ed before the rename, and its folder after it, so that a power cut does not
leave a renamed but empty entry.

Only regular files named ``<key>.h5`` (a 64-digit hex key) in the folder ``<key[:2]>`` are
entries. Anything else in the store (a folder named ``*.h5``, a stray file) is skipped by
`FeatureCache.verify` and `FeatureCache.clear`, never counted by `FeatureCache.info` and
listed by `FeatureCache.other_paths`.

A store on a read-only file system (or without write permission) can still be read; writing
to it raises `CacheError`, which `geofeat.compute` turns into a warning (default store) or
passes on (a store the caller named).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from geofeat.errors import CacheError
from geofeat.storage import cache_folder
from geofeat.storage.entry_folder import EntryFolder, StoreInfo, array_crc32
from geofeat.storage.files import atomic_write, probe_writable

log = logging.getLogger(__name__)


def _h5py():
    """The h5py module, imported on first use: ``import geofeat`` then skips its 45 ms."""
    import h5py

    return h5py


#: What `FeatureCache.info` returns (the summary every store folder gives).
CacheInfo = StoreInfo
#: Start of the names of probe files (`FeatureCache.check_writable`); one left behind by a killed process is temporary.
TMP_PREFIX = ".tmp-"
#: File name of an entry: the 64 hex digits of its key and ``.h5``.
_ENTRY_NAME = re.compile(r"[0-9a-f]{64}\.h5")
#: Temporary file of an entry being written (`geofeat.storage.files.atomic_write`): ``.<entry name>.<random>.tmp``.
_ENTRY_TEMPORARY = re.compile(r"\.[0-9a-f]{64}\.h5\.[^/]+\.tmp")
#: Ending of the manifests that ``geofeat extract`` writes at the top of the store: not entries, left alone.
MANIFEST_SUFFIX = ".manifest.json"
_NOT_WRITABLE_HINT = (
    "Set GEOFEAT_CACHE_DIR (or call geofeat.set_cache_dir) to a writable folder, or pass cache=False to compute without caching."
)


def cache_key(mesh_hash: str, descriptor: str, params_json: str, version: str, weights_digest: str | None) -> str:
    """SHA-256 hex key of a mesh hash, descriptor name, canonical parameters, code version and weights digest."""
    parts = {"mesh": mesh_hash, "descriptor": descriptor, "params": params_json, "version": version, "weights": weights_digest}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _checksum(array: np.ndarray) -> str:
    """The entry's checksum attribute: ``"crc32:"`` and `geofeat.storage.entry_folder.array_crc32` in hex."""
    return f"crc32:{array_crc32(array):08x}"


def _features_problem(features: np.ndarray, n_rows: int | None) -> str | None:
    """Why a stored array is not the features of a mesh with ``n_rows`` vertices, or None."""
    if not isinstance(features, np.ndarray) or features.dtype != np.float32:
        return f"holds {getattr(features, 'dtype', type(features).__name__)} values, not float32 features"
    if features.ndim != 2:
        return f"holds an array of shape {features.shape}, not (V, C)"
    if n_rows is not None and features.shape[0] != n_rows:
        return f"holds {features.shape[0]} rows for a mesh of {n_rows} vertices"
    if not np.isfinite(features).all():
        return "holds NaN or infinite values"
    return None


class FeatureCache(EntryFolder):
    """A directory of HDF5 feature entries, safe with several processes.

    Parameters
    ----------
    root : str or PathLike, optional
        Directory of the store; default ``geofeat.storage.cache_folder.cache_dir() / "features"``.
    """

    label = "the feature cache"
    error = CacheError

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else cache_folder.cache_dir() / "features"

    def __repr__(self) -> str:
        return f"FeatureCache({str(self.root)!r})"

    def path(self, key: str) -> Path:
        """File of an entry."""
        return self.root / key[:2] / f"{key}.h5"

    def get(self, key: str, n_rows: int | None = None) -> np.ndarray | None:
        """The cached features for ``key``, or None when absent or damaged (a damaged entry is deleted).

        An entry is damaged when it cannot be read, its key or checksum does not match, or it
        does not hold features: a finite float32 array of shape (V, C), with ``n_rows`` rows
        when given.

        Parameters
        ----------
        key : str
            The entry's key (64 hex digits).
        n_rows : int, optional
            The number of vertices of the mesh the features are for.

        Returns
        -------
        numpy.ndarray or None
            The stored array, shape (V, C) float32, checksum verified.
        """
        path = self.path(key)
        if not path.is_file():  # absent, or something else under an entry's name (see `other_paths`)
            return None
        problem = None
        try:
            with _h5py().File(path, "r", locking=False) as fh:
                features = fh["features"][()]
                expected = fh.attrs.get("checksum")
                if fh.attrs.get("key") != key:
                    problem = "key attribute does not match the file name"
        except (OSError, KeyError, ValueError, TypeError) as err:
            problem = f"unreadable ({type(err).__name__}: {err})"
        else:
            problem = problem or _features_problem(features, n_rows)
            if problem is None and expected != _checksum(features):
                problem = "checksum mismatch"
        if problem is not None:
            log.warning("cache entry %s is damaged (%s); removing it, the features will be recomputed", path, problem)
            self._remove(path)
            return None
        return features

    def put(self, key: str, features: np.ndarray, meta: Mapping[str, str | None] | None = None) -> Path:
        """Store ``features`` (V, C) under ``key`` atomically; returns the entry's path.

        ``meta`` values are saved as string attributes (descriptor name, parameters, ...; None as ``""``).

        Raises
        ------
        CacheError
            The store cannot be written (read-only file system, no permission, disk full);
            nothing is left behind.
        """
        path = self.path(key)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise CacheError(f"cannot create cache directory {path.parent}: {err}. {_NOT_WRITABLE_HINT}") from err

        def write(tmp: Path) -> None:
            with _h5py().File(tmp, "w", locking=False) as fh:
                fh.create_dataset("features", data=features)
                fh.attrs["key"] = key
                fh.attrs["checksum"] = _checksum(features)
                fh.attrs["created"] = time.time()
                for name, value in (meta or {}).items():
                    fh.attrs[name] = "" if value is None else str(value)
                fh.flush()

        try:
            return atomic_write(path, write)  # the temporary file is removed on any failure
        except FileNotFoundError as err:
            if path.parent.is_dir():  # not a removed folder: a path that cannot be made
                raise CacheError(f"cannot write the cache entry {path}: {err}. {_NOT_WRITABLE_HINT}") from err
            raise CacheError(
                f"cannot write the cache entry {path}: its folder was removed while it was written, twice (is "
                "'geofeat cache clear' or another process emptying the cache?). Run again once it is done."
            ) from err
        except OSError as err:
            raise CacheError(f"cannot write the cache entry {path}: {err}. {_NOT_WRITABLE_HINT}") from err

    def check_writable(self, hint: str = _NOT_WRITABLE_HINT) -> None:
        """Raise `CacheError` unless a file can be created in the store (created when missing).

        Parameters
        ----------
        hint : str
            How to fix it, in the caller's terms (default: the settings of `geofeat.compute`).

        Raises
        ------
        CacheError
            Read-only file system, no permission or no space; the message says how to fix it.
        """
        try:
            probe_writable(self.root, prefix=f"{TMP_PREFIX}probe-")
        except OSError as err:
            raise CacheError(f"the feature cache {self.root} is not writable: {err}. {hint}") from err

    def _scan(self) -> tuple[list[Path], list[Path], list[Path]]:
        """One pass over the store: entry files, temporary files and everything else (sorted)."""
        entries: list[Path] = []
        temporary: list[Path] = []
        other: list[Path] = []
        if not self.root.is_dir():
            return entries, temporary, other
        for folder in self.root.iterdir():
            if not folder.is_dir() or folder.is_symlink():
                regular = folder.is_file() and not folder.is_symlink()
                if regular and folder.name.endswith(MANIFEST_SUFFIX):
                    continue  # a manifest of geofeat extract, kept beside the entries it lists
                (temporary if regular and folder.name.startswith(TMP_PREFIX) else other).append(folder)
                continue
            for path in folder.iterdir():
                regular = path.is_file() and not path.is_symlink()
                if regular and (_ENTRY_TEMPORARY.fullmatch(path.name) or path.name.startswith(TMP_PREFIX)):
                    temporary.append(path)
                elif regular and _ENTRY_NAME.fullmatch(path.name) and path.name[:2] == folder.name:
                    entries.append(path)
                else:
                    other.append(path)
        return sorted(entries), sorted(temporary), sorted(other)

    def _is_sound(self, path: Path) -> bool:
        try:
            with _h5py().File(path, "r", locking=False) as fh:
                return fh.attrs.get("checksum") == _checksum(fh["features"][()]) and fh.attrs.get("key") == path.stem
        except (OSError, KeyError, ValueError):
            return False
