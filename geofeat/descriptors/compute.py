"""`compute`: one call from a mesh (or file) and a descriptor name to cached features."""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

from geofeat._version import __version__
from geofeat.checks import canonical, check_integer
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.cache import FeatureCache, cache_key
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import CacheError
from geofeat.lru import LRUCache
from geofeat.mesh import Mesh, as_mesh
from geofeat.progress import progress_bar

log = logging.getLogger(__name__)

CacheArg = bool | str | os.PathLike | FeatureCache | None
MeshLike = Mesh | str | os.PathLike | tuple | object

#: Roots of default stores already reported as not writable (warned once per process).
_UNWRITABLE_WARNED: set[str] = set()

#: Descriptors kept alive between calls, so that a model is loaded once per process, not per mesh.
_RECENT_SIZE = 4
_RECENT_DESCRIPTORS: LRUCache[tuple[str, str], Descriptor] = LRUCache(lambda: _RECENT_SIZE)


def reusable_descriptor(name: str, **params) -> Descriptor:
    """`make_descriptor`, reusing the instance of a recent call with the same name and parameters.

    Model-backed descriptors load their weights on first use and keep them; reusing the
    instance saves that load on every further mesh. Weights files changed on disk during
    the process are not re-read (call `clear_descriptors`).
    """
    key = (name, json.dumps(canonical(params), sort_keys=True, default=str))
    return _RECENT_DESCRIPTORS.get_or_compute(key, lambda: make_descriptor(name, **params))


def clear_descriptors() -> None:
    """Forget the descriptors (and their loaded models) kept by `compute`."""
    _RECENT_DESCRIPTORS.clear()


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


def compute(mesh_or_path: MeshLike, name: str, cache: CacheArg = True, **params) -> np.ndarray:
    """Per-vertex features of a mesh.

    Parameters
    ----------
    mesh_or_path : Mesh, path, (verts, faces) or trimesh object
        A `Mesh`; a ``.off``/``.obj``/``.ply`` file read with `load_mesh`; a pair
        ``(verts, faces)`` of arrays (``faces`` None for a point cloud); a
        ``trimesh.Trimesh`` or ``trimesh.PointCloud`` (see `geofeat.mesh.as_mesh`).
    name : str
        Registered descriptor name (see `geofeat.descriptors()`).
    cache : bool, path or FeatureCache
        Where to look up and store the result; ``False`` computes without caching. When the
        default store (``True``) cannot be written (a read-only file system), the features
        are computed without caching and a warning is logged once. A store named here (a
        path or a `FeatureCache`) that cannot be written raises `CacheError` instead.
    **params
        Descriptor parameters (an unknown one raises an error listing the valid ones).
        NumPy scalars are accepted; booleans must be booleans.

    Returns
    -------
    numpy.ndarray, shape (V, dim), float32, C-contiguous
        Finite values; non-finite output raises `DescriptorError` and is never cached.

    Raises
    ------
    MeshError
        An input that is not a mesh (the message lists what is accepted) or a malformed one.
    DescriptorError
        Unknown descriptor or parameter, bad parameter value, non-finite features.
    CacheError
        A store named by ``cache`` cannot be written.
    """
    mesh = as_mesh(mesh_or_path)
    descriptor = reusable_descriptor(name, **params)
    store = resolve_cache(cache)
    if store is None:
        return descriptor(mesh)
    params_json = descriptor.params_json()
    weights = descriptor.weights_digest()
    key = entry_key(descriptor, mesh)
    hit = store.get(key, n_rows=mesh.n_vertices)
    if hit is not None:
        log.debug("cache hit %s for %s on %r", key[:12], descriptor.name, mesh.name)
        return np.ascontiguousarray(hit, dtype=np.float32)
    explicit = cache is not True
    if explicit:
        store.check_writable()  # fail before the work, not after it
    features = descriptor(mesh)
    meta = {
        "mesh_hash": mesh.hash,
        "mesh_name": mesh.name,
        "descriptor": descriptor.name,
        "params": params_json,
        "descriptor_version": descriptor.version,
        "weights_digest": weights,
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
    return features


def compute_many(
    meshes_or_paths: Sequence[MeshLike],
    name: str,
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
    name, cache, **params
        As for `compute` (the parameters are checked once, before any work starts).
    n_jobs : int
        Worker processes; 1 computes in this process. Workers are started with ``spawn``
        (safe with PyTorch and OpenMP), which costs about a second before the first result.
    progress : bool
        Show a tqdm progress bar.

    Returns
    -------
    list of numpy.ndarray
        One (V_i, dim) float32 array per input, in input order.
    """
    make_descriptor(name, **params)  # unknown names or bad parameters fail here, not in a worker
    n_jobs = check_integer(n_jobs, "n_jobs", low=1, expected="a positive integer number of processes")
    items = list(meshes_or_paths)
    bar = progress_bar(total=len(items), desc=f"{name} features", unit="shape", show=progress)
    results: list[np.ndarray | None] = [None] * len(items)
    with bar:
        if n_jobs == 1:
            for i, item in enumerate(items):
                results[i] = compute(item, name, cache=cache, **params)
                bar.update()
        else:
            context = multiprocessing.get_context("spawn")
            with (
                _one_thread_per_worker(),
                ProcessPoolExecutor(max_workers=min(n_jobs, len(items)) or 1, mp_context=context) as pool,
            ):
                futures = {pool.submit(compute, item, name, cache, **params): i for i, item in enumerate(items)}
                for future in as_completed(futures):
                    results[futures[future]] = future.result()
                    bar.update()
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
