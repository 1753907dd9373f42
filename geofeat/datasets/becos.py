"""BeCoS (Ehm, El Amrani et al.): generated full-full, partial-full and partial-partial pairs.

The benchmark is produced by the BeCoS generator; its output layout::

    BeCoS/
    └── partial_full/            (also full_full/, partial_partial/)
        └── test/                (also train/, val/)
            └── 0/, 1/, 2/ ...   one folder per pair
                ├── 0_<name>.off      shape 0
                ├── 1_<name>.off      shape 1
                ├── corres_10.npy     (V_1,) for each vertex of shape 1 its vertex of shape 0, -1: none
                └── corres_01.npy     (V_0,) the other direction (absent in partial_full)

Both maps are 0-based with -1 for "no counterpart". In ``partial_full`` shape 0 is the full
shape and shape 1 the partial one, so a pair is ``x = shape 0``, ``y = shape 1``, matched
with ``corres_10`` (GeoLoRA and DeepShapeMatchingKit read it the same way); the other
settings use the same orientation. With ``both_directions=True`` the partial-partial and
full-full settings add the reverse pair (``x = shape 1``, ``y = shape 0``, ``corres_01``).

Overlap masks come from the maps: ``overlap_y`` marks the vertices of y with a counterpart,
``overlap_x`` the vertices of x with one in the reverse map (None when ``corres_01.npy`` is
absent). Full-full pairs carry no overlap masks. Meshes keep the scale stored in the .off
files (BeCoS stores each shape at its source dataset's scale); the ``_info.pkl`` files are
never read (unpickling can run code), and the geodesic error normalises by the target's own
surface area anyway.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

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

TREE = """\
BeCoS/
└── <setting>/                 full_full, partial_full or partial_partial
    └── <split>/               train, val or test
        └── <k>/               0, 1, 2, ... one folder per pair
            ├── 0_<name>.off   x (the full shape in partial_full)
            ├── 1_<name>.off   y
            ├── corres_10.npy  (V_1,) int: vertex of shape 0 for each vertex of shape 1, -1: none
            └── corres_01.npy  (V_0,) int: the reverse map (not in partial_full)"""

SOURCE = (
    "generate it with the official generator, https://github.com/NafieAmrani/becos-code "
    "(project page https://nafieamrani.github.io/BeCoS/), following its data_download.md."
)


@dataclass(frozen=True)
class _Pair:
    y: str
    x: str
    folder: Path
    file0: Path
    file1: Path
    reverse: bool  # True: x = shape 1, y = shape 0


class BeCoS(PairDataset):
    """BeCoS pairs of one setting and split.

    Parameters
    ----------
    root : path-like or None
        The split folder itself (``.../partial_full/test``), the setting folder, the BeCoS
        folder, or a folder that contains ``BeCoS/``. None: ``$GEOFEAT_DATA``.
    split : {"train", "val", "test"}
    setting : {"partial_full", "partial_partial", "full_full"}
        Gives the protocol: p2f, p2p or f2f.
    both_directions : bool
        Also match shape 0 to shape 1 (p2p and f2f only).
    mesh_cache_size : int or None
        See `PairDataset`. Every BeCoS shape belongs to one pair, so a bound (say 64) keeps
        memory flat while iterating.
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
        pairs = []
        for folder in _pair_folders(self.root):
            file0, file1 = self._shape_file(folder, "0"), self._shape_file(folder, "1")
            name0, name1 = f"{folder.name}_{file0.stem}", f"{folder.name}_{file1.stem}"
            needed = ["corres_10.npy"] + (["corres_01.npy"] if both_directions else [])
            absent = [f for f in needed if not (folder / f).is_file()]
            if absent:
                raise DatasetError(
                    f"{self.title}: pair folder {folder} lacks {', '.join(absent)}; regenerate it or remove the folder."
                )
            pairs.append(_Pair(y=name1, x=name0, folder=folder, file0=file0, file1=file1, reverse=False))
            if both_directions:
                pairs.append(_Pair(y=name0, x=name1, folder=folder, file0=file0, file1=file1, reverse=True))
        return pairs

    def _shape_file(self, folder: Path, side: str) -> Path:
        found = sorted(folder.glob(f"{side}_*.off"))
        if len(found) != 1:
            raise DatasetError(f"{self.title}: pair folder {folder} must hold exactly one {side}_<name>.off; found {len(found)}.")
        return found[0]

    def _load_pair(self, entry: _Pair) -> ShapePair:
        folder = entry.folder
        mesh0 = self._mesh(entry.file0, f"{folder.name}_{entry.file0.stem}")
        mesh1 = self._mesh(entry.file1, f"{folder.name}_{entry.file1.stem}")
        map_10 = self._map(folder / "corres_10.npy", mesh1.n_vertices, mesh0.n_vertices)
        path_01 = folder / "corres_01.npy"
        map_01 = self._map(path_01, mesh0.n_vertices, mesh1.n_vertices) if path_01.is_file() else None
        x, y, map_yx, map_xy = (mesh1, mesh0, map_01, map_10) if entry.reverse else (mesh0, mesh1, map_10, map_01)
        if self.protocol == "f2f":
            return ShapePair(x=x, y=y, map_yx=map_yx.copy(), protocol="f2f")
        overlap_x = None if map_xy is None else has_counterpart(map_xy)
        return ShapePair(
            x=x, y=y, map_yx=map_yx.copy(), overlap_x=overlap_x, overlap_y=has_counterpart(map_yx), protocol=self.protocol
        )

    def _map(self, path: Path, n_source: int, n_target: int) -> np.ndarray:
        return self._array(path, lambda p: read_becos_map(p, n_source, n_target))


def _pair_folders(folder: Path) -> list[Path]:
    """Numbered subfolders, in numeric order (empty when ``folder`` is not a folder)."""
    if not folder.is_dir():
        return []
    return sorted((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))


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
    if values.ndim != 1:
        raise DatasetError(
            f"{path}: expected a vertex-to-vertex map of shape ({n_source},); found shape {values.shape}. "
            "Maps saved as barycentric coordinates are not supported: generate BeCoS with vertex-to-vertex "
            "correspondences."
        )
    values = as_indices(values, path)
    check_length(values, n_source, path, "one entry per vertex of the mapped shape")
    return check_zero_based(values, n_target, path)
