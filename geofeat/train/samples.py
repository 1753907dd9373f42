"""The CPU half of a GeoLoRA training step: samples prepared ahead of the step, in worker processes.

A training sample is one full shape with everything drawn for it: the shape turned about the
up axis, its ``partials_per_shape`` partial shapes (each turned by its own angle, with the
exact vertex map back to the full shape) and the full shape's geodesic matrix.
`prepare_sample` makes sample ``g`` from the settings, the shapes and ``g`` alone (no state),
so any process can make any sample and get the same arrays to the bit:

- the full shape is ``shapes[shape_index(seed, len(shapes), g)]``: position ``g % n`` of a
  permutation of the ``n`` shapes drawn from ``numpy.random.default_rng([seed, g // n, 1])``
  (a new permutation per epoch);
- every other draw comes from ``rng = numpy.random.default_rng([seed, g])``, in this order:
  the full shape's angle ``rng.uniform(0, 360)``, then per partial shape its generator
  ``partial_kinds[rng.integers(len(partial_kinds))]``, the generator's seed
  ``rng.integers(2**63 - 1)`` (`geofeat.geometry.partial.make_partial` of the turned full
  shape) and its own angle ``rng.uniform(0, 360)`` (`rotate_about_up`, degrees,
  counter-clockwise seen from +y);
- under ``config.generators() == "reference"`` the sample is made as GeoLoRA's training loop
  makes it (`reference_partials`): the draws come from a legacy ``RandomState`` and a torch
  generator, both seeded from ``rng.integers(2**32)``;
- the geodesic matrix is read from the float16 `geofeat.train.geodesics.TorchGeodesicStore`
  (computed and stored when missing) and handed out as stored, float16 on the CPU: the
  device widens it to float32, so the copy to the device moves half the bytes.

`SampleDataset` is the map-style `torch.utils.data.Dataset` of those samples (indexed by the
global sample index) and `SamplePrefetcher` runs it in `torch.utils.data.DataLoader` worker
processes that prepare the samples of the coming steps while the trainer computes the
current one. Workers never touch CUDA (they return CPU tensors, pinned by the loader when the
trainer's device is CUDA), open the geodesic store themselves (a store holds no open file:
each read maps its ``.npy`` file anew) and ignore Ctrl-C (the trainer finishes its step
first, with their samples). Workers do not change results: one process or many, the samples
are the same.

Workers need shared memory (``/dev/shm``) for the samples in flight, about
``PREFETCH_PER_WORKER * workers`` of them, each mostly its geodesic matrix (``2 V^2`` bytes:
50 MB for 5,000 vertices, 288 MB for 12,000); in a container, give it room (``docker run
--shm-size``) or train with ``workers=0``.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from geofeat.errors import GeofeatError, MeshError, TrainingError
from geofeat.geometry.partial import PartialShape, make_partial
from geofeat.geometry.partial_reference import cut_partial_reference, draw_holes, holes_partial_reference
from geofeat.mesh import Mesh, quiet_reports
from geofeat.render.cameras import rotation_about_up
from geofeat.render.raycast import official_ray_eye, ray_partial_reference
from geofeat.runtime.processes import end_with_parent
from geofeat.topology import triangle_areas
from geofeat.train.config import TrainConfig
from geofeat.train.geodesics import TorchGeodesicStore

log = logging.getLogger(__name__)

__all__ = [
    "PREFETCH_PER_WORKER",
    "PreparedSample",
    "SampleDataset",
    "SamplePrefetcher",
    "prepare_sample",
    "reference_partials",
    "training_partial_reference",
    "resolve_workers",
    "rotate_about_up",
    "shape_index",
]

#: Samples each worker process keeps ready (`torch.utils.data.DataLoader`'s ``prefetch_factor``).
PREFETCH_PER_WORKER = 2
#: Most workers ``workers="auto"`` starts per rank on CUDA.
AUTO_WORKERS = 4

#: The generators of GeoLoRA's training loop in its order (``random_view``, ``random_cut``, ``random_holes``).
TRAINING_KINDS = ("ray", "cuts", "holes")
#: Tries of the training loop for one partial shape ...
TRAINING_TRIES = 10
#: ... until it has at least this many vertices.
TRAINING_MIN_VERTICES = 10

#: ``timer(phase)``: a context manager charging the seconds of its block to ``phase``.
Timer = Callable[[str], contextlib.AbstractContextManager]


def rotate_about_up(mesh: Mesh, angle_degrees: float) -> Mesh:
    """The mesh turned about the y (up) axis through the origin; same vertex order.

    The rotation is `geofeat.render.cameras.rotation_about_up`, the one that turns a camera rig.

    Parameters
    ----------
    mesh : Mesh
        V vertices.
    angle_degrees : float
        Counter-clockwise seen from +y.

    Returns
    -------
    Mesh
        Vertices (V, 3) float64 turned, faces and name unchanged.
    """
    return Mesh(mesh.verts @ rotation_about_up(angle_degrees).T, mesh.faces, mesh.name)


def shape_index(seed: int, n_shapes: int, index: int) -> int:
    """The full shape of global sample ``index``: position ``index % n_shapes`` of the permutation of its epoch.

    Parameters
    ----------
    seed : int
        The run's seed.
    n_shapes : int
        Number of full shapes ``n``.
    index : int
        Global sample index ``g >= 0``.

    Returns
    -------
    int
        ``numpy.random.default_rng([seed, g // n, 1]).permutation(n)[g % n]``.
    """
    order = np.random.default_rng([seed, index // n_shapes, 1]).permutation(n_shapes)
    return int(order[index % n_shapes])


class PreparedSample(NamedTuple):
    """One training sample, ready for the device: what `prepare_sample` drew for global sample ``index``.

    Attributes
    ----------
    index : int
        Global sample index.
    shape_index : int
        Position of its full shape in the trainer's shape list.
    full : Mesh
        The full shape turned about the up axis (V vertices, in the order of the shape).
    partials : list of (Mesh, torch.Tensor)
        Per partial shape: the turned partial mesh (P vertices) and its ground truth, the
        index of each partial vertex in ``full``, shape (P,), int64, on the CPU.
    geodesics : torch.Tensor, shape (V, V), float16
        Geodesic distances of the full shape (over ``sqrt(area)``) as the store keeps them, on the CPU.
    """

    index: int
    shape_index: int
    full: Mesh
    partials: list[tuple[Mesh, torch.Tensor]]
    geodesics: torch.Tensor

    def pin_memory(self) -> PreparedSample:
        """The sample with its tensors in page-locked memory (called by `torch.utils.data.DataLoader`)."""
        return self._replace(
            partials=[(mesh, gt.pin_memory()) for mesh, gt in self.partials], geodesics=self.geodesics.pin_memory()
        )


class SampleFailure(NamedTuple):
    """What a worker process hands back for a sample it could not prepare: the error, to raise in the trainer.

    Attributes
    ----------
    index : int
        Global sample index.
    error : type
        The `GeofeatError` subclass raised in the worker.
    message : str
        Its message.
    """

    index: int
    error: type[GeofeatError]
    message: str


def prepare_sample(
    config: TrainConfig,
    shapes: Sequence[Mesh],
    index: int,
    geodesics: TorchGeodesicStore,
    timer: Timer | None = None,
) -> PreparedSample:
    """Global sample ``index`` of a run, made on the CPU (the rule is in the module notes).

    Parameters
    ----------
    config : TrainConfig
        Reads ``seed``, ``partials_per_shape`` and ``partial_kinds``.
    shapes : sequence of Mesh
        The run's full shapes, in the trainer's order.
    index : int
        Global sample index.
    geodesics : TorchGeodesicStore
        Where the full shapes' geodesic matrices are (a missing one is computed and stored).
    timer : callable, optional
        ``timer(phase)`` around the reading of the geodesics (``"geodesics"``) and the
        rotation and partial shapes (``"partial"``).

    Returns
    -------
    PreparedSample
        CPU tensors only.
    """
    timer = timer or (lambda phase: contextlib.nullcontext())
    rng = np.random.default_rng([config.seed, index])
    which = shape_index(config.seed, len(shapes), index)
    mesh = shapes[which]
    with timer("geodesics"):
        dist = geodesics.load_stored(mesh)
    if config.generators() == "reference":
        with timer("partial"), quiet_reports():
            full, partials = reference_partials(mesh, dist, config, int(rng.integers(2**32)))
        return PreparedSample(index, which, full, partials, dist)
    with timer("partial"), quiet_reports():
        full = rotate_about_up(mesh, rng.uniform(0.0, 360.0))
        partials = []
        for _ in range(config.partials_per_shape):
            kind = config.partial_kinds[rng.integers(len(config.partial_kinds))]
            partial = make_partial(full, kind, seed=int(rng.integers(2**63 - 1)))
            turned = rotate_about_up(partial.mesh, rng.uniform(0.0, 360.0))
            partials.append((turned, torch.tensor(partial.vertex_map, dtype=torch.int64)))
    return PreparedSample(index, which, full, partials, dist)


def reference_partials(mesh: Mesh, geodesics: torch.Tensor, config: TrainConfig, seed: int) -> tuple[Mesh, list]:
    """The full shape and partial shapes of one sample as GeoLoRA's training loop makes them.

    The full shape is turned about the up axis by an angle ``random_state.uniform(0, 2 pi)``,
    as ``vertices @ R_y(angle)`` turns it, and divided by the square root of its area (the
    official loop's vertices are, once its geodesic matrix is computed); each of the
    ``config.partials_per_shape`` partial shapes is `training_partial_reference` of it,
    turned again by its own angle. A partial shape not made in its tries is left out (with a warning).

    Parameters
    ----------
    mesh : Mesh
        The full shape as loaded (V vertices).
    geodesics : torch.Tensor, shape (V, V), float16
        Its geodesic matrix over the square root of its area (the store's).
    config : TrainConfig
        Reads ``partials_per_shape`` and ``partial_kinds``.
    seed : int
        Seeds the legacy ``numpy.random.RandomState`` of every draw but HOLES' and the torch
        generator of HOLES' draws.

    Returns
    -------
    full : Mesh
        Turned, then scaled (float32 positions, as the official loop's).
    partials : list of (Mesh, torch.Tensor)
        Each partial shape, turned, with its ground truth (V_p,) int64: the nearest full vertex.
    """
    random_state = np.random.RandomState(seed)
    generator = torch.Generator().manual_seed(seed)
    turned = rotate_about_up(mesh, -np.degrees(random_state.uniform(0.0, 2 * np.pi))).verts.astype(np.float32)
    turned /= np.float32(np.sqrt(triangle_areas(turned, mesh.faces).sum()))
    full = Mesh(turned, mesh.faces, mesh.name)
    dist = geodesics.numpy()  # float16 as stored, no copy: HOLES reads the rows of its centres
    partials = []
    for _ in range(config.partials_per_shape):
        partial = training_partial_reference(full, config.partial_kinds, dist, random_state, generator)
        if partial is None:
            log.warning("no partial shape of %s with 10 vertices or more in its tries: left out", mesh.name)
            continue
        turned = rotate_about_up(partial.mesh, -np.degrees(random_state.uniform(0.0, 2 * np.pi)))
        partials.append((turned, torch.tensor(partial.vertex_map, dtype=torch.int64)))
    return full, partials


def training_partial_reference(
    full: Mesh, kinds, geodesics: np.ndarray, random_state: np.random.RandomState, generator=None
) -> PartialShape | None:
    """One partial shape of ``full`` as GeoLoRA's training loop makes it, or None.

    Each try draws a generator uniformly (``random_state.randint(len(kinds))``) and makes a
    partial shape with it: RAY from `geofeat.render.raycast.official_ray_eye`, CUTS with
    normals from ``random_state``, HOLES from `draw_holes` with ``generator``. The first with
    at least `TRAINING_MIN_VERTICES` vertices is returned; after `TRAINING_TRIES` tries
    without one, None (the official loop gives up there too). A try whose generator finds
    no partial shape at all (no ray hits, every face in a hole) counts as a failed try.

    Parameters
    ----------
    full : Mesh
        The full shape as the training loop sees it: turned, and divided by the square root
        of its area (the official loop works on those vertices; RAY depends on the scale).
    kinds : sequence of {"ray", "cuts", "holes"}
        The generators to draw from, taken in the order of `TRAINING_KINDS`.
    geodesics : numpy.ndarray, shape (V, V)
        Geodesic matrix of ``full`` over the square root of its area (read by HOLES only).
    random_state : numpy.random.RandomState
        The legacy NumPy stream (the official loop's global ``np.random``).
    generator : torch.Generator, optional
        CPU stream of the HOLES draws (None: torch's default, as the official loop).

    Returns
    -------
    PartialShape or None
        ``exact=False`` (``vertex_map`` is the nearest full vertex of each partial vertex);
        ``info["tries"]`` is replaced by the tries of this loop.
    """
    unknown = sorted(set(kinds) - set(TRAINING_KINDS))
    if unknown or not kinds:
        raise TrainingError(f"kinds must be a non-empty subset of {TRAINING_KINDS}; found {list(kinds)}.")
    ordered = [kind for kind in TRAINING_KINDS if kind in kinds]
    for attempt in range(1, TRAINING_TRIES + 1):
        kind = ordered[random_state.randint(0, len(ordered))]
        try:
            if kind == "ray":
                partial = ray_partial_reference(full, official_ray_eye(random_state))
            elif kind == "cuts":
                partial = cut_partial_reference(full, random_state)
            else:
                drawn = draw_holes(full.n_vertices, generator)
                partial = holes_partial_reference(full, drawn.centres, drawn.radius, geodesics)
        except MeshError:
            continue
        if partial.mesh.n_vertices >= TRAINING_MIN_VERTICES:
            info = {**partial.info, "tries": attempt}
            return PartialShape(partial.mesh, partial.vertex_map, partial.face_map, partial.kind, info, exact=False)
    return None


class SampleDataset(Dataset):
    """The samples of a run as a map-style dataset: ``dataset[g]`` is `prepare_sample` of global sample ``g``.

    Parameters
    ----------
    config : TrainConfig
    shapes : sequence of Mesh
        The run's full shapes.
    geodesic_folder : str or os.PathLike
        Folder of the run's `TorchGeodesicStore`; every process opens its own store on it.

    Notes
    -----
    It has no length: any index ``g >= 0`` is a sample (the sampler says which are taken).
    It pickles without its store, for worker processes started by ``spawn``.
    """

    def __init__(self, config: TrainConfig, shapes: Sequence[Mesh], geodesic_folder: str | os.PathLike):
        self.config = config
        self.shapes = list(shapes)
        self.geodesic_folder = Path(geodesic_folder)
        self._store: TorchGeodesicStore | None = None
        self._store_pid: int | None = None

    def store(self) -> TorchGeodesicStore:
        """The geodesic store of this process (opened on first use in each process)."""
        if self._store is None or self._store_pid != os.getpid():
            self._store, self._store_pid = TorchGeodesicStore(self.geodesic_folder), os.getpid()
        return self._store

    def prepare(self, index: int, timer: Timer | None = None) -> PreparedSample:
        """`prepare_sample` of global sample ``index`` in this process, ``timer`` charged as it says."""
        return prepare_sample(self.config, self.shapes, int(index), self.store(), timer)

    def __getitem__(self, index: int) -> PreparedSample | SampleFailure:
        """In a worker process: the sample, or its `SampleFailure` (raised by `SamplePrefetcher.take` as it was)."""
        try:
            return self.prepare(index)
        except GeofeatError as err:
            return SampleFailure(int(index), type(err), str(err))

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_store"] = state["_store_pid"] = None
        return state


def resolve_workers(workers: int | str, device: torch.device) -> int:
    """Worker processes of a ``workers`` setting on ``device``.

    Parameters
    ----------
    workers : int or "auto"
        ``"auto"``: none on the CPU (the step's own work takes the cores there); on CUDA
        ``min(4, c - 1)``, where ``c`` is this rank's share of the usable cores (those of
        ``os.sched_getaffinity`` divided among the ``LOCAL_WORLD_SIZE`` ranks of the node).
    device : torch.device
        The trainer's device.

    Returns
    -------
    int
        ``>= 0``.
    """
    if workers != "auto":
        return int(workers)
    if device.type != "cuda":
        return 0
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        cores = os.cpu_count() or 1
    local_ranks = max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1") or 1))
    return max(0, min(AUTO_WORKERS, cores // local_ranks - 1))


class _StepSampler(Sampler[int]):
    """The global sample indices of steps ``first, first + 1, ..., stop - 1``, step by step."""

    def __init__(self, step_indices: Callable[[int], range], first: int, stop: int):
        self.step_indices, self.first, self.stop = step_indices, first, stop

    def __iter__(self) -> Iterator[int]:
        for step in range(self.first, self.stop):
            yield from self.step_indices(step)

    def __len__(self) -> int:
        return sum(len(self.step_indices(step)) for step in range(self.first, self.stop))


def _identity(sample: PreparedSample) -> PreparedSample:
    """The loader's collate function: a sample is its own batch."""
    return sample


def _worker_start(parent_pid: int, _worker_id: int) -> None:
    """In a worker process: ends with the trainer (`end_with_parent`); Ctrl-C is for the trainer.

    The trainer stops after its step on Ctrl-C and closes the workers then.
    """
    end_with_parent(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class SamplePrefetcher:
    """Worker processes preparing the samples of the coming steps, handed out step by step.

    Parameters
    ----------
    dataset : SampleDataset
    step_indices : callable
        ``step_indices(step)``: the global sample indices this process trains on at ``step``
        (`geofeat.train.trainer.GeoLoraTrainer.sample_indices`); called in this process only.
    first, stop : int
        The steps whose samples are prepared: ``first`` to ``stop - 1``.
    workers : int
        Worker processes (``>= 1``).
    pin_memory : bool
        Put the samples' tensors in page-locked memory (a CUDA trainer: faster, asynchronous copies).
    seed : int
        Seeds the loader's own generator (the workers' base seed; nothing is drawn from it),
        so starting a loader leaves the global torch generator alone.

    Notes
    -----
    A context manager; `close` (or leaving the ``with`` block) stops the workers and waits
    for them.

    Workers are forked where ``fork`` exists, whatever the process's default start method
    (``spawn`` in a process that was itself spawned, ``forkserver`` from Python 3.14): they
    start at once and inherit the shapes instead of importing torch anew and unpickling
    them. They only ever run `prepare_sample` (CPU work), so forking a process that uses CUDA
    is safe. Elsewhere the default start method is used (the dataset pickles).
    """

    def __init__(
        self,
        dataset: SampleDataset,
        step_indices: Callable[[int], range],
        first: int,
        stop: int,
        workers: int,
        pin_memory: bool = False,
        seed: int = 0,
    ):
        if workers < 1:
            raise TrainingError(f"SamplePrefetcher needs at least one worker process; found workers={workers}.")
        self.step_indices = step_indices
        self.next_step, self.stop = first, stop
        loader = DataLoader(
            dataset,
            batch_size=None,
            sampler=_StepSampler(step_indices, first, stop),
            num_workers=workers,
            collate_fn=_identity,
            pin_memory=pin_memory,
            worker_init_fn=functools.partial(_worker_start, os.getpid()),
            prefetch_factor=PREFETCH_PER_WORKER,
            persistent_workers=False,
            generator=torch.Generator().manual_seed(seed),
            multiprocessing_context="fork" if "fork" in multiprocessing.get_all_start_methods() else None,
        )
        self._iterator = iter(loader) if first < stop else None
        log.debug("%d worker process(es) prepare the samples of steps %d to %d", workers, first, stop - 1)

    def take(self, step: int) -> list[PreparedSample] | None:
        """The prepared samples of ``step``, in the order of ``step_indices(step)``; None when it is not the next step.

        Raises
        ------
        GeofeatError
            A worker could not prepare a sample: its error, with its message.
        TrainingError
            The loader handed out other samples than those of ``step``.
        """
        if self._iterator is None or step != self.next_step or step >= self.stop:
            return None
        samples = []
        for expected in self.step_indices(step):
            try:
                sample = next(self._iterator)
            except StopIteration:
                raise TrainingError(f"the sample loader ran out before sample {expected} of step {step}.") from None
            if isinstance(sample, SampleFailure):
                raise sample.error(sample.message)
            if sample.index != expected:
                raise TrainingError(
                    f"the sample loader handed out sample {sample.index} where step {step} expected sample {expected}."
                )
            samples.append(sample)
        self.next_step += 1
        return samples

    def close(self) -> None:
        """Stop the workers and wait for them (idempotent)."""
        iterator, self._iterator = self._iterator, None
        if iterator is not None and hasattr(iterator, "_shutdown_workers"):
            iterator._shutdown_workers()

    def __enter__(self) -> SamplePrefetcher:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
