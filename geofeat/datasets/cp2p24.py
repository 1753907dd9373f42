"""CP2P24 (EchoMatch, Xie et al. CVPR 2025) and CP2P (DPFM, 2021): partial-to-partial pairs.

Layout::

    CP2P24/
    ├── train/ ...
    └── test/
        ├── off/<shape>.off          e.g. cat-01.off
        └── maps/<y>_<x>.map         integers, one per line

A ``<y>_<x>.map`` file holds |V_y| + |V_x| integers: first, for each vertex of y, its vertex
of x (0-based, -1 for none); then, for each vertex of x, 1 if it lies in the overlap with y,
else 0. Each map file is one pair (protocol ``"p2p"``). ``overlap_x`` is that flag block;
``overlap_y`` is the flag block of the reverse file ``<x>_<y>.map`` when it exists, else the
vertices of y with a counterpart. Older CP2P / DPFM files with only the |V_y| map entries are
read too (``overlap_x`` is then None).

This is the layout EchoMatch's reader takes; geofeat has not read real CP2P24 files (they are
not in a repository). ``geofeat data check cp2p24`` reports what a copy gives.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geofeat.datasets.base import (
    PairDataset,
    as_flags,
    check_split,
    check_zero_based,
    data_root,
    has_counterpart,
    locate_split,
    natural_key,
    read_indices,
    split_pair_stems,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError

TREE = """\
CP2P24/
├── train/
└── test/
    ├── off/    <shape>.off
    └── maps/   <y>_<x>.map    |V_y| 0-based vertices of x (-1: none), then |V_x| overlap flags (0/1)"""

SOURCE = (
    "CP2P24: see the 'Datasets' section and download_datasets.sh of https://github.com/vikiehm/echo-match "
    "(EchoMatch); the original CP2P: https://github.com/pvnieo/cp2p-pfarm-benchmark."
)


@dataclass(frozen=True)
class _Pair:
    y: str
    x: str


class CP2P24(PairDataset):
    """CP2P24 partial-to-partial pairs, one per ``.map`` file.

    Parameters
    ----------
    root : path-like or None
        The split folder (holding ``off/`` and ``maps/``), the CP2P24 folder, or a folder
        containing ``CP2P24/``. None: ``$GEOFEAT_DATA``.
    split : {"train", "test"}
    mesh_cache_size : int or None
        See `PairDataset`.
    """

    title = "CP2P24"
    source = SOURCE

    def __init__(self, root: str | os.PathLike | None = None, split: str = "test", *, mesh_cache_size: int | None = None):
        check_split(split, ("train", "test"), self.title)
        given = data_root(root, self.title)
        folder = locate_split(
            given, split, "CP2P24", ["off/*.off", "maps/*.map"], title=self.title, tree=TREE, source=self.source
        )
        super().__init__(folder, split, "p2p", mesh_cache_size=mesh_cache_size)
        names = {p.stem for p in (self.root / "off").glob("*.off")}
        maps = sorted((self.root / "maps").glob("*.map"), key=lambda p: natural_key(p.stem))
        self._entries = [_Pair(*pair) for pair in split_pair_stems(maps, names, self.title)]

    def _load_pair(self, entry: _Pair) -> ShapePair:
        y = self._mesh(self.root / "off" / f"{entry.y}.off")
        x = self._mesh(self.root / "off" / f"{entry.x}.off")
        map_yx, overlap_x = self._read(entry.y, entry.x, y.n_vertices, x.n_vertices)
        overlap_y = has_counterpart(map_yx)
        if (self.root / "maps" / f"{entry.x}_{entry.y}.map").is_file():
            _, flags_y = self._read(entry.x, entry.y, x.n_vertices, y.n_vertices)
            overlap_y = overlap_y if flags_y is None else flags_y.copy()
        overlap_x = None if overlap_x is None else overlap_x.copy()
        return ShapePair(x=x, y=y, map_yx=map_yx.copy(), overlap_x=overlap_x, overlap_y=overlap_y, protocol="p2p")

    def _read(self, src: str, tgt: str, n_src: int, n_tgt: int) -> tuple[np.ndarray, np.ndarray | None]:
        path = self.root / "maps" / f"{src}_{tgt}.map"
        values = self._array(path, read_indices)
        return read_map_block(values, n_src, n_tgt, path)


def read_map_block(values: np.ndarray, n_src: int, n_tgt: int, path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Split the integers of a ``.map`` file into the vertex map and the target's overlap flags.

    Parameters
    ----------
    values : numpy.ndarray of int64, shape (n_src + n_tgt,) or (n_src,)
    n_src, n_tgt : int
        Vertex counts of the two shapes named in the file (first, second).
    path : Path
        The file (named in errors).

    Returns
    -------
    map_src_tgt : numpy.ndarray, shape (n_src,), int64
        0-based vertex of the second shape for each vertex of the first, -1 where none.
    flags_tgt : numpy.ndarray of bool, shape (n_tgt,), or None
        Overlap flags of the second shape; None for files without the flag block.
    """
    if values.size not in (n_src + n_tgt, n_src):
        raise DatasetError(
            f"{path}: expected {n_src} + {n_tgt} = {n_src + n_tgt} integers (a vertex of the second shape for each "
            f"of the {n_src} vertices of the first, then {n_tgt} overlap flags); found {values.size}."
        )
    map_src_tgt = check_zero_based(values[:n_src], n_tgt, path)
    flags = as_flags(values[n_src:], path) if values.size > n_src else None
    return map_src_tgt, flags
