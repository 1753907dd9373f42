"""Features for a whole collection: the library behind ``geofeat extract``.

`extract` computes one descriptor on every shape into a content-keyed feature store
(`geofeat.FeatureCache`), skipping the shapes whose entry is already there, so a run that
was killed is completed by running it again. It writes a manifest (one record per shape)
and, on request, per-shape files in the layouts other pipelines read (`ExportSpec`).
``geofeat extract`` puts the manifest in the store folder (`default_manifest_path`); every
path in a manifest is absolute, so it reads the same from any folder.

Under ``torchrun`` every rank takes the shapes at positions ``i % world_size == rank`` of
the sorted collection, computes them on its own device (``device="auto"``: the GPU
``LOCAL_RANK``) and writes into the shared store; after a barrier rank 0 gathers every
rank's records and writes the one manifest (and the HDF5 export). Store entries are
written atomically (`geofeat.descriptors.cache`), so a rank killed mid-run leaves complete entries
only.

>>> from geofeat.apps.extract import default_manifest_path, extract, folder_shapes
>>> manifest = extract(folder_shapes("FAUST_r/off"), "wks", {"n_descr": 128}, store="features/",
...                    manifest=default_manifest_path("wks", {"n_descr": 128}, "features/"))
>>> manifest["n_computed"], manifest["n_present"], manifest["manifest"]
(100, 0, '/home/me/features/wks-48ef1801.manifest.json')
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import h5py
import numpy as np
import torch

from geofeat._version import __version__
from geofeat.checks import check_integer, parse_key_values
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.cache import MANIFEST_SUFFIX, FeatureCache
from geofeat.descriptors.collection import Computed, compute_each, default_prefetch
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import ExtractError, GeofeatError
from geofeat.mesh import MESH_SUFFIXES, Mesh, load_mesh
from geofeat.runtime import distributed
from geofeat.storage.files import atomic_write, probe_writable

log = logging.getLogger(__name__)

EXPORT_FORMATS = ("npy", "h5")
LAYOUTS = ("mirror", "beside")
#: Version of the manifest's layout.
MANIFEST_FORMAT = 1
#: How long a rank waits at the barrier for the slowest rank (a shard of ViT features can take hours).
BARRIER_TIMEOUT_MINUTES = 24 * 60.0


@dataclass(frozen=True)
class ShapeSource:
    """One shape of a collection.

    Attributes
    ----------
    name : str
        Unique within the collection and the sort key of sharding: the file's path relative
        to the collection root without its suffix, with ``/`` (``"off/tr_reg_000"``), or the
        mesh name for shapes built in memory.
    path : Path or None
        The mesh file; None for a shape built in memory.
    relative : str or None
        The file's path relative to the collection root, suffix included (``"off/tr_reg_000.off"``).
    mesh : Mesh or None
        The mesh itself for shapes built in memory.
    """

    name: str
    path: Path | None = None
    relative: str | None = None
    mesh: Mesh | None = None

    def load(self) -> Mesh:
        """The mesh (read from `path` now, or the one held)."""
        return self.mesh if self.mesh is not None else load_mesh(self.path)


def folder_shapes(folder: str | os.PathLike) -> list[ShapeSource]:
    """Every ``.off``/``.obj``/``.ply`` file below ``folder`` (sub-folders included), sorted by relative path.

    Raises
    ------
    ExtractError
        The folder does not exist, is not a folder, or holds no mesh file.
    """
    root = Path(folder).expanduser()
    if not root.exists():
        raise ExtractError(f"data folder {root} does not exist; expected a folder of {'/'.join(MESH_SUFFIXES)} meshes.")
    if not root.is_dir():
        raise ExtractError(f"--data must be a folder of meshes; {root} is a file. Pass the folder that holds it.")
    files = sorted(p for p in root.rglob("*") if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
    if not files:
        raise ExtractError(
            f"data folder {root} holds no mesh file (looked for {', '.join(MESH_SUFFIXES)} in it and its sub-folders); "
            "pass the folder that holds the meshes (for FAUST_r: FAUST_r/off)."
        )
    shapes = []
    for path in files:
        relative = path.relative_to(root).as_posix()
        shapes.append(ShapeSource(str(PurePosixPath(relative).with_suffix("")), path, relative))
    return _unique(shapes, str(root))


def dataset_shapes(name: str, root: str | os.PathLike | None = None, split: str = "all") -> tuple[list[ShapeSource], Path | None]:
    """The shapes of a registered dataset (`geofeat.datasets.load_dataset`), and the dataset folder.

    File-based datasets give their mesh files (named relative to the dataset folder, e.g.
    ``off/tr_reg_000``); datasets built in memory (synthetic, derived partial benchmarks)
    give their meshes, named by mesh name, and no folder.

    Parameters
    ----------
    name : str
        Dataset name (``"faust_r"``, ``"scape_r"``, ``"shrec16_cuts"``, ...).
    root : path-like or None
        Data folder; None: ``$GEOFEAT_DATA``.
    split : str
        ``"all"`` for every shape of FAUST_r/SCAPE_r; other datasets name their splits.

    Raises
    ------
    DatasetError
        Unknown dataset, split or a missing dataset folder.
    """
    from geofeat.datasets import load_dataset

    dataset = load_dataset(name, root, split=split)
    files = getattr(dataset, "shape_files", None)
    if callable(files):
        folder = Path(dataset.root)
        shapes = []
        for path in sorted(files().values()):
            path = Path(path)
            try:
                relative = path.relative_to(folder).as_posix()
            except ValueError:  # a mesh outside the dataset folder: name it by its file name
                relative = path.name
            shapes.append(ShapeSource(str(PurePosixPath(relative).with_suffix("")), path, relative))
        return _unique(shapes, f"dataset {name!r}"), folder
    meshes: dict[str, Mesh] = {}
    for position in range(len(dataset)):
        pair = dataset[position]
        for mesh in (pair.y, pair.x):  # the same shape in several pairs counts once; a name used twice gets the hash
            name = mesh.name or "shape"
            if name in meshes and meshes[name].hash != mesh.hash:
                name = f"{name}-{mesh.hash[:8]}"
            meshes.setdefault(name, mesh)
    return _unique([ShapeSource(key, mesh=mesh) for key, mesh in meshes.items()], f"dataset {name!r}"), None


def _unique(shapes: list[ShapeSource], where: str) -> list[ShapeSource]:
    if not shapes:
        raise ExtractError(f"{where} holds no shapes; nothing to extract.")
    names = [s.name for s in shapes]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ExtractError(
            f"{where}: several files give the shape name(s) {repeated[:5]} (the same stem with different suffixes); "
            "keep one file per shape."
        )
    return sorted(shapes, key=lambda s: s.name)


def parse_params(items: Sequence[str]) -> dict[str, Any]:
    """``--param`` items of ``geofeat extract`` as a dict (`geofeat.checks.parse_key_values` raising `ExtractError`).

    ``["n_descr=128", "laplacian=cotan"]`` -> ``{"n_descr": 128, "laplacian": "cotan"}``.
    """
    return parse_key_values(items, "--param", error=ExtractError)


@dataclass(frozen=True)
class ExportSpec:
    """Per-shape files written besides the store.

    Layouts (the arrays are float32, shape (V, C), C-contiguous, written with ``numpy.save``):

    ``npy`` + ``mirror``
        ``<to>/<relative path of the mesh, suffix .npy>``: a folder tree mirroring the input
        (``--data FAUST_r/off`` -> ``<to>/tr_reg_000.npy``; ``--dataset faust_r`` ->
        ``<to>/off/tr_reg_000.npy``). Shapes built in memory: ``<to>/<name>.npy``.
    ``npy`` + ``beside``
        ``<folder holding the mesh's folder>/<feature_folder>/<stem>.npy``, next to ``off/``
        in a dataset folder (``FAUST_r/off/tr_reg_000.off`` -> ``FAUST_r/wks/tr_reg_000.npy``),
        the layout of ULRSSM/DPFM-style dataset folders. With ``to``: ``<to>/<feature_folder>/<stem>.npy``.
    ``h5``
        One HDF5 file ``to``: one dataset per shape, named by the shape's name
        (``off/tr_reg_000``), with attributes ``mesh_hash``, ``descriptor``, ``params``.

    Attributes
    ----------
    format : {"npy", "h5"}
    layout : {"mirror", "beside"}
        For ``npy`` only.
    to : Path or None
        The export folder (``npy``) or file (``h5``); required except for ``beside``.
    feature_folder : str or None
        ``beside``: the folder name; default the descriptor name.
    """

    format: str = "npy"
    layout: str = "mirror"
    to: Path | None = None
    feature_folder: str | None = None

    def __post_init__(self) -> None:
        if self.format not in EXPORT_FORMATS:
            raise ExtractError(f"export format must be one of {', '.join(EXPORT_FORMATS)}; found {self.format!r}.")
        if self.layout not in LAYOUTS:
            raise ExtractError(f"export layout must be one of {', '.join(LAYOUTS)}; found {self.layout!r}.")
        if self.to is not None:
            object.__setattr__(self, "to", Path(self.to).expanduser())
        if self.format == "h5" and self.to is None:
            raise ExtractError("--export h5 needs --export-to FILE.h5 (the HDF5 file to write).")
        if self.format == "npy" and self.layout == "mirror" and self.to is None:
            raise ExtractError("--export npy --layout mirror needs --export-to DIR (the folder the tree is written under).")
        if self.feature_folder is not None and (not self.feature_folder or any(c in self.feature_folder for c in "/\\")):
            raise ExtractError(f"--feature-folder must be one folder name (no slashes); found {self.feature_folder!r}.")

    def check(self, shapes: Sequence[ShapeSource], descriptor: str) -> None:
        """Refuse before any work when the export cannot hold every shape.

        A shape may have no place in the layout (``beside`` needs mesh files), two shapes may
        map to one output (``beside`` keeps only the file stem; in HDF5 a shape ``a`` and a
        shape ``a/b`` would need ``a`` to be both an array and a group), or an output folder
        may not be writable.

        Raises
        ------
        ExtractError
            Naming the shapes or the folder concerned.
        """
        if self.format == "npy" and self.layout == "beside" and self.to is None:
            in_memory = [s.name for s in shapes if s.path is None]
            if in_memory:
                raise ExtractError(
                    f"--layout beside writes next to the mesh files, but {len(in_memory)} shape(s) are built in memory "
                    f"(first {in_memory[0]!r}); use --layout mirror --export-to DIR, or pass --export-to DIR."
                )
        if self.format == "h5":
            names = sorted(s.name for s in shapes)
            for name, after in zip(names, names[1:], strict=False):
                if after.startswith(name + "/"):
                    raise ExtractError(
                        f"--export h5 cannot hold both shape {name!r} and shape {after!r}: the first would be an array "
                        f"and a group at once. Rename one, or use --export npy --layout mirror."
                    )
            folders = {_absolute(self.to).parent}
        else:
            owners: dict[Path, str] = {}
            for shape in shapes:
                target = _absolute(self.target(shape, descriptor))
                if target in owners:
                    raise ExtractError(
                        f"shapes {owners[target]!r} and {shape.name!r} would both be exported to {target}; "
                        "use --layout mirror --export-to DIR, which keeps each shape's relative path."
                    )
                owners[target] = shape.name
            folders = {target.parent for target in owners}
        for folder in sorted(folders):
            problem = writable_folder_problem(folder)
            if problem is not None:
                raise ExtractError(f"cannot export into {folder}: {problem}. Choose another place with --export-to.")

    def target(self, shape: ShapeSource, descriptor: str) -> Path | None:
        """The ``.npy`` file of ``shape`` (None for ``h5``, written whole by `write_h5`)."""
        if self.format != "npy":
            return None
        if self.layout == "mirror":
            relative = shape.relative if shape.relative is not None else shape.name
            return self.to / PurePosixPath(relative).with_suffix(".npy")
        folder_name = self.feature_folder or descriptor
        stem = shape.path.stem if shape.path is not None else PurePosixPath(shape.name).name
        base = self.to if self.to is not None else shape.path.parent.parent
        return base / folder_name / f"{stem}.npy"


def writable_folder_problem(folder: Path) -> str | None:
    """Why files cannot be written into ``folder`` (created if missing), or None when they can.

    A small file is created and removed there, as the later writes will do.
    """
    try:
        probe_writable(folder, prefix=".geofeat-write-check-")
    except OSError as err:
        return err.strerror or type(err).__name__
    return None


def save_npy(path: str | os.PathLike, features: np.ndarray) -> Path:
    """Write ``features`` (V, C) float32 to ``path`` with ``numpy.save``, atomically (no pickle)."""
    array = np.ascontiguousarray(features, dtype=np.float32)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as handle:
            np.save(handle, array, allow_pickle=False)

    return atomic_write(path, write)


def write_h5(path: str | os.PathLike, records: Sequence[Mapping[str, Any]], store: FeatureCache) -> Path:
    """One HDF5 file holding every shape's features, read from ``store`` (atomically).

    Parameters
    ----------
    records : sequence of dict
        Manifest records (``shape``, ``key``, ``mesh_hash``, ``descriptor``, ``params``); failed ones are skipped.

    Raises
    ------
    ExtractError
        An entry went missing from the store meanwhile (run again).
    """

    def write(tmp: Path) -> None:
        with h5py.File(tmp, "w") as fh:
            fh.attrs["geofeat_version"] = __version__
            for record in records:
                if record["status"] == "failed":
                    continue
                features = store.get(record["key"])
                if features is None:
                    raise ExtractError(
                        f"the store entry of {record['shape']!r} ({record['entry']}) disappeared before the HDF5 export; run again."
                    )
                dataset = fh.create_dataset(record["shape"], data=np.ascontiguousarray(features, dtype=np.float32))
                dataset.attrs["mesh_hash"] = record["mesh_hash"]
                dataset.attrs["descriptor"] = record["descriptor"]
                dataset.attrs["params"] = json.dumps(record["params"], sort_keys=True)
            fh.flush()

    return atomic_write(path, write)


def params_digest(descriptor: str, params: Mapping[str, Any]) -> str:
    """Eight hex digits naming a descriptor and its parameters as given (the default manifest name; defaults spelled out give another name)."""
    text = json.dumps({"descriptor": descriptor, "params": params}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:8]


def default_manifest_path(
    descriptor: str, params: Mapping[str, Any], store: str | os.PathLike | FeatureCache | None = None
) -> Path:
    """Where ``geofeat extract`` writes its manifest when no ``--manifest`` is given: in the store folder.

    Parameters
    ----------
    descriptor : str
        Descriptor name.
    params : mapping
        Descriptor parameters as given (`params_digest`).
    store : path or FeatureCache, optional
        The feature store (``--out``); None: the user's feature cache (``$GEOFEAT_CACHE_DIR/features``).

    Returns
    -------
    Path
        ``<store>/<descriptor>-<params digest>.manifest.json``, absolute.
    """
    root = store.root if isinstance(store, FeatureCache) else FeatureCache(store).root
    return _absolute(root) / f"{descriptor}-{params_digest(descriptor, params)}{MANIFEST_SUFFIX}"


def _absolute(path: str | os.PathLike) -> Path:
    """``path`` made absolute against the current folder, ``..`` folded, symbolic links kept as named."""
    return Path(os.path.abspath(Path(path).expanduser()))


def _descriptor_params(name: str, params: Mapping[str, Any], device: torch.device) -> dict[str, Any]:
    """``params`` checked by the descriptor, with ``device`` set to this rank's device when the descriptor takes one."""
    params = dict(params)
    descriptor = make_descriptor(name, **params)  # unknown descriptor or parameter, bad values: fail before any work
    if "device" in type(descriptor).param_names() and "device" not in params:
        params["device"] = str(device)
    return params


def _record(
    shape: ShapeSource,
    outcome: Computed,
    descriptor: Descriptor,
    store: FeatureCache,
    export: ExportSpec | None,
    rank: int,
) -> dict[str, Any]:
    """The manifest record of one shape's outcome, after its export (when one is asked for)."""
    record: dict[str, Any] = {
        "shape": shape.name,
        "path": None if shape.path is None else str(_absolute(shape.path)),
        "rank": rank,
    }
    if outcome.error is not None:
        log.warning("shape %s failed: %s", shape.name, outcome.error)
        record.update(
            status="failed", error=f"{type(outcome.error).__name__}: {outcome.error}", seconds=round(outcome.seconds, 4)
        )
        return record
    start = time.perf_counter()
    features = outcome.features
    target = export.target(shape, descriptor.name) if export is not None else None
    if target is not None:
        try:
            save_npy(target, features)
        except OSError as err:  # the features are in the store; only this shape's export is missing
            log.warning("shape %s: export to %s failed: %s", shape.name, target, err)
            record["export_error"] = f"could not write {_absolute(target)}: {err.strerror or err}"
            target = None
    record.update(
        mesh_hash=outcome.mesh_hash,
        n_vertices=int(features.shape[0]),
        n_channels=int(features.shape[1]),
        feature_shape=[int(n) for n in features.shape],
        descriptor=descriptor.name,
        params=descriptor.get_params(),
        key=outcome.key,
        entry=str(_absolute(store.path(outcome.key))),
        status=outcome.status,
        seconds=round(outcome.seconds + time.perf_counter() - start, 4),
        export=None if target is None else str(_absolute(target)),
    )
    return record


def extract(
    shapes: Sequence[ShapeSource],
    descriptor: str,
    params: Mapping[str, Any] | None = None,
    *,
    store: str | os.PathLike | FeatureCache | None = None,
    manifest: str | os.PathLike | None = None,
    export: ExportSpec | None = None,
    device: str | torch.device | None = "auto",
    prefetch: int | None = None,
    progress: bool = True,
    on_record: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Compute ``descriptor`` on every shape into a feature store, skipping entries already there.

    Parameters
    ----------
    shapes : sequence of ShapeSource
        The collection (`folder_shapes`, `dataset_shapes`); every rank must pass the same.
    descriptor : str
        Registered descriptor name.
    params : mapping, optional
        Descriptor parameters (checked by the descriptor before any work).
    store : path or FeatureCache, optional
        Where entries go; default the user's feature cache (``$GEOFEAT_CACHE_DIR/features``).
    manifest : path, optional
        JSON file to write (rank 0, atomically); None writes none. ``geofeat extract`` passes
        `default_manifest_path`, a file in the store folder.
    export : ExportSpec, optional
        Per-shape files to write as well.
    device : str or torch.device
        ``"auto"``: the GPU ``LOCAL_RANK`` when there are GPUs, else the CPU; given to
        descriptors that take a ``device`` (it is not part of the cache key).
    prefetch : int, optional
        Shapes read, looked up and prepared (for the DINO descriptors: rendered) on a
        background thread ahead of the one being computed, so that the GPU is not left
        waiting for them; 0: none. None: 2 for the DINO descriptors, 0 for the others (see
        `geofeat.descriptors.collection.compute_each`, which also gives the memory it costs).
        The features and the records are the same whatever its value.
    progress : bool
        Show a progress bar (rank 0's shard; on a terminal only, see `geofeat.runtime.progress`).
    on_record : callable, optional
        Called with every record of this rank as it is made.

    Returns
    -------
    dict
        The manifest: ``descriptor``, ``params``, ``store``, ``world_size``, counts
        ``n_shapes``/``n_computed``/``n_present``/``n_failed``, the throughput
        (``wall_seconds``: the loop over the shapes, on the slowest rank, the model's loading
        excluded; ``shapes_per_second``: shapes computed, not those already present, per
        second of it, None when none was computed; ``prefetch``: the read-ahead used), and
        ``shapes``: one record per shape (``shape``, ``path``, ``mesh_hash``,
        ``n_vertices``, ``n_channels``, ``feature_shape``, ``key``, ``entry``, ``status`` in
        ``{"computed", "present", "failed"}``, ``seconds``, ``rank``, ``export``; failed
        ones carry ``error``). Every
        path in it (``store``, ``path``, ``entry``, ``export``) is absolute. The returned
        dict also holds ``manifest``, the absolute path of the file written (when one was),
        and ``export`` for an HDF5 export. On ranks other than 0 under torchrun, only that
        rank's records.

    Raises
    ------
    DescriptorError
        Unknown descriptor or parameter, bad parameter value.
    ExtractError
        No shapes, an export layout the shapes cannot take, or a ``prefetch`` that is not
        an integer >= 0.
    CacheError
        The store cannot be written.
    """
    shapes = sorted(shapes, key=lambda s: s.name)
    if not shapes:
        raise ExtractError("no shapes to extract; pass a folder or a dataset that holds meshes.")
    names = [s.name for s in shapes]
    if len(set(names)) != len(names):
        raise ExtractError("shape names must be unique within a collection (they name manifest records and exports).")
    if prefetch is not None:
        prefetch = check_integer(prefetch, "prefetch", low=0, error=ExtractError, expected="a number of shapes >= 0 (0: none)")
    store = store if isinstance(store, FeatureCache) else FeatureCache(store)
    with distributed.process_group(device, timeout_minutes=BARRIER_TIMEOUT_MINUTES) as rank_device:
        info = distributed.group_rank_info()
        params = _descriptor_params(descriptor, params or {}, rank_device)
        instance = make_descriptor(descriptor, **params)  # one for every shape of this rank (a model loads once)
        store.check_writable(
            "Name a writable folder with --out (or store= in Python); without --out the store is the feature cache, "
            "which GEOFEAT_CACHE_DIR moves."
        )
        # every output place is checked before the work, not found unwritable after it
        if export is not None:
            export.check(shapes, instance.name)
        if manifest is not None and info.is_main:
            problem = writable_folder_problem(_absolute(manifest).parent)
            if problem is not None:
                raise ExtractError(
                    f"cannot write the manifest {_absolute(manifest)}: {problem}. Choose another place with --manifest."
                )
        mine = distributed.shard(shapes, info)
        label = f"{descriptor} features" + (f" (rank 0 of {info.world_size})" if info.world_size > 1 else "")
        records = []
        sources = [shape.path if shape.path is not None else shape.mesh for shape in mine]
        prefetch = default_prefetch(instance) if prefetch is None else prefetch
        try:  # a model loads now, outside the timed loop (the store keys need its digest)
            instance.weights_digest()
        except GeofeatError:
            pass  # every shape fails with this error below and its record says so
        start = time.perf_counter()
        outcomes = compute_each(sources, instance, store, prefetch=prefetch, progress=progress and info.is_main, desc=label)
        with contextlib.closing(outcomes):  # an error here stops the read-ahead thread at once
            for outcome in outcomes:
                record = _record(mine[outcome.index], outcome, instance, store, export, info.rank)
                records.append(record)
                if on_record is not None:
                    on_record(record)
        seconds = time.perf_counter() - start
        n_computed = sum(r["status"] == "computed" for r in records)
        log.info(
            "rank %d of %d: %d shapes, %d computed in %.2f s (%s shapes/s)",
            info.rank,
            info.world_size,
            len(records),
            n_computed,
            seconds,
            "-" if not n_computed else f"{n_computed / seconds:.3g}",
        )
        distributed.barrier()  # every rank's entries are in the store
        gathered = distributed.gather_to_main((records, seconds))
        if not info.is_main:
            return _manifest(instance, store, info.world_size, records, seconds, prefetch)
        merged = sorted((r for part, _ in gathered for r in part), key=lambda r: r["shape"])
        slowest = max(rank_seconds for _, rank_seconds in gathered)
        result = _manifest(instance, store, info.world_size, merged, slowest, prefetch)
        if export is not None and export.format == "h5":
            try:
                write_h5(export.to, merged, store)
                result["export"] = str(_absolute(export.to))
            except (OSError, ExtractError) as err:  # the features are in the store; the manifest still says so
                log.warning("HDF5 export to %s failed: %s", export.to, err)
                result["export_error"] = f"could not write {_absolute(export.to)}: {getattr(err, 'strerror', None) or err}"
        if manifest is not None:
            _write_manifest(result, _absolute(manifest), store)
        return result


def _write_manifest(result: dict[str, Any], path: Path, store: FeatureCache) -> None:
    """Write the manifest to ``path``, else beside the store's entries, else in the temporary folder.

    Sets ``result["manifest"]`` to where it went; ``result["manifest_error"]`` says why it is
    not at ``path`` (nothing written anywhere leaves ``result["manifest"]`` None).
    """
    result["manifest"] = None
    for place in dict.fromkeys([path, _absolute(store.root) / path.name, Path(tempfile.gettempdir()) / path.name]):
        try:
            atomic_write(place, lambda tmp: tmp.write_text(json.dumps(result, indent=1) + "\n"))
        except OSError as err:
            log.warning("could not write the manifest to %s: %s", place, err)
            result.setdefault("manifest_error", f"could not write {path}: {err.strerror or err}")
            continue
        result["manifest"] = str(place)
        return


def _manifest(checked: Descriptor, store: FeatureCache, world: int, records: list[dict], seconds: float, prefetch: int) -> dict:
    n_computed = sum(r["status"] == "computed" for r in records)
    return {
        "format": MANIFEST_FORMAT,
        "geofeat_version": __version__,
        "descriptor": checked.name,
        "params": checked.get_params(),
        "store": str(_absolute(store.root)),
        "world_size": world,
        "n_shapes": len(records),
        "n_computed": n_computed,
        "n_present": sum(r["status"] == "present" for r in records),
        "n_failed": sum(r["status"] == "failed" for r in records),
        "n_export_failed": sum("export_error" in r for r in records),
        "wall_seconds": round(seconds, 4),
        "shapes_per_second": round(n_computed / seconds, 4) if n_computed and seconds > 0 else None,
        "prefetch": prefetch,
        "shapes": records,
    }
