"""A descriptor over a collection: `compute_each` (one outcome per shape) and `compute_many` (the arrays).

`compute_each` is the one loop of a descriptor over many meshes with the feature cache:
`compute_many` collects its arrays and ``geofeat extract`` (`geofeat.apps.extract`) writes its
records. It picks one of three schedulers: inline, reading and preparing ahead in a thread
(`default_prefetch`), or forked worker processes (``n_jobs``).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import threading
import time
from collections import deque
from collections.abc import Generator, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from typing import cast

import numpy as np

from geofeat.checks import check_integer
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.cache import FeatureCache
from geofeat.descriptors.compute import CacheArg, DescriptorArg, FeatureStorage, MeshLike, StoreLookup, resolve_cache
from geofeat.descriptors.registry import as_descriptor
from geofeat.errors import GeofeatError
from geofeat.mesh import Mesh, as_mesh
from geofeat.runtime.processes import end_with_parent
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)


#: `_Ready`'s ``prepared`` when nothing was prepared ahead (None is a valid result of ``prepare``).
_NOT_PREPARED = object()


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


#: Shapes read and prepared ahead by `compute_each` for a descriptor that prepares work (`default_prefetch`).
DEFAULT_PREFETCH = 2


def default_prefetch(descriptor: Descriptor) -> int:
    """`compute_each`'s ``prefetch`` when none is given: `DEFAULT_PREFETCH` for a descriptor that prepares work ahead, else 0.

    A descriptor prepares work when its class overrides `Descriptor.prepare` (the DINO
    descriptors: cameras and renders). For the others read-ahead would only read the mesh
    files early, a small gain that costs a thread.
    """
    return DEFAULT_PREFETCH if type(descriptor).prepare is not Descriptor.prepare else 0


def compute_each(
    meshes_or_paths: Sequence[MeshLike],
    descriptor: Descriptor,
    store: FeatureCache | None,
    *,
    explicit: bool = True,
    n_jobs: int = 1,
    prefetch: int | None = None,
    progress: bool = True,
    desc: str | None = None,
) -> Generator[Computed, None, None]:
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
    prefetch : int or None
        With ``n_jobs == 1``: how many shapes a background thread reads, looks up in the
        store and, when their entry is missing, prepares (``descriptor.prepare``) ahead of
        the shape being computed, so that the next shapes' files are read and (for the DINO
        descriptors) their views rendered while this one is encoded; a computed shape's entry
        is then written by another thread while the next one is computed, and its outcome
        comes once it is written. 0: none, every step in this thread. None:
        `default_prefetch` (2 for the DINO descriptors, 0 for the others). The outcomes are
        the same either way. Memory: up to ``prefetch + 1``
        shapes' prepared work is held at once; for a DINO descriptor that is every rendered
        view of a shape on its device (with 49 views of 512 x 512 pixels: the images as the
        backbone sees them, the pixels that reach a vertex and where they go, about 0.2 GB a
        shape).
        Ignored with ``n_jobs > 1``.
    progress : bool
        Show a progress bar.
    desc : str, optional
        The bar's label; default ``"<descriptor name> features"``.

    Yields
    ------
    Computed

    Notes
    -----
    The read-ahead thread stops when the loop ends, raises or is closed (``close()`` on the
    generator, as `compute_many` does at the first failure): shapes not started are
    dropped, a shape being prepared is finished, and the thread has ended when the
    generator is closed. An exception from it other than a `GeofeatError` is raised when
    its shape's turn comes.
    """
    n_jobs = check_integer(n_jobs, "n_jobs", low=1, expected="a positive integer number of processes")
    if prefetch is None:
        prefetch = default_prefetch(descriptor)
    prefetch = check_integer(prefetch, "prefetch", low=0, expected="a number of shapes >= 0 (0: no read-ahead)")
    items = list(meshes_or_paths)
    storage = FeatureStorage(store, required=explicit)
    if n_jobs > 1 and len(items) > 1:
        outcomes = _in_workers(items, descriptor, storage, n_jobs)
    elif prefetch > 0:
        outcomes = _read_ahead(items, descriptor, storage, prefetch)
    else:
        outcomes = _inline(items, descriptor, storage)
    bar = progress_bar(total=len(items), desc=desc or f"{descriptor.name} features", unit="shape", show=progress)
    with bar, contextlib.closing(outcomes):
        for outcome in outcomes:
            bar.update()
            yield outcome


def _inline(items: list, descriptor: Descriptor, storage: FeatureStorage) -> Generator[Computed, None, None]:
    """`compute_each` in this thread, one shape after the other, in input order."""
    for index, item in enumerate(items):
        yield _compute_one(index, item, descriptor, storage)


def _in_workers(items: list, descriptor: Descriptor, storage: FeatureStorage, n_jobs: int) -> Generator[Computed, None, None]:
    """`compute_each` in up to ``n_jobs`` spawned worker processes, in completion order.

    A caller that stops early (`compute_many` on a failure) starts no further shape: the
    shapes not started are cancelled when the generator is closed.
    """
    context = multiprocessing.get_context("spawn")
    with (
        _one_thread_per_worker(),
        ProcessPoolExecutor(
            max_workers=min(n_jobs, len(items)),
            mp_context=context,
            initializer=_start_worker,
            initargs=(os.getpid(), descriptor, storage),
        ) as pool,
    ):
        futures = [pool.submit(_worker_compute, index, item) for index, item in enumerate(items)]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:
            for future in futures:
                future.cancel()


def _compute_one(index: int, item: MeshLike, descriptor: Descriptor, storage: FeatureStorage) -> Computed:
    """The outcome of shape ``index``: read, looked up in the store, else computed and written."""
    start = time.perf_counter()
    mesh = None
    try:
        mesh = as_mesh(item)
        features, key, present = storage.lookup_or_compute(descriptor, mesh)
    except GeofeatError as err:
        return Computed(
            index, "failed", mesh_hash=None if mesh is None else mesh.hash, error=err, seconds=time.perf_counter() - start
        )
    status = "present" if present else "computed"
    return Computed(index, status, features, key, mesh.hash, seconds=time.perf_counter() - start)


@dataclass(frozen=True, eq=False)
class _Ready:
    """One shape read, looked up and (when its entry is missing) prepared by the read-ahead thread."""

    mesh: Mesh | None = None
    found: StoreLookup | None = None
    prepared: object = _NOT_PREPARED
    error: GeofeatError | None = None
    seconds: float = 0.0


def _read_ahead(items: list, descriptor: Descriptor, storage: FeatureStorage, depth: int) -> Generator[Computed, None, None]:
    """`_compute_one` over ``items`` in input order, each shape read and prepared by a thread up to ``depth`` shapes ahead.

    A computed shape's entry is written by a second thread while the next shape is
    computed; its outcome is given once the write has ended (one outcome behind the
    computation), and a write still running when the loop stops is finished before it returns.
    """
    stop = threading.Event()

    def ready(item: MeshLike) -> _Ready:  # on the read-ahead thread
        start = time.perf_counter()
        mesh = None
        try:
            mesh = as_mesh(item)
            found = storage.look_up(descriptor, mesh)
            if found.features is not None or stop.is_set():  # present, or the consumer has stopped
                return _Ready(mesh, found, seconds=time.perf_counter() - start)
            prepared = descriptor.prepare(mesh)
        except GeofeatError as err:
            return _Ready(mesh, error=err, seconds=time.perf_counter() - start)
        return _Ready(mesh, found, prepared, seconds=time.perf_counter() - start)

    stored: set[str] = set()  # keys written by this loop (a mesh given twice is present the second time)
    pending: deque[Future] = deque()
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="geofeat-read-ahead")
    writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="geofeat-write")
    writing: _Writing | None = None  # the entry being written and its shape's outcome
    try:
        submitted = 0
        for index in range(len(items)):
            while submitted < len(items) and submitted <= index + depth:  # shape `index` and `depth` more
                pending.append(pool.submit(ready, items[submitted]))
                submitted += 1
            try:
                done = pending.popleft().result()
                if writing is not None and done.found is not None and done.found.key == writing.key:
                    outcome, writing = writing.outcome(stored), None  # the same mesh again: its entry first
                    yield outcome
                result = _compute_ready(index, done, descriptor, storage, stored, writer)
            except Exception:  # a bug (not a GeofeatError): raised in its shape's turn, after the shape before it
                if writing is not None:
                    outcome, writing = writing.outcome(stored), None
                    yield outcome
                raise
            if writing is not None:
                outcome, writing = writing.outcome(stored), None
                yield outcome
            if isinstance(result, _Writing):
                writing = result
            else:
                yield result
        if writing is not None:
            outcome, writing = writing.outcome(stored), None
            yield outcome
    finally:
        stop.set()
        pool.shutdown(wait=True, cancel_futures=True)
        writer.shutdown(wait=True)  # a write still running when the loop stopped is finished: nothing computed is lost


@dataclass
class _Writing:
    """A computed shape whose entry a writer thread is writing (`_read_ahead`)."""

    index: int
    features: np.ndarray
    key: str | None
    mesh_hash: str
    future: Future
    seconds: float  # before the write
    started: float  # when the write was handed over

    def outcome(self, stored: set[str]) -> Computed:
        """The shape's `Computed` once its entry is written: ``"failed"`` when the write raised a `GeofeatError`."""
        try:
            self.future.result()
        except GeofeatError as err:
            seconds = self.seconds + time.perf_counter() - self.started
            return Computed(self.index, "failed", mesh_hash=self.mesh_hash, error=err, seconds=seconds)
        if self.key is not None:
            stored.add(self.key)
        seconds = self.seconds + time.perf_counter() - self.started
        return Computed(self.index, "computed", self.features, self.key, self.mesh_hash, seconds=seconds)


def _compute_ready(
    index: int,
    done: _Ready,
    descriptor: Descriptor,
    storage: FeatureStorage,
    stored: set[str],
    writer: ThreadPoolExecutor,
) -> Computed | _Writing:
    """The outcome of a shape from `_read_ahead` (on the consumer's thread), or its features with the write handed to ``writer``.

    Without a store there is nothing to write, so a computed shape's outcome is returned at once.
    """
    start = time.perf_counter()
    mesh = done.mesh
    mesh_hash = None if mesh is None else mesh.hash
    if done.error is not None:
        return Computed(index, "failed", mesh_hash=mesh_hash, error=done.error, seconds=done.seconds)
    found = done.found
    assert mesh is not None and found is not None  # a shape read without error is looked up
    try:
        if found.features is None and found.key in stored:  # the same mesh earlier in this loop, stored after this look-up
            found = storage.look_up(descriptor, mesh)
        if found.features is not None:
            seconds = done.seconds + time.perf_counter() - start
            return Computed(index, "present", found.features, found.key, mesh_hash, seconds=seconds)
        features = descriptor(mesh) if done.prepared is _NOT_PREPARED else descriptor(mesh, done.prepared)
    except GeofeatError as err:
        return Computed(index, "failed", mesh_hash=mesh_hash, error=err, seconds=done.seconds + time.perf_counter() - start)
    if storage.store is None:  # nothing to write: the outcome now, not one shape later
        return Computed(index, "computed", features, found.key, mesh_hash, seconds=done.seconds + time.perf_counter() - start)
    future = writer.submit(storage.write, descriptor, mesh, found.key, features)
    return _Writing(
        index, features, found.key, mesh.hash, future, done.seconds + time.perf_counter() - start, time.perf_counter()
    )


#: The descriptor and storage of this worker process (`compute_each` with ``n_jobs > 1``).
_WORKER: tuple[Descriptor, FeatureStorage] | None = None


def _start_worker(parent_pid: int, descriptor: Descriptor, storage: FeatureStorage) -> None:
    """In a spawned worker: ends with the parent (`end_with_parent`), keeps what every shape needs."""
    global _WORKER
    end_with_parent(parent_pid)
    _WORKER = (descriptor, storage)


def _worker_compute(index: int, item: MeshLike) -> Computed:
    assert _WORKER is not None  # set by _start_worker, the initializer of every worker process
    descriptor, storage = _WORKER
    return _compute_one(index, item, descriptor, storage)


def compute_many(
    meshes_or_paths: Sequence[MeshLike],
    descriptor: DescriptorArg,
    cache: CacheArg = True,
    n_jobs: int = 1,
    progress: bool = True,
    prefetch: int | None = None,
    **params,
) -> list[np.ndarray]:
    """`compute` over a collection, optionally in several processes, with a progress bar.

    Parameters
    ----------
    meshes_or_paths : sequence of Mesh, path, (verts, faces) or trimesh object
        The shapes (see `compute`).
    descriptor : str or Descriptor
        A registered descriptor name or a descriptor instance, as for `compute`; a name is
        built (and its parameters checked) once, before any work starts, and used for every shape.
    cache : bool, path or FeatureCache
        Where to look up and store the results, as for `compute`; ``False`` computes without caching.
    n_jobs : int
        Worker processes; 1 computes in this process. Workers are started with ``spawn``
        (safe with PyTorch and OpenMP), which costs about a second before the first result.
    progress : bool
        Show a tqdm progress bar.
    prefetch : int or None
        With ``n_jobs == 1``: shapes read and prepared ahead on a background thread (see
        `compute_each`); None: 2 for the DINO descriptors, 0 for the others.
    **params
        Descriptor parameters with a name, as for `compute` (none with an instance).

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
    outcomes = compute_each(
        items, descriptor, resolve_cache(cache), explicit=cache is not True, n_jobs=n_jobs, prefetch=prefetch, progress=progress
    )
    with contextlib.closing(outcomes):
        for outcome in outcomes:
            if outcome.error is not None:
                raise outcome.error
            results[outcome.index] = outcome.features
    return cast(list[np.ndarray], results)  # every shape has its features once none failed


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
