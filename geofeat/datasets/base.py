"""Shared machinery of the benchmark loaders.

`PairDataset` is the base of every loader: a lazy sequence of `ShapePair` records. Building
one only scans file names; a pair's meshes and ground-truth files are read when the pair is
requested, and kept in a per-instance cache so that each file is read once.

The helpers below check folder layouts (a wrong layout raises `DatasetError` showing the
expected tree, what was missing and where to get the data) and turn on-disk index files into
the in-memory convention: int64, 0-based, ``-1`` where a vertex has no counterpart. Loaders
call them at the file boundary; nothing later in geofeat converts indices again.
"""

from __future__ import annotations

import logging
import operator
import os
import re
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import ClassVar, Protocol

import numpy as np

from geofeat.datasets.records import PROTOCOLS, ShapePair
from geofeat.errors import DatasetError, UnknownSplitError
from geofeat.mesh import Mesh, load_mesh
from geofeat.storage.lru import LRUCache

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
DATA_ENV = "GEOFEAT_DATA"


class PairEntry(Protocol):
    """What a loader stores per pair: the names of the source ``y`` and target ``x`` shapes."""

    y: str
    x: str


class PairDataset(Sequence):
    """Base of the benchmark loaders: a lazy, indexable sequence of `ShapePair` records.

    Subclasses scan file names in ``__init__`` (no mesh is read there), store one entry per
    pair in ``self._entries`` (objects with ``y`` and ``x`` shape names) and implement
    `_load_pair`. Meshes are read through `_mesh`, which caches them per instance.

    Parameters
    ----------
    root : path-like
        The dataset folder actually used (already located by the subclass).
    split : str
        Which part of the dataset the pairs come from.
    protocol : {"p2f", "p2p", "f2f"}
        Evaluation protocol of every pair.
    mesh_cache_size : int or None
        Most meshes kept in memory, least recently used dropped first; None keeps them all
        (each file is then read exactly once).

    Attributes
    ----------
    title : str
        Human-readable dataset name used in messages (class attribute).
    source : str
        Where the dataset can be obtained (class attribute).
    """

    title: ClassVar[str] = "dataset"
    source: ClassVar[str] = ""

    def __init__(self, root: str | os.PathLike, split: str, protocol: str, *, mesh_cache_size: int | None = None):
        if protocol not in PROTOCOLS:
            raise DatasetError(f"protocol must be one of {PROTOCOLS}; found {protocol!r}.")
        if mesh_cache_size is not None and mesh_cache_size < 1:
            raise DatasetError(f"mesh_cache_size must be a positive integer or None; found {mesh_cache_size!r}.")
        self.root = Path(root)
        self.split = split
        self.protocol = protocol
        self.mesh_cache_size = mesh_cache_size
        self._entries: list[PairEntry] = []
        self._meshes: LRUCache[tuple[Path, str], Mesh] = LRUCache(mesh_cache_size)
        self._arrays: dict[Path, np.ndarray] = {}
        self._mesh_files: dict[str, Path] = {}

    def __len__(self) -> int:
        return len(self._entries)

    def __getitem__(self, index: int) -> ShapePair:
        """Pair ``index`` (negative counts from the end); reads its files on first use."""
        if isinstance(index, slice):
            raise TypeError("PairDataset does not support slices; use [dataset[i] for i in range(start, stop)].")
        position = operator.index(index)
        if not -len(self) <= position < len(self):
            raise IndexError(f"pair index {position} out of range for {len(self)} pairs of {self.title}.")
        return self._load_pair(self._entries[position])

    @property
    def pair_names(self) -> list[str]:
        """``"<y name>-><x name>"`` for every pair, in index order (equals ``dataset[i].name``)."""
        return [f"{entry.y}->{entry.x}" for entry in self._entries]

    def clear_cache(self) -> None:
        """Forget every cached mesh and index array (they are read again when needed)."""
        self._meshes.clear()
        self._arrays.clear()

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(root={str(self.root)!r}, split={self.split!r}, protocol={self.protocol!r}, {len(self)} pairs)"
        )

    def _load_pair(self, entry) -> ShapePair:
        raise NotImplementedError

    def shape_files(self) -> dict[str, Path]:
        """The mesh file of every shape the pairs use, by shape name (the ``name`` of its `Mesh`).

        This default reads every pair once (meshes and ground truth); loaders that know their
        files without reading them override it.
        """
        for position in range(len(self)):
            self[position]
        return dict(self._mesh_files)

    def files_read(self) -> list[Path]:
        """Every file this instance has read so far (meshes and ground-truth files), sorted.

        After every pair has been loaded, this is exactly what the dataset uses; the other files
        of its folder are not read (``geofeat data check`` lists them).
        """
        arrays = [path for path in self._arrays if Path(path).is_file()]
        return sorted({*self._mesh_files.values(), *arrays})

    def _mesh(self, path: Path, name: str | None = None) -> Mesh:
        """The mesh at ``path`` (named ``name``, else the file stem), read once per instance."""
        key = (Path(path), name or Path(path).stem)
        self._mesh_files[key[1]] = key[0]

        def load() -> Mesh:
            mesh = load_mesh(path)
            return mesh.renamed(name) if name is not None and name != mesh.name else mesh

        return self._meshes.get_or_compute(key, load)

    def _array(self, path: Path, reader: Callable[[Path], np.ndarray]) -> np.ndarray:
        """``reader(path)``, read once per instance and returned read-only."""
        array = self._arrays.get(path)
        if array is None:
            array = reader(path)
            array.flags.writeable = False
            self._arrays[path] = array
        return array


# ----------------------------------------------------------------------------- layouts


def data_root(root: str | os.PathLike | None, title: str) -> Path:
    """``root`` as a Path; when None, ``$GEOFEAT_DATA``.

    Raises
    ------
    DatasetError
        When ``root`` is None and the environment variable is not set.
    """
    if root is not None:
        return Path(root).expanduser()
    from_env = os.environ.get(DATA_ENV)
    if not from_env:
        raise DatasetError(
            f"{title}: no data folder given. Pass root=<folder holding the dataset> or set ${DATA_ENV} "
            "to the folder that contains your datasets."
        )
    return Path(from_env).expanduser()


def missing_items(folder: Path, required: Iterable[str]) -> list[str]:
    """Which of ``required`` are absent under ``folder``.

    Parameters
    ----------
    folder : Path
    required : iterable of str
        Relative paths: ``"off/"`` (trailing slash) must be a folder, ``"off/*.off"`` (a glob)
        must match at least one file, anything else must be a file.

    Returns
    -------
    list of str
        One short phrase per missing item; empty when the layout is complete.
    """
    if not folder.is_dir():
        return [f"{folder} is not a folder"]
    problems = []
    for item in required:
        if item.endswith("/"):
            if not (folder / item).is_dir():
                problems.append(f"missing folder {item}")
        elif any(char in item for char in "*?["):
            if next(folder.glob(item), None) is None:
                problems.append(f"no file matches {item}")
        elif not (folder / item).is_file():
            problems.append(f"missing file {item}")
    return problems


def layout_error(title: str, folder: Path, problems: Sequence[str], tree: str, source: str, hint: str = "") -> DatasetError:
    """A `DatasetError` that names the folder, what was missing, the expected tree and the data source."""
    lines = [f"{title}: cannot use {folder}: {'; '.join(problems)}.", "Expected layout:"]
    lines += ["    " + line for line in tree.strip("\n").splitlines()]
    if hint:
        lines.append(hint)
    if source:
        lines.append(f"Where to get it: {source}")
    return DatasetError("\n".join(lines))


def locate(
    root: Path, candidates: Sequence[Path], required: Sequence[str], *, title: str, tree: str, source: str, hint: str = ""
) -> Path:
    """The first of ``candidates`` that holds every ``required`` item.

    Parameters
    ----------
    root : Path
        The folder the user gave (named in the error).
    candidates : sequence of Path
        Places to look, most specific first (for example ``root``, ``root / split``).
    required : sequence of str
        Items every dataset folder has (see `missing_items`).
    title, tree, source, hint : str
        Dataset name, expected layout drawn as a tree, where to obtain it, extra advice.

    Raises
    ------
    DatasetError
        When no candidate is complete; the message reports what ``root`` lacks.
    """
    for candidate in candidates:
        if not missing_items(candidate, required):
            return candidate
    looked = ", ".join(str(c) for c in candidates if c != root)
    extra = f"Also looked in: {looked}." if looked else ""
    problems = missing_items(root, required)
    raise layout_error(title, root, problems, tree, source, " ".join(part for part in (extra, hint) if part))


def locate_split(
    root: Path, split: str, dataset_folder: str, required: Sequence[str], *, title: str, tree: str, source: str
) -> Path:
    """The split folder of a dataset stored as ``<dataset_folder>/<split>/...``.

    ``root`` may be the split folder itself, the dataset folder, or a folder containing the
    dataset folder. A split folder named after another split is refused.
    """
    candidates = [root, root / split, root / dataset_folder / split]
    folder = locate(root, candidates, required, title=title, tree=tree, source=source)
    check_split_folder(folder, split, title)
    return folder


def check_split(split: str, allowed: Sequence[str], title: str) -> str:
    """``split`` when it is one of ``allowed``, else an `UnknownSplitError` listing them."""
    if split not in allowed:
        raise UnknownSplitError(f"{title}: split must be one of {', '.join(map(repr, allowed))}; found {split!r}.")
    return split


def check_split_folder(folder: Path, split: str, title: str) -> None:
    """Refuse a folder named after another split (``.../train`` when ``split="test"``)."""
    if folder.name in SPLITS and folder.name != split:
        raise DatasetError(
            f"{title}: {folder} is the {folder.name!r} split folder but split={split!r} was asked for. "
            f"Pass the folder that holds {split}/ or set split={folder.name!r}."
        )


def natural_key(text: str) -> tuple:
    """Sort key that orders ``shape_2`` before ``shape_10``."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text))


def trailing_number(stem: str) -> int | None:
    """The number a name ends with (``tr_reg_081`` -> 81), or None."""
    match = re.search(r"(\d+)$", stem)
    return None if match is None else int(match.group(1))


def split_pair_stem(stem: str, names: set[str], source: Path) -> tuple[str, str]:
    """Split ``"<first>_<second>"`` into two known shape names (names may contain ``_`` too).

    Raises
    ------
    DatasetError
        When no split, or more than one, gives two names from ``names``.
    """
    cuts = [i for i, char in enumerate(stem) if char == "_"]
    found = [(stem[:i], stem[i + 1 :]) for i in cuts if stem[:i] in names and stem[i + 1 :] in names]
    if len(found) == 1:
        return found[0]
    if not found:
        raise DatasetError(
            f"{source}: cannot tell which two shapes this file pairs. Expected '<first shape>_<second shape>' "
            f"where both are mesh names of the dataset (for example {sorted(names, key=natural_key)[:2]}); "
            "check that both meshes exist."
        )
    raise DatasetError(f"{source}: the name is ambiguous, it splits into known shape pairs in several ways: {found}.")


def split_pair_stems(paths: Sequence[Path], names: set[str], title: str) -> list[tuple[str, str]]:
    """`split_pair_stem` of every file of ``paths``, with one error that names every file that fails.

    Parameters
    ----------
    paths : sequence of Path
        Files named ``<first>_<second>.<suffix>`` (maps of a dataset).
    names : set of str
        The shape names of the dataset.
    title : str
        Dataset name used in the message.

    Returns
    -------
    list of (str, str)
        ``(first, second)`` for each file, in the order of ``paths``.

    Raises
    ------
    DatasetError
        When any file does not split into two known shape names (a missing mesh, usually) or
        splits in several ways; the message lists up to 10 of them and how many there are.
    """
    pairs, failed = [], []
    for path in paths:
        try:
            pairs.append(split_pair_stem(path.stem, names, path))
        except DatasetError as err:
            failed.append((path, str(err)))
    if not failed:
        return pairs
    if len(failed) == 1:
        raise DatasetError(failed[0][1])
    example = sorted(names, key=natural_key)[:2]
    lines = [
        f"{title}: cannot tell which two shapes {len(failed)} of {len(paths)} map files pair. Each must be named "
        f"'<first shape>_<second shape>' after two mesh files of the dataset (for example {example}); check that both "
        "meshes exist, or remove the map:"
    ]
    lines += [f"    {path.name}" + (" (ambiguous)" if "ambiguous" in message else "") for path, message in failed[:10]]
    if len(failed) > 10:
        lines.append(f"    ... and {len(failed) - 10} more")
    raise DatasetError("\n".join(lines))


# ----------------------------------------------------------------------------- index files


def read_numbers(path: Path) -> np.ndarray:
    """All whitespace-separated numbers of a text file, shape (N,) float64."""
    try:
        text = Path(path).read_text(encoding="ascii")
        return np.array(text.split(), dtype=np.float64)
    except FileNotFoundError:
        raise DatasetError(f"ground-truth file {path} does not exist.") from None
    except (ValueError, UnicodeDecodeError) as err:
        raise DatasetError(f"{path}: expected whitespace-separated numbers; cannot parse the file ({err}).") from None


def as_indices(values: np.ndarray, path: Path) -> np.ndarray:
    """Integral numbers as int64 (files sometimes write indices as ``2.812e+03``)."""
    values = np.asarray(values)
    if values.dtype.kind in "iu":
        return values.astype(np.int64)
    if values.dtype.kind != "f":
        raise DatasetError(f"{path}: expected integer vertex indices; found values of dtype {values.dtype}.")
    bad = ~np.isfinite(values) | (values != np.round(values))
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DatasetError(f"{path}: expected integer vertex indices; entry {first} is {values[first]!r}.")
    return values.astype(np.int64)


def read_indices(path: Path) -> np.ndarray:
    """A text file of integer indices (one per line or whitespace-separated), shape (N,) int64."""
    return as_indices(read_numbers(path), path)


def read_table(path: Path, n_columns: int) -> np.ndarray:
    """A text table with ``n_columns`` numbers per non-empty line, shape (rows, n_columns) float64."""
    values = read_numbers(path)
    if values.size % n_columns:
        raise DatasetError(f"{path}: expected {n_columns} numbers per row; {values.size} numbers do not make whole rows.")
    return values.reshape(-1, n_columns)


def check_length(values: np.ndarray, expected: int, path: Path, what: str) -> None:
    """Raise a `DatasetError` unless ``values`` has exactly ``expected`` entries."""
    if values.shape[0] != expected:
        raise DatasetError(
            f"{path}: expected {expected} entries ({what}); found {values.shape[0]}. "
            "Does the file belong to another shape or another version of the dataset?"
        )


def from_one_based(values: np.ndarray, n_target: int, path: Path) -> np.ndarray:
    """1-based vertex indices to 0-based; entries <= 0 mean "no counterpart" and become -1.

    Parameters
    ----------
    values : numpy.ndarray of int, shape (N,)
        Indices as stored in the file.
    n_target : int
        Vertex count of the shape they index.
    path : Path
        The file (named in errors).

    Returns
    -------
    numpy.ndarray, shape (N,), int64
    """
    values = np.asarray(values, dtype=np.int64)
    too_big = np.flatnonzero(values > n_target)
    if too_big.size:
        first = int(too_big[0])
        raise DatasetError(
            f"{path}: 1-based vertex indices must lie in [1, {n_target}] (the indexed shape has {n_target} vertices); "
            f"entry {first} is {values[first]}. Is the file meant for another shape?"
        )
    return np.where(values >= 1, values - 1, -1).astype(np.int64)


def check_zero_based(values: np.ndarray, n_target: int, path: Path) -> np.ndarray:
    """0-based vertex indices with -1 for "none", checked against ``n_target`` vertices; int64 copy."""
    values = np.asarray(values, dtype=np.int64)
    bad = np.flatnonzero((values < -1) | (values >= n_target))
    if bad.size:
        first = int(bad[0])
        hint = ""
        if values.max(initial=-1) == n_target and not np.any(values == 0):
            hint = " The file looks 1-based (it reaches the vertex count and never uses 0)."
        raise DatasetError(
            f"{path}: 0-based vertex indices must lie in [0, {n_target - 1}], or be -1 for no counterpart "
            f"(the indexed shape has {n_target} vertices); entry {first} is {values[first]}.{hint}"
        )
    return values.copy()


def as_flags(values: np.ndarray, path: Path) -> np.ndarray:
    """0/1 entries as a boolean mask; anything else raises a `DatasetError`."""
    values = np.asarray(values)
    bad = np.flatnonzero((values != 0) & (values != 1))
    if bad.size:
        first = int(bad[0])
        raise DatasetError(f"{path}: expected 0/1 flags; entry {first} is {values[first]}.")
    return values.astype(bool)


def first_hit_map(src: np.ndarray, tgt: np.ndarray, n_src: int) -> np.ndarray:
    """Per-vertex map from paired index lists (for example two template correspondence files).

    Entry ``k`` says that vertex ``src[k]`` of the source corresponds to vertex ``tgt[k]`` of
    the target. Entries where either index is -1 are skipped; when several entries name the
    same source vertex, the first one is kept.

    Parameters
    ----------
    src, tgt : numpy.ndarray of int64, shape (K,)
        0-based indices (-1 allowed).
    n_src : int
        Vertex count of the source shape.

    Returns
    -------
    numpy.ndarray, shape (n_src,), int64
        Target vertex of each source vertex, -1 where no entry names it.
    """
    if src.shape != tgt.shape:
        raise DatasetError(f"paired correspondence lists differ in length: {src.shape[0]} and {tgt.shape[0]} entries.")
    keep = (src >= 0) & (tgt >= 0)
    src, tgt = src[keep], tgt[keep]
    out = np.full(n_src, -1, dtype=np.int64)
    vertices, first = np.unique(src, return_index=True)
    out[vertices] = tgt[first]
    return out


def has_counterpart(map_yx: np.ndarray) -> np.ndarray:
    """Boolean mask, shape (V,), of the vertices that have a counterpart (``map >= 0``)."""
    return np.asarray(map_yx) >= 0
