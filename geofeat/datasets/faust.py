"""FAUST_r and SCAPE_r: remeshed full shapes with correspondences through a common template.

On disk (the layout used by ULRSSM and the BCICP release)::

    FAUST_r/
    ├── off/tr_reg_000.off ...       the meshes
    ├── corres/tr_reg_000.vts ...     line i: 1-based vertex of this shape at template point i
    ├── corres/tr_reg_000.sym.vts ... the same for the left-right mirrored template (optional)
    └── test_pairs.txt                optional list of "<shape> <shape>" pairs

For a pair (y = A, x = B), vertex ``A.vts[i]-1`` of A corresponds to vertex ``B.vts[i]-1``
of B. ``map_yx`` holds, for every vertex of A, the counterpart given by the first template
point that lands on it, and -1 where no template point does. ``map_yx_sym`` does the same
with ``B.sym.vts``. Every pair is full-to-full (protocol ``"f2f"``); no overlap masks.

Splits follow ULRSSM: FAUST_r has 100 shapes, train = the first 80, test = the last 20;
SCAPE_r has 71 shapes, train = the first 51, test = the last 20. A shape's place is the
number its name ends with (``tr_reg_081`` is shape 81, ``mesh052`` is shape 52), which
equals its place in the sorted folder.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from geofeat.datasets.base import (
    PairDataset,
    check_split,
    data_root,
    first_hit_map,
    from_one_based,
    locate,
    natural_key,
    read_indices,
    trailing_number,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError
from geofeat.mesh import Mesh

log = logging.getLogger(__name__)

PAIRS_FILE = "test_pairs.txt"


@dataclass(frozen=True)
class _Pair:
    y: str
    x: str


class RemeshedTemplateDataset(PairDataset):
    """Full-to-full pairs of a remeshed collection with template correspondences (.vts).

    Parameters
    ----------
    root : path-like or None
        The dataset folder (holding ``off/`` and ``corres/``) or a folder that contains it
        under its usual name (``FAUST_r``, ``SCAPE_r``). None: ``$GEOFEAT_DATA``.
    split : {"train", "test", "all"}
        Which shapes (see the module notes); default ``"test"``.
    pairs : {"all", "file"} or sequence of (str, str)
        ``"all"`` (default): every ordered pair (y, x) of two different shapes of the split.
        ``"combinations"``: every unordered pair once, x the earlier shape and y the later
        one (the 190 pairs ``i < j`` of the 20 FAUST_r test shapes that the references
        evaluate). ``"file"``: the pairs listed in ``test_pairs.txt`` (first column y, second column x)
        whose two shapes both belong to the split. Or an explicit list of (y, x) shape names.
    mesh_cache_size : int or None
        See `PairDataset`.
    """

    folder_names: ClassVar[tuple[str, ...]] = ()
    n_shapes: ClassVar[int] = 0
    n_train: ClassVar[int] = 0

    def __init__(
        self,
        root: str | os.PathLike | None = None,
        split: str = "test",
        *,
        pairs: str | Sequence[tuple[str, str]] = "all",
        mesh_cache_size: int | None = None,
    ):
        check_split(split, ("train", "test", "all"), self.title)
        given = data_root(root, self.title)
        folder = locate(
            given,
            [given] + [given / name for name in self.folder_names],
            ["off/*.off", "corres/"],
            title=self.title,
            tree=self._tree(),
            source=self.source,
        )
        super().__init__(folder, split, "f2f", mesh_cache_size=mesh_cache_size)
        self.shape_names = self._split_shapes(self._all_shapes())
        self._entries = self._pairs(pairs)

    @classmethod
    def _tree(cls) -> str:
        return (
            f"{cls.folder_names[0]}/\n"
            "├── off/      <shape>.off          one mesh per shape\n"
            "├── corres/   <shape>.vts          1-based vertex at each template point\n"
            "│             <shape>.sym.vts      same for the mirrored template (optional)\n"
            "└── test_pairs.txt                 optional: one '<shape> <shape>' pair per line"
        )

    def _all_shapes(self) -> list[str]:
        stems = sorted((p.stem for p in (self.root / "off").glob("*.off")), key=natural_key)
        no_gt = [s for s in stems if not (self.root / "corres" / f"{s}.vts").is_file()]
        if no_gt:
            raise DatasetError(
                f"{self.title}: {len(no_gt)} mesh(es) in {self.root / 'off'} have no correspondence file "
                f"corres/<name>.vts, first {no_gt[:3]}. Every shape needs one; restore the missing files."
            )
        return stems

    def _split_shapes(self, stems: list[str]) -> list[str]:
        if self.split == "all":
            return stems
        wanted = range(0, self.n_train) if self.split == "train" else range(self.n_train, self.n_shapes)
        unnumbered = [s for s in stems if trailing_number(s) is None]
        if unnumbered:
            raise DatasetError(
                f"{self.title}: cannot place {unnumbered[:3]} in the {self.split!r} split: shape names must end in "
                "their number (tr_reg_081, mesh052). Use split='all' for other collections."
            )
        chosen = [s for s in stems if trailing_number(s) in wanted]
        expected = f"{len(wanted)} shapes (numbers {wanted.start}-{wanted.stop - 1})"
        if len(chosen) != len(wanted):
            log.warning(
                "%s: the %r split should hold %s; found %d in %s",
                self.title,
                self.split,
                expected,
                len(chosen),
                self.root / "off",
            )
        if not chosen:
            raise DatasetError(f"{self.title}: none of the {expected} of the {self.split!r} split is in {self.root / 'off'}.")
        return chosen

    def _pairs(self, pairs: str | Sequence[tuple[str, str]]) -> list[_Pair]:
        if isinstance(pairs, str):
            if pairs == "all":
                return [_Pair(y, x) for y in self.shape_names for x in self.shape_names if y != x]
            if pairs == "combinations":
                names = self.shape_names
                return [_Pair(names[j], names[i]) for i in range(len(names)) for j in range(i + 1, len(names))]
            if pairs == "file":
                return self._listed_pairs()
            raise DatasetError(
                f"{self.title}: pairs must be 'all', 'combinations', 'file' or a list of (y, x) names; found {pairs!r}."
            )
        chosen = [_Pair(str(y), str(x)) for y, x in pairs]
        unknown = sorted({n for p in chosen for n in (p.y, p.x)} - set(self.shape_names))
        if unknown:
            raise DatasetError(f"{self.title}: pairs name shapes that are not in the {self.split!r} split: {unknown[:5]}.")
        return chosen

    def _listed_pairs(self) -> list[_Pair]:
        path = self.root / PAIRS_FILE
        if not path.is_file():
            raise DatasetError(f"{self.title}: pairs='file' needs {path}, which does not exist. Use pairs='all'.")
        rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
        bad = [i for i, row in enumerate(rows) if len(row) != 2]
        if bad:
            raise DatasetError(f"{path}: expected two shape names per line; line {bad[0] + 1} is {' '.join(rows[bad[0]])!r}.")
        in_split = set(self.shape_names)
        listed = [_Pair(y, x) for y, x in rows if y in in_split and x in in_split]
        if len(listed) < len(rows):
            log.info("%s: %d of the %d pairs in %s lie in the %r split", self.title, len(listed), len(rows), path, self.split)
        if not listed:
            raise DatasetError(f"{path}: none of its {len(rows)} pairs lies in the {self.split!r} split; try split='all'.")
        return listed

    def shape_files(self) -> dict[str, Path]:
        """``off/<name>.off`` of every shape of the split, by name (nothing is read)."""
        return {name: self.root / "off" / f"{name}.off" for name in self.shape_names}

    def mesh(self, name: str) -> Mesh:
        """The mesh of shape ``name`` (cached)."""
        return self._mesh(self.root / "off" / f"{name}.off")

    def template_map(self, name: str) -> np.ndarray:
        """Shape (T,) int64: the vertex of shape ``name`` at each template point, 0-based (-1: none)."""
        return self._template(self.root / "corres" / f"{name}.vts", name)

    def template_map_sym(self, name: str) -> np.ndarray | None:
        """Like `template_map` for the mirrored template, or None when ``<name>.sym.vts`` is absent."""
        path = self.root / "corres" / f"{name}.sym.vts"
        return self._template(path, name) if path.is_file() else None

    def _template(self, path: Path, name: str) -> np.ndarray:
        n_vertices = self.mesh(name).n_vertices
        return self._array(path, lambda p: from_one_based(read_indices(p), n_vertices, p))

    def _load_pair(self, entry: _Pair) -> ShapePair:
        y, x = self.mesh(entry.y), self.mesh(entry.x)
        template_y, template_x = self.template_map(entry.y), self.template_map(entry.x)
        if template_y.size != template_x.size:
            raise DatasetError(
                f"{self.title}: {entry.y}.vts has {template_y.size} template points but {entry.x}.vts has "
                f"{template_x.size}; both must index the same template."
            )
        map_yx = first_hit_map(template_y, template_x, y.n_vertices)
        template_x_sym = self.template_map_sym(entry.x)
        map_yx_sym = None
        if template_x_sym is not None and template_x_sym.size == template_y.size:
            map_yx_sym = first_hit_map(template_y, template_x_sym, y.n_vertices)
        elif template_x_sym is not None:
            raise DatasetError(f"{self.title}: {entry.x}.sym.vts has {template_x_sym.size} entries; expected {template_y.size}.")
        return ShapePair(
            x=x,
            y=y,
            map_yx=map_yx,
            map_yx_sym=map_yx_sym,
            protocol="f2f",
            corr_x=template_x,
            corr_y=template_y,
            corr_x_sym=template_x_sym,
        )


class FaustRemeshed(RemeshedTemplateDataset):
    """FAUST_r: 100 remeshed FAUST registrations (10 people x 10 poses), ~5,000 vertices each."""

    title = "FAUST_r"
    folder_names = ("FAUST_r",)
    n_shapes = 100
    n_train = 80
    source = (
        "the remeshed FAUST of Ren et al. 2018, https://github.com/llorz/SGA18_orientation_BCICP_dataset "
        "(folder Dataset/FAUST/vtx_5k), or the FAUST_r folder of the data linked from the README of "
        "https://github.com/dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching. "
        "Original FAUST: https://faust.is.tue.mpg.de (research licence)."
    )


class ScapeRemeshed(RemeshedTemplateDataset):
    """SCAPE_r: 71 remeshed poses of one person (mesh000 ... mesh070)."""

    title = "SCAPE_r"
    folder_names = ("SCAPE_r",)
    n_shapes = 71
    n_train = 51
    source = (
        "the SCAPE_r folder of the data linked from the README of "
        "https://github.com/dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching "
        "(remeshed by Ren et al. 2018 from SCAPE, Anguelov et al. 2005)."
    )
