"""PARTIALSMAL (Ehm et al., CVPR 2024): partial-to-partial pairs of SMAL animals.

Layout (as released in the gc-ppsm repository)::

    PARTIALSMAL/
    ├── train/ ...
    └── test/
        ├── shapes/<shape>.off           e.g. cuts_0_cougar_04.off
        └── maps/<src>_<tgt>.vts         one line per vertex of <src>: its vertex of <tgt>

Map files are 0-based with -1 for "no counterpart": line i of ``<y>_<x>.vts`` is the vertex of
x matched to vertex i of y (one line per vertex of the first shape of the name). Each file is
one pair (y = src, x = tgt, protocol ``"p2p"``, ``map_yx`` as stored); shape names contain
underscores themselves, so a map's name is split where both halves are shape names.
``overlap_y`` marks the vertices of y with a counterpart, ``overlap_x`` those of x with one in
the reverse file ``<x>_<y>.vts``.

Both situations are read. The released benchmark holds every map in both directions (train:
304 files, 152 shape pairs both ways; test: 100 files, 50 shape pairs both ways), so it gives
two pairs per pair of shapes, each with ``overlap_x`` from the other file. A copy with one
direction only (such as a sample) gives one pair per file, with ``overlap_x`` None. The
``shapes/`` folder may hold shapes that no map names; they are not read. Meshes are returned
as stored; GeoLoRA flips SMAL shapes upside down (180 degrees about x) before rendering them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geofeat.datasets.base import (
    PairDataset,
    check_length,
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

TREE = """\
PARTIALSMAL/
├── train/
└── test/
    ├── shapes/   <shape>.off              for example cuts_0_cougar_04.off
    └── maps/     <src>_<tgt>.vts          0-based vertex of <tgt> per vertex of <src>, -1: none"""

SOURCE = "https://github.com/vikiehm/gc-ppsm (folder PARTIALSMAL; shapes from SMAL, https://smal.is.tue.mpg.de)."


@dataclass(frozen=True)
class _Pair:
    y: str
    x: str


class PartialSmal(PairDataset):
    """PARTIALSMAL partial-to-partial pairs, one per map file.

    Parameters
    ----------
    root : path-like or None
        The split folder (holding ``shapes/`` and ``maps/``), the PARTIALSMAL folder, or a
        folder containing ``PARTIALSMAL/``. None: ``$GEOFEAT_DATA``.
    split : {"train", "test"}
    mesh_cache_size : int or None
        See `PairDataset`.
    """

    title = "PARTIALSMAL"
    source = SOURCE

    def __init__(self, root: str | os.PathLike | None = None, split: str = "test", *, mesh_cache_size: int | None = None):
        check_split(split, ("train", "test"), self.title)
        given = data_root(root, self.title)
        required = ["shapes/*.off", "maps/*.vts"]
        folder = locate_split(given, split, "PARTIALSMAL", required, title=self.title, tree=TREE, source=self.source)
        super().__init__(folder, split, "p2p", mesh_cache_size=mesh_cache_size)
        names = {p.stem for p in (self.root / "shapes").glob("*.off")}
        maps = sorted((self.root / "maps").glob("*.vts"), key=lambda p: natural_key(p.stem))
        self._entries = [_Pair(*pair) for pair in split_pair_stems(maps, names, self.title)]

    def _load_pair(self, entry: _Pair) -> ShapePair:
        y = self._mesh(self.root / "shapes" / f"{entry.y}.off")
        x = self._mesh(self.root / "shapes" / f"{entry.x}.off")
        map_yx = self._map(entry.y, entry.x, y.n_vertices, x.n_vertices)
        reverse = self.root / "maps" / f"{entry.x}_{entry.y}.vts"
        overlap_x = has_counterpart(self._map(entry.x, entry.y, x.n_vertices, y.n_vertices)) if reverse.is_file() else None
        return ShapePair(x=x, y=y, map_yx=map_yx.copy(), overlap_x=overlap_x, overlap_y=has_counterpart(map_yx), protocol="p2p")

    def _map(self, src: str, tgt: str, n_src: int, n_tgt: int) -> np.ndarray:
        return self._array(self.root / "maps" / f"{src}_{tgt}.vts", lambda p: _read_map(p, n_src, n_tgt))


def _read_map(path: Path, n_src: int, n_tgt: int) -> np.ndarray:
    values = read_indices(path)
    check_length(values, n_src, path, "one line per vertex of the first shape in the file name")
    return check_zero_based(values, n_tgt, path)
