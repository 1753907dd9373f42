"""PFAUST-M and PFAUST-H (Bracha et al.): partial FAUST_r shapes matched to full shapes, P2F.

Each partial shape is a FAUST_r shape with holes (PFAUST-M: 4 holes of geodesic radius 0.16;
PFAUST-H: 13 holes of radius 0.1). The layout is the one GeoLoRA evaluates, inside the
FAUST_r folder::

    FAUST_r/
    ├── neutral_pose/tr_reg_000.off ... tr_reg_090.off   the 10 full shapes (pose 0 of each person)
    ├── corres/<full>.vts          1-based vertex of the full shape at each of the T template points
    ├── off_medium/<partial>.off   partial shapes (off_hard/ for PFAUST-H)
    ├── corres_medium/<partial>.vts  1-based partial vertex of each template point kept
    └── masks_medium/<partial>.vts   T lines of 0/1: which template points the partial shape kept

Template point ``mask.nonzero()[k]`` lies at vertex ``corres_medium[k]-1`` of the partial
shape and at vertex ``corres[mask][k]-1`` of the full shape. ``map_yx`` keeps, for every
partial vertex, the first kept template point that lands on it (-1 when none does); with
``corres/<full>.sym.vts`` present (FAUST_r has it) ``map_yx_sym`` is built the same way.
``overlap_y`` marks the partial vertices with a counterpart; the full shape has no
ground-truth overlap region in this data, so ``overlap_x`` is None. The kept template points
are the pair's ``corr_x`` (their full vertices) and ``corr_y`` (their partial vertices), so
``protocol="template"`` evaluates every kept template point, as GeoLoRA's evaluation does
(a partial vertex that several template points land on then counts once per point).

Pairs: every full shape of the split against every partial shape of the split (GeoLoRA:
test = 2 full x 20 partial = 40 pairs). A shape's split comes from the number its name ends
with: train 0-79, test 80-99 (the first 8 and last 2 full shapes, the first 80 and last 20
partial shapes).

geofeat has not read a complete real copy: the public ``ABracha/PFAUST`` repository holds the
partial shapes, their ``corres/`` files (1-based, written as floats) and ``full_shape_corres/``
(the same files as FAUST_r's ``corres/``), but not the masks. ``geofeat data check pfaust_m``
reports what a copy gives.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geofeat.datasets.base import (
    PairDataset,
    as_flags,
    check_split,
    data_root,
    first_hit_map,
    from_one_based,
    has_counterpart,
    locate,
    natural_key,
    read_indices,
    trailing_number,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError

log = logging.getLogger(__name__)

DIFFICULTIES = {"medium": "medium", "m": "medium", "hard": "hard", "h": "hard"}
N_TRAIN = 80  # shapes 0-79 train, 80-99 test

SOURCE = (
    "partial shapes and their template correspondences: https://github.com/ABracha/PFAUST (PFAUST-M/, PFAUST-H/: "
    "put off/ in off_<difficulty>/ and corres/ in corres_<difficulty>/); the template masks come with the PFAUST data "
    "of https://github.com/ABracha/Wormhole (masks/ -> masks_<difficulty>/); the full shapes and corres/ are FAUST_r "
    "(https://github.com/llorz/SGA18_orientation_BCICP_dataset): copy tr_reg_000, 010, ..., 090 into neutral_pose/."
)


@dataclass(frozen=True)
class _Pair:
    y: str  # partial shape
    x: str  # full shape


class PFaust(PairDataset):
    """PFAUST partial-to-full pairs in GeoLoRA's layout.

    Parameters
    ----------
    root : path-like or None
        The FAUST_r folder holding ``neutral_pose/``, ``off_<difficulty>/`` etc., or a folder
        that contains ``FAUST_r/``. None: ``$GEOFEAT_DATA``.
    split : {"train", "test", "all"}
    difficulty : {"medium", "hard"}
        PFAUST-M or PFAUST-H (``"m"``, ``"h"`` accepted).
    mesh_cache_size : int or None
        See `PairDataset`.
    """

    title = "PFAUST"
    source = SOURCE

    def __init__(
        self,
        root: str | os.PathLike | None = None,
        split: str = "test",
        *,
        difficulty: str = "medium",
        mesh_cache_size: int | None = None,
    ):
        check_split(split, ("train", "test", "all"), self.title)
        if str(difficulty).lower() not in DIFFICULTIES:
            raise DatasetError(f"{self.title}: difficulty must be 'medium' or 'hard'; found {difficulty!r}.")
        self.difficulty = DIFFICULTIES[str(difficulty).lower()]
        given = data_root(root, self.title)
        d = self.difficulty
        folder = locate(
            given,
            [given, given / "FAUST_r"],
            ["neutral_pose/*.off", "corres/", f"off_{d}/*.off", f"corres_{d}/", f"masks_{d}/"],
            title=self.title,
            tree=_tree(d),
            source=self.source,
        )
        super().__init__(folder, split, "p2f", mesh_cache_size=mesh_cache_size)
        self.title = f"PFAUST-{d[0].upper()}"
        self.full_names = self._shapes(self.root / "neutral_pose", "corres")
        self.partial_names = self._shapes(self.root / f"off_{d}", f"corres_{d}", f"masks_{d}")
        self._entries = [_Pair(y=partial, x=full) for full in self.full_names for partial in self.partial_names]

    def _shapes(self, off_dir: Path, *gt_dirs: str) -> list[str]:
        stems = sorted((p.stem for p in off_dir.glob("*.off")), key=natural_key)
        for gt_dir in gt_dirs:
            missing = [s for s in stems if not (self.root / gt_dir / f"{s}.vts").is_file()]
            if missing:
                raise DatasetError(
                    f"{self.title}: {len(missing)} shape(s) of {off_dir} have no {gt_dir}/<name>.vts, first {missing[:3]}."
                )
        if self.split == "all":
            return stems
        unnumbered = [s for s in stems if trailing_number(s) is None]
        if unnumbered:
            raise DatasetError(f"{self.title}: shape names must end in their FAUST number (tr_reg_081); found {unnumbered[:3]}.")
        in_test = self.split == "test"
        chosen = [s for s in stems if (trailing_number(s) >= N_TRAIN) == in_test]
        if not chosen:
            raise DatasetError(f"{self.title}: no shape of the {self.split!r} split in {off_dir} (train: 0-79, test: 80-99).")
        return chosen

    def _load_pair(self, entry: _Pair) -> ShapePair:
        d = self.difficulty
        y = self._mesh(self.root / f"off_{d}" / f"{entry.y}.off")
        x = self._mesh(self.root / "neutral_pose" / f"{entry.x}.off")
        mask = self._array(self.root / f"masks_{d}" / f"{entry.y}.vts", lambda p: as_flags(read_indices(p), p))
        kept_y = self._array(self.root / f"corres_{d}" / f"{entry.y}.vts", lambda p: self._kept(p, mask, y.n_vertices))
        kept_x = self._template(entry.x, x.n_vertices, mask.size)[mask]
        map_yx = first_hit_map(kept_y, kept_x, y.n_vertices)
        map_yx_sym = kept_x_sym = None
        if (self.root / "corres" / f"{entry.x}.sym.vts").is_file():
            kept_x_sym = self._template(entry.x, x.n_vertices, mask.size, sym=True)[mask]
            map_yx_sym = first_hit_map(kept_y, kept_x_sym, y.n_vertices)
        return ShapePair(
            x=x,
            y=y,
            map_yx=map_yx,
            overlap_y=has_counterpart(map_yx),
            map_yx_sym=map_yx_sym,
            protocol="p2f",
            corr_x=kept_x,
            corr_y=kept_y,
            corr_x_sym=kept_x_sym,
        )

    @staticmethod
    def _kept(path: Path, mask: np.ndarray, n_partial: int) -> np.ndarray:
        values = read_indices(path)
        if values.size != int(mask.sum()):
            raise DatasetError(
                f"{path}: expected one partial vertex per kept template point, {int(mask.sum())} entries "
                f"(the ones in its mask file); found {values.size}."
            )
        return from_one_based(values, n_partial, path)

    def _template(self, full: str, n_full: int, n_points: int, sym: bool = False) -> np.ndarray:
        path = self.root / "corres" / f"{full}{'.sym' if sym else ''}.vts"
        template = self._array(path, lambda p: from_one_based(read_indices(p), n_full, p))
        if template.size != n_points:
            raise DatasetError(f"{path}: {template.size} template points, but the masks have {n_points}; they must match.")
        return template


def _tree(difficulty: str) -> str:
    return (
        "FAUST_r/\n"
        "├── neutral_pose/   tr_reg_000.off, tr_reg_010.off, ..., tr_reg_090.off   full shapes\n"
        "├── corres/         <full>.vts (and <full>.sym.vts)    1-based, one line per template point\n"
        f"├── off_{difficulty}/     <partial>.off                       partial shapes tr_reg_000 ... tr_reg_099\n"
        f"├── corres_{difficulty}/  <partial>.vts                       1-based partial vertex per kept template point\n"
        f"└── masks_{difficulty}/   <partial>.vts                       0/1 per template point (kept or not)"
    )
