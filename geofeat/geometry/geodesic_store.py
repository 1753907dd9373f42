"""All-pairs geodesic matrices on disk, one checked ``.npy`` file per mesh content: `GeodesicStore`.

Evaluation and training read a target's matrix back instead of computing it again
(`geofeat.geometry.geodesic.geodesic_matrix` over ``sqrt(area)``: edge Dijkstra on a mesh,
the heat method on a point cloud);
``geofeat cache info|verify|clear`` sees the store's folder like the feature cache's.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np

from geofeat.errors import MeshError, StoreError
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.mesh import Mesh
from geofeat.storage.cache_folder import cache_dir
from geofeat.storage.entry_folder import EntryFolder, array_crc32
from geofeat.storage.files import atomic_write, probe_writable
from geofeat.storage.sizes import format_size, parse_size

__all__ = ["STORE_DTYPES", "STORE_LIMIT", "STORE_LIMIT_ENV", "STORE_VERSION", "GeodesicStore"]

log = logging.getLogger(__name__)

#: Version of the layout of `GeodesicStore` entries (part of their file names).
STORE_VERSION = "2"
#: Default size limit of a `GeodesicStore` (all its entries together), bytes.
STORE_LIMIT = 4 << 30
#: Environment variable that changes it (``"10G"``, ``"500M"``, bytes).
STORE_LIMIT_ENV = "GEOFEAT_GEODESIC_STORE_LIMIT"
#: Folders of default stores already reported as not writable (warned once per process).
_UNWRITABLE_WARNED: set[str] = set()
#: Precisions a `GeodesicStore` keeps its matrices in.
STORE_DTYPES = ("float32", "float16")
#: File name of an entry (any precision and layout version): mesh hash, dtype, version, CRC-32.
_ENTRY_PATTERN = r"[0-9a-f]{64}-(float32|float16)-v[0-9]+-([0-9a-f]{8})\.npy"
_STORE_ENTRY = re.compile(_ENTRY_PATTERN)
#: Temporary file of an entry being written (`geofeat.storage.files.atomic_write`): ``.<entry name>.<random>.tmp``.
_STORE_TEMPORARY = re.compile(rf"\.{_ENTRY_PATTERN}\.[^/]+\.tmp")


def _entry_problem(stored: np.ndarray, n: int, dtype: np.dtype, crc: str) -> str | None:
    """What is wrong with a store entry's array (expected: ``dtype``, shape (n, n), CRC-32 ``crc`` in hex), or None."""
    if stored.shape != (n, n) or stored.dtype != dtype:
        return f"holds a {stored.dtype} {stored.shape} array; expected {dtype.name} ({n}, {n})"
    if f"{array_crc32(stored):08x}" != crc:
        return f"fails its checksum (expected {crc})"
    return None


class GeodesicStore(EntryFolder):
    """All-pairs geodesic matrices on disk (over ``sqrt(area)``), one ``.npy`` file per mesh or point-cloud content.

    The matrix of a shape is `geodesic_matrix` with its evaluation method
    (`geofeat.geometry.geodesic.evaluation_method`): edge Dijkstra on a triangle mesh, the
    heat method on a point cloud (whose content hash, faces None, differs from any mesh's).

    An entry is named ``<mesh hash>-<dtype>-v<version>-<crc>.npy``: a plain NumPy file whose
    name carries the CRC-32 of its array (dtype, shape and bytes). It is written through a
    temporary file and renamed (`geofeat.storage.files.atomic_write`), so a reader sees a whole
    entry or none, with several processes too. Every read checks shape, dtype and checksum;
    a damaged entry (truncated, overwritten, bit rot) is logged, deleted and recomputed,
    never returned. Writes are not ``fsync``-ed: an entry that a power cut left empty or
    half written is such a damaged entry, found on its first read. A float32 entry read back
    is its file mapped in memory: the store only ever renames a new file over an entry or
    deletes it, which leaves a mapping intact; a file truncated or overwritten in place
    while a process holds its array would break that array (a bus error on Linux), so
    remove entries by deleting their files, never by editing them.

    `info`, `verify` and `clear` (``geofeat cache info|verify|clear``) see every entry of the
    folder, whatever its precision or layout version.

    Parameters
    ----------
    folder : str or os.PathLike, optional
        Default ``<geofeat cache>/geodesics`` (`geofeat.storage.cache_folder.cache_dir`: ``$GEOFEAT_CACHE_DIR``
        or `geofeat.set_cache_dir` move it).
    dtype : {"float32", "float16"}
        ``"float32"``: exactly the matrix of `geodesic_matrix` (evaluation; 4 V^2 bytes, 100 MB
        for 5,000 vertices). ``"float16"``: about three significant digits in half the space
        (training loss weights).
    connected : bool
        Refuse meshes in several pieces (`MeshError`): their matrices hold ``inf``.
    limit : int or str, optional
        Most bytes the folder's entries may take together (``"4G"``, see `geofeat.storage.sizes.parse_size`).
        Default ``$GEOFEAT_GEODESIC_STORE_LIMIT``, else `STORE_LIMIT` (4 GiB). Before a new
        entry is written, the least recently used entries (by modification time, which
        every read refreshes) are deleted until it fits. An entry larger than the limit, or
        than half the free disk space, is not written: its matrix is computed and returned
        in memory, with a warning.

    Notes
    -----
    A store that cannot be written (read-only, disk full, ``$GEOFEAT_CACHE_DIR`` naming a
    file): the default store (no ``folder``) logs a warning once per folder and returns the
    matrices computed in memory; a store given a ``folder`` raises `StoreError`, before any
    computation where the problem can be seen then.
    """

    label = "the geodesic store"

    def __init__(
        self,
        folder: str | os.PathLike | None = None,
        dtype: str = "float32",
        connected: bool = False,
        limit: int | str | None = None,
    ):
        if dtype not in STORE_DTYPES:
            raise MeshError(f"GeodesicStore keeps matrices in one of {STORE_DTYPES}; found dtype={dtype!r}.")
        self.explicit = folder is not None
        self.folder = Path(folder).expanduser() if folder is not None else cache_dir() / "geodesics"
        self.dtype = np.dtype(dtype)
        self.connected = bool(connected)
        env = os.environ.get(STORE_LIMIT_ENV) if limit is None else None
        name = STORE_LIMIT_ENV if env else "limit"
        self.limit = parse_size(limit if limit is not None else env or STORE_LIMIT, name, StoreError)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.folder)!r}, dtype={self.dtype.name!r})"

    @property
    def root(self) -> Path:  # type: ignore[override]  # EntryFolder only reads root: here the read-only name of folder
        """The folder (`geofeat.storage.entry_folder.EntryFolder`'s name for it)."""
        return self.folder

    def _scan(self) -> tuple[list[Path], list[Path], list[Path]]:
        entries, temporary, other = [], [], []
        if self.folder.is_dir():
            for path in self.folder.iterdir():
                regular = path.is_file() and not path.is_symlink()
                if regular and _STORE_ENTRY.fullmatch(path.name):
                    entries.append(path)
                elif regular and _STORE_TEMPORARY.fullmatch(path.name):
                    temporary.append(path)
                else:
                    other.append(path)
        return sorted(entries), sorted(temporary), sorted(other)

    def _is_sound(self, path: Path) -> bool:
        match = _STORE_ENTRY.fullmatch(path.name)
        if match is None:
            return False
        dtype, crc = match.groups()
        try:
            stored = np.load(path, mmap_mode="r")
            n = stored.shape[0] if stored.ndim == 2 else -1
            return _entry_problem(stored, n, np.dtype(dtype), crc) is None
        except (OSError, ValueError, EOFError):
            return False

    def _prefix(self, mesh: Mesh) -> str:
        return f"{mesh.hash}-{self.dtype.name}-v{STORE_VERSION}-"

    def _entries(self, mesh: Mesh) -> list[Path]:
        if not self.folder.is_dir():
            return []
        return sorted(p for p in self.folder.glob(f"{self._prefix(mesh)}*.npy") if p.is_file())

    def path(self, mesh: Mesh) -> Path | None:
        """The file of the matrix of ``mesh``, or None when not stored."""
        entries = self._entries(mesh)
        return entries[0] if entries else None

    def get(self, mesh: Mesh, widen: bool = True) -> np.ndarray | None:
        """The stored matrix of ``mesh`` (checked, as `load` returns it with ``widen``), or None when not stored; never computes."""
        for path in self._entries(mesh):
            dist = self._read(path, mesh, widen)
            if isinstance(dist, np.ndarray):
                return dist
        return None

    def ensure(self, mesh: Mesh) -> Path | None:
        """Compute and store the matrix unless a sound entry is present; returns its file.

        None when the matrix could not be stored (too large for the limit or the disk, or
        a default store that cannot be written: a warning says why).
        """
        for path in self._entries(mesh):
            if isinstance(self._read(path, mesh, widen=False), np.ndarray):  # checked, not converted
                return path
        return self._compute(mesh, widen=False)[0]

    def load(self, mesh: Mesh, widen: bool = True) -> np.ndarray:
        """The matrix of ``mesh``, read back (checked) or computed and stored.

        Parameters
        ----------
        mesh : Mesh
            V vertices.
        widen : bool
            False: a float16 store returns its values as stored (float16, half the memory
            of the widened matrix; read back, the file mapped into memory). A float32 store
            ignores it.

        Returns
        -------
        numpy.ndarray, shape (V, V), float32 (float16 for a float16 store when ``widen`` is False), read-only
            A float32 store returns exactly `geodesic_matrix` (the shape's evaluation
            method, ``normalize=True``); read back, it is the file mapped into memory (``mmap``,
            no copy: pages shared between processes, read from the page cache). A float16
            store returns its rounding, widened to float32.

        Raises
        ------
        StoreError
            A store given a folder cannot be written (read-only, disk full, a file in the way).
        """
        dist = self.get(mesh, widen)
        return dist if dist is not None else self._compute(mesh, widen)[1]

    def entry_bytes(self, n_vertices: int) -> int:
        """Size on disk of the entry of a mesh with ``n_vertices`` vertices (the ``.npy`` header included)."""
        return int(n_vertices) ** 2 * self.dtype.itemsize + 128

    def check_writable(self) -> None:
        """Raise `StoreError` unless a file can be created in the folder (created when missing)."""
        try:
            probe_writable(self.folder, prefix=".probe-", suffix=".tmp")
        except OSError as err:
            raise StoreError(self._unwritable(err)) from err

    def _unwritable(self, err: OSError) -> str:
        return (
            f"the geodesic store {self.folder} cannot be written: {err.strerror or err}. Set GEOFEAT_CACHE_DIR (or "
            "call geofeat.set_cache_dir) to a writable folder, give GeodesicStore another folder, or evaluate without "
            "the store (benchmarks/run.py --no-geodesic-store)."
        )

    def _not_kept(self, message: str) -> None:
        """A default store that cannot be written: warn once per folder (then compute in memory)."""
        if str(self.folder) not in _UNWRITABLE_WARNED:
            _UNWRITABLE_WARNED.add(str(self.folder))
            log.warning("geodesic matrices are computed in memory and not kept (this warning is shown once): %s", message)

    def _room(self, size: int) -> str | None:
        """Why an entry of ``size`` bytes cannot be written (too large for the limit or the disk), or None."""
        if size > self.limit:
            return f"larger than the store's limit of {format_size(self.limit)} ({STORE_LIMIT_ENV} changes it)"
        probe = self.folder
        while not probe.exists() and probe != probe.parent:
            probe = probe.parent
        try:
            free = shutil.disk_usage(probe).free
        except OSError:
            return None
        if size > free // 2:
            return f"larger than half the {format_size(free)} free on the disk of {self.folder}"
        return None

    def _evict(self, incoming: int) -> None:
        """Delete the least recently used entries until ``incoming`` more bytes fit under the limit."""
        stats = []
        for path in self._scan()[0]:
            try:
                info = path.stat()
            except OSError:
                continue
            stats.append((info.st_mtime, info.st_size, path))
        total = sum(size for _, size, _ in stats)
        for _, size, path in sorted(stats):
            if total + incoming <= self.limit:
                break
            log.info(
                "geodesic store over its limit of %s: removing the least recently used entry %s",
                format_size(self.limit),
                path.name,
            )
            self._remove(path)
            if not path.exists():
                total -= size

    def _compute(self, mesh: Mesh, widen: bool = True) -> tuple[Path | None, np.ndarray]:
        size = self.entry_bytes(mesh.n_vertices)
        too_large = self._room(size)
        if too_large is None and self.explicit:
            self.check_writable()  # fail before the work, not after it
        # not in the in-memory cache as well: the file is the kept copy (read back mapped, no copy)
        dist = geodesic_matrix(mesh, normalize=True, cache=False)  # Dijkstra on a mesh, heat on points
        if self.connected and not np.isfinite(dist).all():
            raise MeshError(
                f"{mesh.name!r} is not connected: its geodesic distances are infinite; give a connected mesh "
                "(geofeat.geometry.partial.largest_component_submesh keeps its largest piece)."
            )
        stored = np.ascontiguousarray(dist, dtype=self.dtype)
        if self.dtype == np.float32:
            result = dist
        elif widen:
            result = stored.astype(np.float32)
            result.flags.writeable = False
        else:
            result = stored.view()
            result.flags.writeable = False
        if too_large is not None:
            log.warning(
                "the geodesic matrix of %r (%d vertices, %s) is not kept in the geodesic store: %s; it is computed in memory",
                mesh.name,
                mesh.n_vertices,
                format_size(size),
                too_large,
            )
            return None, result
        path = self.folder / f"{self._prefix(mesh)}{array_crc32(stored):08x}.npy"

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as handle:  # a handle: np.save would append ".npy" to the temporary name
                np.save(handle, stored)

        try:
            if self.folder.is_dir():
                self._evict(size)
            atomic_write(path, write, durable=False)  # every read checks the checksum: no need to wait for the disk
        except OSError as err:
            if self.explicit:
                raise StoreError(self._unwritable(err)) from err
            self._not_kept(self._unwritable(err))
            return None, result
        return path, result

    def _read(self, path: Path, mesh: Mesh, widen: bool = True) -> np.ndarray | None:
        """The checked matrix in ``path`` (float32, or as stored when not ``widen``), or None after deleting a damaged entry."""
        n = mesh.n_vertices
        try:
            stored = np.load(path, mmap_mode="r")
            problem = _entry_problem(stored, n, self.dtype, path.stem.rsplit("-", 1)[1])
        except (OSError, ValueError, EOFError) as exc:
            problem = f"cannot be read ({exc})"
        if problem is None:
            try:
                os.utime(path)  # recently used: the last entry the limit evicts
            except OSError as err:  # a read-only store: the order of eviction does not matter there
                log.debug("cannot touch %s: %s", path, err)
            if self.dtype == np.float32 or not widen:
                # No copy: the checked pages of the file are the matrix. The store never changes
                # a file in place (it renames a new one over it or deletes it, and a mapping
                # keeps the old content), so the array stays as checked; a copy would cost a
                # fresh 113 MB allocation per 5,000-vertex matrix, slower than the checksum.
                return stored.view(np.ndarray)
            dist = stored.astype(np.float32)
            dist.flags.writeable = False
            return dist
        log.warning("geodesic store entry %s of %r %s; recomputing it", path, mesh.name, problem)
        self._remove(path)
        return None
