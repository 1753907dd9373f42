"""`compute` and `compute_many`: features of one mesh or of a collection, through the feature cache.

`compute_each` is the one loop of a descriptor over many meshes with the cache: `compute_many`
collects its arrays and ``geofeat extract`` (`geofeat.apps.extract`) writes its records.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass

import numpy as np

from geofeat._version import __version__
from geofeat.checks import check_integer
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.cache import FeatureCache, cache_key
from geofeat.descriptors.registry import as_descriptor
from geofeat.errors import CacheError, GeofeatError
from geofeat.mesh import Mesh, as_mesh
from geofeat.progress import progress_bar

log = logging.getLogger(__name__)

CacheArg = bool | str | os.PathLike | FeatureCache | None
MeshLike = Mesh | str | os.PathLike | tuple | object
DescriptorArg = str | Descriptor

#: Roots of default stores already reported as not writable (warned once per process).
_UNWRITABLE_WARNED: set[str] = set()


def resolve_cache(cache: CacheArg) -> FeatureCache | None:
    """Turn the ``cache`` argument into a store (or None for no caching).

    ``True``: the default store; ``False``/``None``: no cache; a path: a store there; a
    `FeatureCache`: itself.
    """
    if cache is True:
        return FeatureCache()
    if cache is False or cache is None:
        return None
    if isinstance(cache, FeatureCache):
        return cache
    if isinstance(cache, (str, os.PathLike)):
        return FeatureCache(cache)
    raise CacheError(f"cache must be True, False, a directory path or a FeatureCache; found {type(cache).__name__}.")


def entry_key(descriptor: Descriptor, mesh: Mesh) -> str:
    """The feature-store key of ``descriptor`` on ``mesh`` (see `geofeat.descriptors.cache.cache_key`): what `compute` looks up."""
    return cache_key(mesh.hash, descriptor.name, descriptor.params_json(), descriptor.version, descriptor.weights_digest())


def compute(mesh_or_path: MeshLike, descriptor: DescriptorArg, cache: CacheArg = True, **params) -> np.ndarray:
    """Per-vertex features of a mesh.

    Parameters
    ----------
    mesh_or_path : Mesh, path, (verts, faces) or trimesh object
        A `Mesh`; a ``.off``/``.obj``/``.ply`` file read with `load_mesh`; a pair
        ``(verts, faces)`` of arrays (``faces`` None for a point cloud); a
        ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (see `geofeat.mesh.as_mesh`).
    descriptor : str or Descriptor
        A registered descriptor name (see `geofeat.descriptors()`), built with ``**params``
        on every call, or a descriptor instance (``WKS(n_descr=64)``,
        `geofeat.descriptors.make_descriptor`), used as it is. A model-backed descriptor
        (DINOv2, DINOv3, GeoLoRA) loads its weights once per instance: build it once and
        pass the instance for every mesh.
    cache : bool, path or FeatureCache
        Where to look up and store the result; ``False`` computes without caching. When the
        default store (``True``) cannot be written (a read-only file system), the features
        are computed without caching and a warning is logged once. A store named here (a
        path or a `FeatureCache`) that cannot be written raises `CacheError` instead.
    **params
        Descriptor parameters with a name (an unknown one raises an error listing the valid
        ones); none with an instance. NumPy scalars are accepted; booleans must be booleans.

    Returns
    -------
    numpy.ndarray, shape (V, dim), float32, C-contiguous
        Finite values; non-finite output raises `DescriptorError` and is never cached.

    Raises
    ------
    MeshError
        An input that is not a mesh (the message lists what is accepted) or a malformed one.
    DescriptorError
        Unknown descriptor or parameter, bad parameter value, parameters given with an
        instance, non-finite features.
    CacheError
        A store named by ``cache`` cannot be written.
    """
    mesh = as_mesh(mesh_or_path)
    descriptor = as_descriptor(descriptor, **params)
    features, _, _ = lookup_or_compute(descriptor, mesh, resolve_cache(cache), explicit=cache is not True)
    return features


def lookup_or_compute(
    descriptor: Descriptor, mesh: Mesh, store: FeatureCache | None, explicit: bool = True
) -> tuple[np.ndarray, str | None, bool]:
    """The features of ``descriptor`` on ``mesh``: read from ``store``, else computed and stored.

    Parameters
    ----------
    descriptor : Descriptor
    mesh : Mesh
    store : FeatureCache or None
        None: compute without caching.
    explicit : bool
        True: the caller named the store, which must be writable (`CacheError` before the
        work, or when the write fails). False (the default store): a failed write logs a
        warning once and the features are returned uncached.

    Returns
    -------
    features : numpy.ndarray, shape (V, dim), float32, C-contiguous
    key : str or None
        The store key (`entry_key`); None without a store.
    present : bool
        True when the features were read from the store.
    """
    if store is None:
        return descriptor(mesh), None, False
    key = entry_key(descriptor, mesh)
    hit = store.get(key, n_rows=mesh.n_vertices)
    if hit is not None:
        log.debug("cache hit %s for %s on %r", key[:12], descriptor.name, mesh.name)
        return np.ascontiguousarray(hit, dtype=np.float32), key, True
    if explicit:
        store.check_writable()  # fail before the work, not after it
    features = descriptor(mesh)
    meta = {
        "mesh_hash": mesh.hash,
        "mesh_name": mesh.name,
        "descriptor": descriptor.name,
        "params": descriptor.params_json(),
        "descriptor_version": descriptor.version,
        "weights_digest": descriptor.weights_digest(),
        "geofeat_version": __version__,
    }
    try:
        store.put(key, features, meta)
    except CacheError as err:
        if explicit:
            raise
        root = str(store.root)
        if root not in _UNWRITABLE_WARNED:
            _UNWRITABLE_WARNED.add(root)
            log.warning("features are computed without caching (this warning is shown once): %s", err)
    return features, key, False


@dataclass(frozen=True, eq=False)
class Computed:
    """One shape's outcome in `compute_each`.

    Attributes
    ----------
    index : int
        Position of the shape in the input.
    status : {"computed", "present", "failed"}
        ``present``: read from the store.
    features : numpy.ndarray or None
        Shape (V, dim), float32; None when failed.
    key : str or None
        The store key; None without a store or when failed before it was known.
    mesh_hash : str or None
        The mesh's content hash; None when the mesh could not be read.
    error : GeofeatError or None
        Why it failed.
    seconds : float
        Time spent on this shape (reading the mesh included).
    """

    index: int
    status: str
    features: np.ndarray | None = None
    key: str | None = None
    mesh_hash: str | None = None
    error: GeofeatError | None = None
    seconds: float = 0.0


def compute_each(
    meshes_or_paths: Sequence[MeshLike],
    descriptor: Descriptor,
    store: FeatureCache | None,
    *,
    explicit: bool = True,
    n_jobs: int = 1,
    progress: bool = True,
    desc: str | None = None,
) -> Iterator[Computed]:
    """`lookup_or_compute` over a collection: one `Computed` per shape as it is done.

    A shape that fails with a `GeofeatError` (unreadable mesh, non-finite features, a failed
    write to a named store) gives a ``"failed"`` outcome; the others go on.

    Parameters
    ----------
    meshes_or_paths : sequence of Mesh, path, (verts, faces) or trimesh object
        The shapes (see `compute`); paths are read one at a time, in the worker that computes them.
    descriptor : Descriptor
        Used for every shape (with ``n_jobs > 1`` each worker gets a copy, built once per worker).
    store : FeatureCache or None
        See `lookup_or_compute`, as ``explicit``.
    n_jobs : int
        Worker processes; 1 computes in this process, in input order. Workers are started
        with ``spawn`` (safe with PyTorch and OpenMP) and yield in completion order.
    progress : bool
        Show a progress bar.
    desc : str, optional
        The bar's label; default ``"<descriptor name> features"``.

    Yields
    ------
    Computed
    """
    n_jobs = check_integer(n_jobs, "n_jobs", low=1, expected="a positive integer number of processes")
    items = list(meshes_or_paths)
    bar = progress_bar(total=len(items), desc=desc or f"{descriptor.name} features", unit="shape", show=progress)
    with bar:
        if n_jobs == 1 or len(items) <= 1:
            for index, item in enumerate(items):
                outcome = _compute_one(index, item, descriptor, store, explicit)
                bar.update()
                yield outcome
            return
        context = multiprocessing.get_context("spawn")
        with (
            _one_thread_per_worker(),
            ProcessPoolExecutor(
                max_workers=min(n_jobs, len(items)),
                mp_context=context,
                initializer=_start_worker,
                initargs=(descriptor, store, explicit),
            ) as pool,
        ):
            futures = [pool.submit(_worker_compute, index, item) for index, item in enumerate(items)]
            try:
                for future in as_completed(futures):
                    bar.update()
                    yield future.result()
            finally:  # a caller that stops early (compute_many on a failure) starts no further shape
                for future in futures:
                    future.cancel()


def _compute_one(index: int, item: MeshLike, descriptor: Descriptor, store: FeatureCache | None, explicit: bool) -> Computed:
    start = time.perf_counter()
    mesh = None
    try:
        mesh = as_mesh(item)
        features, key, present = lookup_or_compute(descriptor, mesh, store, explicit)
    except GeofeatError as err:
        return Computed(
            index, "failed", mesh_hash=None if mesh is None else mesh.hash, error=err, seconds=time.perf_counter() - start
        )
    status = "present" if present else "computed"
    return Computed(index, status, features, key, mesh.hash, seconds=time.perf_counter() - start)


#: The descriptor and store of this worker process (`compute_each` with ``n_jobs > 1``).
_WORKER: tuple[Descriptor, FeatureCache | None, bool] | None = None


def _start_worker(descriptor: Descriptor, store: FeatureCache | None, explicit: bool) -> None:
    global _WORKER
    _WORKER = (descriptor, store, explicit)


def _worker_compute(index: int, item: MeshLike) -> Computed:
    descriptor, store, explicit = _WORKER
    return _compute_one(index, item, descriptor, store, explicit)


def compute_many(
    meshes_or_paths: Sequence[MeshLike],
    descriptor: DescriptorArg,
    cache: CacheArg = True,
    n_jobs: int = 1,
    progress: bool = True,
    **params,
) -> list[np.ndarray]:
    """`compute` over a collection, optionally in several processes, with a progress bar.

    Parameters
    ----------
    meshes_or_paths : sequence of Mesh, path, (verts, faces) or trimesh object
        The shapes (see `compute`).
    descriptor, cache, **params
        As for `compute`; the descriptor is built (and its parameters checked) once, before
        any work starts, and used for every shape.
    n_jobs : int
        Worker processes; 1 computes in this process. Workers are started with ``spawn``
        (safe with PyTorch and OpenMP), which costs about a second before the first result.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    list of numpy.ndarray
        One (V_i, dim) float32 array per input, in input order.

    Raises
    ------
    GeofeatError
        The first failure (as `compute` raises it); no further shape is started.
    """
    descriptor = as_descriptor(descriptor, **params)  # unknown names or bad parameters fail here, not in a worker
    items = list(meshes_or_paths)
    results: list[np.ndarray | None] = [None] * len(items)
    outcomes = compute_each(items, descriptor, resolve_cache(cache), explicit=cache is not True, n_jobs=n_jobs, progress=progress)
    with contextlib.closing(outcomes):
        for outcome in outcomes:
            if outcome.error is not None:
                raise outcome.error
            results[outcome.index] = outcome.features
    return results


_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextlib.contextmanager
def _one_thread_per_worker():
    """Spawned workers inherit one BLAS/OpenMP thread each (unless the user set these variables).

    Several workers each running a BLAS thread pool as wide as the machine oversubscribe
    the cores; with OpenBLAS's spinning threads that made two workers 6x slower than one.
    """
    saved = {name: os.environ.get(name) for name in _THREAD_VARIABLES}
    for name in _THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
