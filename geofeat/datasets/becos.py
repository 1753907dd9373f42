"""BeCoS (Ehm, El Amrani et al.): generated full-full, partial-full and partial-partial pairs.

The benchmark is produced by its authors' generator (``main.py`` of
``NafieAmrani/becos-code``); its output layout, one folder per setting::

    <setting>/                   full_full, partial_full or partial_partial
    ├── train/, val/, test/
    │   └── 0/, 1/, 2/ ...       one folder per pair
    │       ├── 0_<name>.off         shape 0
    │       ├── 1_<name>.off         shape 1
    │       ├── corres_01.npy        (V_0,) for each vertex of shape 0 its vertex of shape 1, -1: none
    │       ├── corres_10.npy        (V_1,) for each vertex of shape 1 its vertex of shape 0, -1: none
    │       ├── 0_<name>_info.pkl    shape 0's record (below)
    │       └── 1_<name>_info.pkl    shape 1's record, written last
    ├── logs/config.yaml         the generator's settings
    └── pairings.pkl             the pairs of every split, drawn before any is written

``<name>`` is the source shape's name with ``/`` replaced by ``_``. Both maps are 0-based int64
with -1 for "no counterpart". In ``partial_full`` shape 0 is the full shape and shape 1 the
partial one, and ``corres_01.npy`` is not written. Each pair is ``x = shape 0``,
``y = shape 1``, matched with ``corres_10`` (GeoLoRA reads it the same way); with
``both_directions=True`` the partial-partial and full-full settings add the reverse pair
(``x = shape 1``, ``y = shape 0``, ``corres_01``).

The ``_info.pkl`` records (Python dictionaries of strings, numbers and numpy arrays) hold the
shape's source ``name`` and ``org_dataset``, ``scale_per_dataset``, ``surface_area`` (despite
its name the square root of the surface area of the *full* shape, at the scale of the files;
the released benchmark files used by GeoLoRA call it ``surface_area_after_scaling``),
``random_rotation`` (3, 3) (the file's vertices are the aligned shape's vertices times this
matrix), ``align_rotation`` and ``align_translation`` (shape 1 only), and for partial shapes
``partial2full`` (vertex of the full shape for each vertex of the partial one) and
``cam_pos``. ``overlap_mask`` is, in ``partial_full``, shape 0's mask of the vertices with a
counterpart in the partial shape; in ``partial_partial`` each record holds the mask of the
*other* shape's vertices. They are read with a restricted unpickler that accepts only
builtins and numpy arrays (`read_becos_info`); anything else is refused.

Overlap masks: ``overlap_y`` marks the vertices of y with a counterpart; ``overlap_x`` those of
x, from the reverse map when there is one and otherwise (``partial_full``) from shape 0's
``overlap_mask``. Full-full pairs carry no overlap masks. Meshes keep the position, scale and
random rotation stored in the files; `BeCoS.info` gives each pair's records, among them the
square root of the full shapes' areas, by which BeCoS normalises geodesic errors (on a partial
shape its own area is smaller).
"""

from __future__ import annotations

import io
import logging
import os
import pickle
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.datasets.base import (
    SPLITS,
    PairDataset,
    as_indices,
    check_length,
    check_split,
    check_split_folder,
    check_zero_based,
    data_root,
    has_counterpart,
    layout_error,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError

log = logging.getLogger(__name__)

SETTINGS = {"full_full": "f2f", "partial_full": "p2f", "partial_partial": "p2p"}

#: Keys of the square root of the full shape's area, in the order they are looked for.
AREA_KEYS = ("surface_area_after_scaling", "surface_area")

TREE = """\
<setting>/                     full_full, partial_full or partial_partial (in BeCoS/ or the generator's output/)
└── <split>/                   train, val or test
    └── <k>/                   0, 1, 2, ... one folder per pair
        ├── 0_<name>.off       x (the full shape in partial_full)
        ├── 1_<name>.off       y (the partial shape in partial_full)
        ├── corres_10.npy      (V_1,) int: vertex of shape 0 for each vertex of shape 1, -1: none
        ├── corres_01.npy      (V_0,) int: the reverse map (not in partial_full)
        ├── 0_<name>_info.pkl  shape 0's record: surface_area, random_rotation, ...
        └── 1_<name>_info.pkl  shape 1's record (written last)"""

SOURCE = (
    "generate it with its authors' generator, https://github.com/NafieAmrani/becos-code "
    "(python main.py --config demo_config writes the TOSCA subset; `geofeat data prepare becos` runs it and "
    "checks the output), or download it as linked from https://nafieamrani.github.io/BeCoS/."
)


@dataclass(frozen=True)
class _Pair:
    y: str
    x: str
    folder: Path
    file0: Path
    file1: Path
    reverse: bool  # True: x = shape 1, y = shape 0


@dataclass(frozen=True, eq=False)
class BecosShapeInfo:
    """One shape's ``_info.pkl`` record, as the generator wrote it.

    Attributes
    ----------
    name : str
        The source shape's name (``michael0``, ``tr_reg_000``; may contain ``/``).
    dataset : str
        The source dataset (``org_dataset``: ``tosca``, ``faust``, ...).
    sqrt_area : float
        Square root of the surface area of the full shape at the scale of the files
        (``surface_area_after_scaling`` or ``surface_area``); for a partial shape that of the
        full shape it was cut from. BeCoS divides geodesic distances on the shape by it.
    rotation : numpy.ndarray, shape (3, 3)
        ``random_rotation``: the file's vertices are the aligned shape's vertices ``@ rotation``.
    partial : bool
        Whether the shape is a partial one (its record has ``partial2full``).
    partial2full : numpy.ndarray, shape (V,), int64, or None
        For each vertex of a partial shape, its vertex in the full shape it was cut from.
    overlap_mask : numpy.ndarray of bool or None
        As stored (see the module notes for which shape it describes).
    record : dict
        Every key of the file, as read.
    path : Path
        The file.
    """

    name: str
    dataset: str
    sqrt_area: float
    rotation: np.ndarray
    partial: bool
    partial2full: np.ndarray | None
    overlap_mask: np.ndarray | None
    record: dict
    path: Path

    @property
    def file_stem(self) -> str:
        """The name as the generator writes it into file names (``/`` replaced by ``_``)."""
        return self.name.replace("/", "_")


@dataclass(frozen=True, eq=False)
class BecosPairInfo:
    """The records of a pair's two shapes, in the pair's orientation (``x`` is the target).

    Attributes
    ----------
    x, y : BecosShapeInfo
    sqrt_area_x : float
        ``x.sqrt_area``: what BeCoS divides geodesic distances on x by. For a full x it equals
        the square root of x's own area; for a partial x (``partial_partial``) it is larger.
    """

    x: BecosShapeInfo
    y: BecosShapeInfo

    @property
    def sqrt_area_x(self) -> float:
        """What BeCoS divides geodesic distances on the pair's target x by."""
        return self.x.sqrt_area


class BeCoS(PairDataset):
    """BeCoS pairs of one setting and split.

    Parameters
    ----------
    root : path-like or None
        The split folder itself (``.../partial_full/test``), the setting folder, a folder that
        holds the setting folders (the generator's ``output/``, a ``BeCoS/`` folder), or a
        folder that contains ``BeCoS/``. None: ``$GEOFEAT_DATA``.
    split : {"train", "val", "test"}
    setting : {"partial_full", "partial_partial", "full_full"}
        Gives the protocol: p2f, p2p or f2f.
    both_directions : bool
        Also match shape 0 to shape 1 (p2p and f2f only).
    mesh_cache_size : int or None
        See `PairDataset`. Every BeCoS shape belongs to one pair, so a bound (say 64) keeps
        memory flat while iterating.

    Raises
    ------
    DatasetError
        When no pair folder is found, or a pair folder is incomplete (a file missing: an
        interrupted generator run); the message names every incomplete folder.

    Notes
    -----
    A split whose pair folders hold no ``_info.pkl`` at all is read without the records (older
    copies, hand-made files); `info` then raises. Where some folders have them, a folder
    without both is incomplete.
    """

    title = "BeCoS"
    source = SOURCE

    def __init__(
        self,
        root: str | os.PathLike | None = None,
        split: str = "test",
        *,
        setting: str = "partial_full",
        both_directions: bool = False,
        mesh_cache_size: int | None = None,
    ):
        check_split(split, SPLITS, self.title)
        if setting not in SETTINGS:
            raise DatasetError(f"{self.title}: setting must be one of {', '.join(SETTINGS)}; found {setting!r}.")
        if both_directions and setting == "partial_full":
            raise DatasetError(
                f"{self.title}: both_directions=True needs a symmetric setting; in partial_full x must be the full shape."
            )
        given = data_root(root, self.title)
        folder = self._locate(given, split, setting)
        super().__init__(folder, split, SETTINGS[setting], mesh_cache_size=mesh_cache_size)
        self.title = f"BeCoS {setting}"
        self.setting = setting
        self._infos: dict[Path, BecosShapeInfo] = {}
        self._entries = self._pairs(both_directions)

    def _locate(self, given: Path, split: str, setting: str) -> Path:
        candidates = [given, given / split, given / setting / split, given / "BeCoS" / setting / split]
        for folder in candidates:
            if _pair_folders(folder):
                check_split_folder(folder, split, self.title)
                if folder.parent.name in SETTINGS and folder.parent.name != setting:
                    raise DatasetError(
                        f"{self.title}: {folder} belongs to the {folder.parent.name!r} setting but setting={setting!r} "
                        "was asked for. Pass the BeCoS folder, or the matching setting."
                    )
                return folder
        problems = [f"no numbered pair folder (0/, 1/, ...) in {given}"] if given.is_dir() else [f"{given} is not a folder"]
        hint = f"Also looked in: {', '.join(str(c) for c in candidates[1:])}."
        raise layout_error(self.title, given, problems, TREE, self.source, hint)

    def _pairs(self, both_directions: bool) -> list[_Pair]:
        folders = _pair_folders(self.root)
        with_info = any(next(folder.glob("*_info.pkl"), None) is not None for folder in folders)
        needed = ["corres_10.npy"]
        if both_directions or (self.setting != "partial_full" and with_info):
            needed.append("corres_01.npy")  # the generator writes both maps in these settings
        incomplete = {}
        for folder in folders:
            missing = pair_folder_missing(folder, needed, with_info)
            if missing:
                incomplete[folder] = missing
        if incomplete:
            raise DatasetError(_incomplete_message(self.title, self.root, incomplete))
        pairs = []
        for folder in folders:
            file0, file1 = _shape_file(folder, "0"), _shape_file(folder, "1")
            name0, name1 = f"{folder.name}_{file0.stem}", f"{folder.name}_{file1.stem}"
            pairs.append(_Pair(y=name1, x=name0, folder=folder, file0=file0, file1=file1, reverse=False))
            if both_directions:
                pairs.append(_Pair(y=name0, x=name1, folder=folder, file0=file0, file1=file1, reverse=True))
        return pairs

    def _load_pair(self, entry: _Pair) -> ShapePair:
        folder = entry.folder
        mesh0 = self._mesh(entry.file0, f"{folder.name}_{entry.file0.stem}")
        mesh1 = self._mesh(entry.file1, f"{folder.name}_{entry.file1.stem}")
        map_10 = self._map(folder / "corres_10.npy", mesh1.n_vertices, mesh0.n_vertices)
        path_01 = folder / "corres_01.npy"
        map_01 = self._map(path_01, mesh0.n_vertices, mesh1.n_vertices) if path_01.is_file() else None
        infos = self._pair_infos(entry)
        if infos is not None:
            check_roles(self.setting, infos, (mesh0.n_vertices, mesh1.n_vertices), folder)
        x, y, map_yx, map_xy = (mesh1, mesh0, map_01, map_10) if entry.reverse else (mesh0, mesh1, map_10, map_01)
        # BeCoS divides geodesic errors on x by the recorded sqrt(area) of x's full shape
        error_scale = None if infos is None else (infos[1] if entry.reverse else infos[0]).sqrt_area
        if self.protocol == "f2f":
            return ShapePair(x=x, y=y, map_yx=map_yx.copy(), protocol="f2f", error_scale=error_scale)
        if map_xy is not None:
            overlap_x = has_counterpart(map_xy)
        elif infos is not None and infos[0].overlap_mask is not None:
            overlap_x = infos[0].overlap_mask.copy()  # partial_full: shape 0's mask, length checked by check_roles
        else:
            overlap_x = None
        return ShapePair(
            x=x,
            y=y,
            map_yx=map_yx.copy(),
            overlap_x=overlap_x,
            overlap_y=has_counterpart(map_yx),
            protocol=self.protocol,
            error_scale=error_scale,
        )

    def _map(self, path: Path, n_source: int, n_target: int) -> np.ndarray:
        return self._array(path, lambda p: read_becos_map(p, n_source, n_target))

    def _pair_infos(self, entry: _Pair) -> tuple[BecosShapeInfo, BecosShapeInfo] | None:
        """The records of shape 0 and shape 1 (file order), or None when the folder has none."""
        paths = [info_path(entry.file0), info_path(entry.file1)]
        if not all(path.is_file() for path in paths):
            return None
        infos = []
        for path in paths:
            if path not in self._infos:
                self._infos[path] = read_shape_info(path)
            infos.append(self._infos[path])
        return infos[0], infos[1]

    def info(self, index: int) -> BecosPairInfo:
        """The generator's records of pair ``index``'s two shapes, in the pair's orientation.

        Parameters
        ----------
        index : int
            Pair index, as for ``dataset[index]``.

        Returns
        -------
        BecosPairInfo
            ``info.x`` and ``info.y`` are the records of the pair's x and y; ``sqrt_area_x`` is
            what BeCoS divides geodesic errors on x by.

        Raises
        ------
        DatasetError
            When the pair folder has no ``_info.pkl`` files, or they cannot be read.
        """
        if not -len(self) <= index < len(self):
            raise IndexError(f"pair index {index} out of range for {len(self)} pairs of {self.title}.")
        entry = self._entries[index]
        infos = self._pair_infos(entry)
        if infos is None:
            raise DatasetError(
                f"{self.title}: pair folder {entry.folder} has no 0_<name>_info.pkl and 1_<name>_info.pkl; "
                "the generator writes them with every pair. Regenerate the split to get areas and rotations."
            )
        first, second = infos
        return BecosPairInfo(x=second, y=first) if entry.reverse else BecosPairInfo(x=first, y=second)

    def files_read(self) -> list[Path]:
        """Every file this instance has read so far: meshes, maps and ``_info.pkl`` records."""
        return sorted({*super().files_read(), *self._infos})


def _pair_folders(folder: Path) -> list[Path]:
    """Numbered subfolders, in numeric order (empty when ``folder`` is not a folder)."""
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


def _shape_file(folder: Path, side: str) -> Path:
    found = sorted(folder.glob(f"{side}_*.off"))
    if len(found) != 1:
        raise DatasetError(f"BeCoS: pair folder {folder} must hold exactly one {side}_<name>.off; found {len(found)}.")
    return found[0]


def info_path(mesh_file: Path) -> Path:
    """The ``_info.pkl`` record next to a shape file: ``0_cat0.off`` -> ``0_cat0_info.pkl``."""
    return mesh_file.with_name(f"{mesh_file.stem}_info.pkl")


def pair_folder_missing(folder: Path, maps: list[str], with_info: bool) -> list[str]:
    """What a pair folder lacks: ``0_<name>.off``, ``1_<name>.off``, the ``maps`` and, with ``with_info``, both records.

    Parameters
    ----------
    folder : Path
        One numbered pair folder.
    maps : list of str
        The map files required (``corres_10.npy``, and ``corres_01.npy`` outside ``partial_full``).
    with_info : bool
        Whether both ``<side>_<name>_info.pkl`` files are required.

    Returns
    -------
    list of str
        Short phrases, empty when the folder is complete. Several candidate shape files count as
        a problem too.
    """
    missing = []
    for side in "01":
        found = sorted(folder.glob(f"{side}_*.off"))
        if len(found) != 1:
            missing.append(f"{side}_<name>.off" if not found else f"one {side}_<name>.off (found {len(found)})")
        elif with_info and not info_path(found[0]).is_file():
            missing.append(info_path(found[0]).name)
    missing += [name for name in maps if not (folder / name).is_file()]
    return missing


def _incomplete_message(title: str, root: Path, incomplete: dict[Path, list[str]]) -> str:
    lines = [
        f"{title}: {len(incomplete)} pair folder(s) of {root} are incomplete (an interrupted or failed generator run "
        "writes a pair's files one after another, the second _info.pkl last):"
    ]
    for folder, missing in list(incomplete.items())[:10]:
        lines.append(f"    {folder.name}/: lacks {', '.join(missing)}")
    if len(incomplete) > 10:
        lines.append(f"    ... and {len(incomplete) - 10} more")
    lines.append("Run the generator again (or `geofeat data check` / `geofeat data prepare becos` to see the whole state).")
    return "\n".join(lines)


def check_roles(setting: str, infos: tuple[BecosShapeInfo, BecosShapeInfo], n_vertices: tuple[int, int], folder: Path) -> None:
    """Refuse records that contradict the files of a pair folder.

    Parameters
    ----------
    setting : {"full_full", "partial_full", "partial_partial"}
    infos : (BecosShapeInfo, BecosShapeInfo)
        The records of shape 0 and shape 1.
    n_vertices : (int, int)
        Vertex counts of ``0_<name>.off`` and ``1_<name>.off``.
    folder : Path
        The pair folder.

    Raises
    ------
    DatasetError
        When a record names another shape than its file, calls a shape partial (it has
        ``partial2full``) that the setting says is full or the reverse, or holds
        ``partial2full`` / (partial_full) shape 0's ``overlap_mask`` of the wrong length.
    """
    files = (_shape_file(folder, "0"), _shape_file(folder, "1"))
    for side, (info, file, n) in enumerate(zip(infos, files, n_vertices, strict=True)):
        if f"{side}_{info.file_stem}" != file.stem:
            raise DatasetError(
                f"{info.path}: records shape {info.name!r} but the pair's shape {side} is {file.name}; "
                "the folder mixes files of different pairs. Regenerate it."
            )
        expected_partial = setting == "partial_partial" or (setting == "partial_full" and side == 1)
        if info.partial != expected_partial:
            role = "partial" if info.partial else "full"
            raise DatasetError(
                f"{info.path}: shape {side} is recorded as a {role} shape, but in {setting} shape {side} is "
                f"{'partial' if expected_partial else 'full'}. Is the folder of another setting?"
            )
        if info.partial2full is not None and info.partial2full.shape != (n,):
            raise DatasetError(
                f"{info.path}: partial2full has {info.partial2full.shape[0]} entries; {file.name} has {n} vertices."
            )
    mask = infos[0].overlap_mask
    if setting == "partial_full" and mask is not None and mask.shape != (n_vertices[0],):
        raise DatasetError(f"{infos[0].path}: overlap_mask has {mask.shape[0]} entries; {files[0].name} has {n_vertices[0]}.")


def read_becos_map(path: Path, n_source: int, n_target: int) -> np.ndarray:
    """Read a BeCoS ``corres_*.npy`` vertex map.

    Parameters
    ----------
    path : Path
        ``.npy`` array, shape (n_source,), integer (or integral float), 0-based, -1 for none.
    n_source, n_target : int
        Vertex counts of the mapped shape and of the shape it maps into.

    Returns
    -------
    numpy.ndarray, shape (n_source,), int64
    """
    try:
        values = np.load(path, allow_pickle=False)
    except ValueError as err:
        raise DatasetError(f"{path}: not a plain numeric .npy array ({err}).") from None
    except (OSError, EOFError) as err:
        raise DatasetError(f"{path}: cannot be read ({err}); the file is truncated or damaged, regenerate the pair.") from None
    if values.ndim != 1:
        raise DatasetError(
            f"{path}: expected a vertex-to-vertex map of shape ({n_source},); found shape {values.shape}. "
            "Maps saved as barycentric coordinates are not supported: generate BeCoS with vertex-to-vertex "
            "correspondences."
        )
    values = as_indices(values, path)
    check_length(values, n_source, path, "one entry per vertex of the mapped shape")
    return check_zero_based(values, n_target, path)


# ----------------------------------------------------------------------------- _info.pkl records


def _numpy_globals() -> dict[tuple[str, str], Any]:
    """The names a pickle of numpy arrays and scalars refers to, under numpy 1 and numpy 2 module names.

    Protocols 2 to 4 rebuild arrays with ``_reconstruct`` (protocol 2 encodes their bytes with
    ``_codecs.encode``), protocol 5 with ``_frombuffer``; scalars come from ``scalar``.
    """
    import codecs

    try:
        from numpy._core import multiarray, numeric  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1
        from numpy.core import multiarray, numeric
    allowed: dict[tuple[str, str], Any] = {
        ("numpy", "ndarray"): np.ndarray,
        ("numpy", "dtype"): np.dtype,
        ("_codecs", "encode"): codecs.encode,
    }
    for package in ("numpy.core", "numpy._core"):
        allowed[(f"{package}.multiarray", "_reconstruct")] = multiarray._reconstruct
        allowed[(f"{package}.multiarray", "scalar")] = multiarray.scalar
        allowed[(f"{package}.numeric", "_frombuffer")] = numeric._frombuffer
    return allowed


class _RecordUnpickler(pickle.Unpickler):
    """Unpickles builtins (dict, list, str, numbers, None) and numpy arrays, dtypes and scalars; refuses any other name."""

    allowed = _numpy_globals()

    def find_class(self, module: str, name: str) -> Any:
        found = self.allowed.get((module, name))
        if found is None:
            raise pickle.UnpicklingError(f"refused global {module}.{name}")
        return found


def _read_record_pickle(path: Path, what: str) -> Any:
    """Unpickle ``path`` with `_RecordUnpickler`; every failure is a `DatasetError` that says what to do."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise DatasetError(f"{path}: cannot read {what} ({err}).") from None
    try:
        return _RecordUnpickler(io.BytesIO(data)).load()
    except pickle.UnpicklingError as err:
        if "refused global" in str(err):
            raise DatasetError(
                f"{path} was refused for safety: {what} holds only strings, numbers, lists, dictionaries and numpy "
                f"arrays, but this pickle names another Python object ({str(err).removeprefix('refused global ')}), "
                "and unpickling it could run arbitrary code. Regenerate it with the BeCoS generator, or convert the "
                "file where you trust its source."
            ) from None
        reason = str(err)
    except Exception as err:  # EOFError, ValueError, TypeError ... from a truncated or foreign stream
        reason = " ".join(str(err).split()) or type(err).__name__
    raise DatasetError(
        f"{path}: not readable as {what} ({reason}); the file is truncated (an interrupted run or copy) or damaged. "
        "Regenerate it."
    )


def read_becos_info(path: str | os.PathLike) -> dict:
    """Read a BeCoS ``_info.pkl`` record without running code.

    Only builtin containers and values and numpy arrays, dtypes and scalars are accepted; a
    pickle that names any other Python object is refused (unpickling it could run code).

    Parameters
    ----------
    path : path-like
        A ``<side>_<name>_info.pkl`` file of the generator.

    Returns
    -------
    dict
        The record, keys as written.

    Raises
    ------
    DatasetError
        When the file is missing, truncated, not a pickle, not a dictionary, or names a
        Python object other than those above.
    """
    path = Path(path)
    record = _read_record_pickle(path, "a BeCoS shape record")
    if not isinstance(record, dict):
        raise DatasetError(f"{path}: expected a dictionary (a BeCoS shape record); found {type(record).__name__}.")
    return record


#: The order of the splits in the generator's ``pairings.pkl``.
PAIRINGS_ORDER = ("train", "test", "val")


def read_becos_pairings(path: str | os.PathLike) -> dict[str, list[tuple[dict, dict]]]:
    """The generator's ``pairings.pkl``: the pairs of every split, drawn before any pair is written.

    ``main.py`` writes it into ``output/<setting>/`` (with ``original_settings: true`` it reads
    ``config/pairings_original_<setting>.pkl`` instead, of the same form). Read without
    running code, as `read_becos_info`.

    Parameters
    ----------
    path : path-like

    Returns
    -------
    dict of str to list of (dict, dict)
        For ``"train"``, ``"test"`` and ``"val"``: pair ``k`` of the split as the generator's
        records of shape 0 and shape 1 (keys ``name``, ``org_dataset``, ``random_rot``, ...);
        pair ``k`` is written to folder ``<split>/<k>/``.

    Raises
    ------
    DatasetError
        When the file cannot be read safely or is not three lists of pairs.
    """
    path = Path(path)
    data = _read_record_pickle(path, "the BeCoS pairings")
    ok = isinstance(data, (list, tuple)) and len(data) == len(PAIRINGS_ORDER)
    ok = ok and all(
        isinstance(pairs, (list, tuple))
        and all(
            isinstance(p, (list, tuple)) and len(p) == 2 and all(isinstance(s, dict) and "name" in s for s in p) for p in pairs
        )
        for pairs in data
    )
    if not ok:
        raise DatasetError(
            f"{path}: expected the generator's pairings (a list of train, test and val pair lists, each pair two "
            "shape dictionaries with a 'name'); found something else."
        )
    return {split: [tuple(pair) for pair in pairs] for split, pairs in zip(PAIRINGS_ORDER, data, strict=True)}


def read_shape_info(path: str | os.PathLike) -> BecosShapeInfo:
    """`read_becos_info`, checked and converted into a `BecosShapeInfo`.

    Raises
    ------
    DatasetError
        When a key the generator always writes is missing or has the wrong shape.
    """
    path = Path(path)
    record = read_becos_info(path)
    area_key = next((key for key in AREA_KEYS if key in record), None)
    problems = [f"no {' or '.join(AREA_KEYS)}"] if area_key is None else []
    problems += [f"no {key}" for key in ("name", "random_rotation") if key not in record]
    if problems:
        raise DatasetError(
            f"{path}: not a BeCoS shape record ({'; '.join(problems)}; keys found: {', '.join(map(str, record))})."
        )
    sqrt_area = float(np.asarray(record[area_key], dtype=np.float64))
    rotation = np.asarray(record["random_rotation"], dtype=np.float64)
    if rotation.shape != (3, 3):
        raise DatasetError(f"{path}: random_rotation has shape {rotation.shape}; expected (3, 3).")
    if not np.isfinite(sqrt_area) or sqrt_area <= 0:
        raise DatasetError(f"{path}: {area_key} is {sqrt_area}; expected a positive number.")
    partial2full = record.get("partial2full")
    if partial2full is not None:
        partial2full = as_indices(np.asarray(partial2full), path)
    mask = record.get("overlap_mask")
    if mask is not None:
        mask = np.asarray(mask).astype(bool)
    rotation.flags.writeable = False
    return BecosShapeInfo(
        name=str(record["name"]),
        dataset=str(record.get("org_dataset", "")),
        sqrt_area=sqrt_area,
        rotation=rotation,
        partial="partial2full" in record,
        partial2full=partial2full,
        overlap_mask=mask,
        record=record,
        path=path,
    )
