"""SHREC'16 Partial Matching of Deformable Shapes (CUTS and HOLES), partial-to-full.

Each partial shape is matched to the full shape of its class in the canonical ("null")
pose: ``x`` is the null shape, ``y`` the partial one, protocol ``"p2f"``. A partial shape's
name tells its class: ``cuts_cat_shape_1`` belongs to null shape ``cat`` (``<kind>_<class>_
shape_<n>``). Three layouts are read:

Original contest archive::

    <root>/
    ├── null/<class>.off
    └── cuts/  cuts_<class>_shape_<n>.off, .baryc_gt, .baryc_gt_sym (optional)
        (holes/ likewise)

A ``.baryc_gt`` row per partial vertex holds the 1-based index of a triangle of the null
shape and the three barycentric weights of the corresponding point in that triangle. geofeat
keeps vertex-to-vertex ground truth: the counterpart is the corner of that triangle with the
largest weight (the first corner on ties). The triangle index counts the triangles of the
null shape's file as stored: `Mesh` drops repeated and collapsed triangles (DPFM's copy of the
``cat`` null shape repeats 12), which would shift every later index, so the conversion reads
the file's own triangle list. Rows that name a triangle the file does not have get -1, with
a warning. ``.baryc_gt_sym`` (the mirrored ground truth) gives ``map_yx_sym`` the same way.

Layout of ULRSSM and GeoLoRA (``SHREC16/`` train, ``SHREC16_test/`` test)::

    <root>/
    ├── null/off/<class>.off
    └── cuts/off/cuts_<class>_shape_<n>.off
        cuts/corres/cuts_<class>_shape_<n>.vts   1-based null-shape vertex per partial vertex

Entries <= 0 in a ``.vts`` file mean "no counterpart" (-1).

Layout of DPFM (``shrec_partial_train/``, ``shrec_partial_test/``)::

    <root>/
    ├── shapes/  cuts-<class>.off                 the null shape, under the partiality's prefix
    │            cuts-<class><n>.off              partial shapes (cuts-cat1.off)
    └── maps/    cuts-<class><n>_cuts-<class>.map  0-based null-shape vertex per partial vertex

Each map file whose name starts with the partiality is one pair: the first shape of its name
is the partial shape ``y``, the second the full shape ``x`` (DPFM reads them so). A ``.map``
file holds one line per vertex of the partial shape: its vertex of the full shape, **0-based**,
-1 for none. The base was read off the real files of DPFM's repository: the partial shape
is cut from the full one, and with 0-based indices each partial vertex lies on its mapped
full vertex (median distance 4e-5 of the bounding-box diagonal; read as 1-based, 0.008 and up
to 0.24). Shape names are kept as stored (``cuts-cat1``), so they differ from the other
layouts' names.

In every layout ``overlap_y`` marks the partial vertices with a counterpart; the data defines
no overlap region on the null shape, so ``overlap_x`` is None. Meshes are returned as stored;
GeoLoRA rotates SHREC'16 shapes by 90 degrees about the x axis before rendering them.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geofeat.datasets.base import (
    PairDataset,
    check_length,
    check_split,
    check_zero_based,
    data_root,
    from_one_based,
    has_counterpart,
    layout_error,
    missing_items,
    natural_key,
    read_indices,
    read_table,
    split_pair_stems,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError, MeshError
from geofeat.mesh import read_mesh_arrays

log = logging.getLogger(__name__)

PARTIALITIES = ("cuts", "holes")
LAYOUTS = ("auto", "original", "ulrssm", "dpfm")
#: How each layout is named in messages.
LAYOUT_TITLES = {"original": "the contest archive", "ulrssm": "the ULRSSM / GeoLoRA layout", "dpfm": "DPFM's layout"}
SPLIT_FOLDERS = {"train": ("SHREC16", "shrec_partial_train"), "test": ("SHREC16_test", "shrec_partial_test")}

TREE = """\
original contest archive:
<root>/
├── null/    <class>.off                          cat, centaur, david, dog, horse, michael, victoria, wolf
├── cuts/    cuts_<class>_shape_<n>.off           partial shapes
│            cuts_<class>_shape_<n>.baryc_gt      ground truth (.baryc_gt_sym: mirrored, optional)
└── holes/   holes_<class>_shape_<n>.off, .baryc_gt
or the ULRSSM / GeoLoRA layout (SHREC16/ for train, SHREC16_test/ for test):
<root>/
├── null/off/       <class>.off
├── cuts/off/       cuts_<class>_shape_<n>.off
├── cuts/corres/    cuts_<class>_shape_<n>.vts    1-based null-shape vertex per partial vertex
└── holes/off/, holes/corres/
or DPFM's layout (shrec_partial_train/, shrec_partial_test/):
<root>/
├── shapes/    cuts-<class>.off, cuts-<class><n>.off    null shape and partial shapes (holes-... alike)
└── maps/      cuts-<class><n>_cuts-<class>.map          0-based null-shape vertex per partial vertex, -1: none"""

SOURCE = (
    "the contest page http://www.dais.unive.it/~shrec2016/ (original archive, training set with ground truth); "
    "the test set with ground truth is in https://github.com/pvnieo/cp2p-pfarm-benchmark (shrec16partiality/); "
    "the ULRSSM layout (SHREC16, SHREC16_test) comes with the data linked from the README of "
    "https://github.com/dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching; "
    "DPFM's layout (shrec_partial_train, shrec_partial_test) is the one read by https://github.com/pvnieo/DPFM."
)


@dataclass(frozen=True)
class _Pair:
    y: str  # partial shape
    x: str  # null shape
    gt: Path  # its ground-truth file


class Shrec16Partial(PairDataset):
    """SHREC'16 Partial (CUTS or HOLES): every partial shape against its null shape.

    Parameters
    ----------
    root : path-like or None
        The dataset folder (holding ``null/`` and ``cuts/`` or ``holes/``, or DPFM's
        ``shapes/`` and ``maps/``), or a folder that contains ``SHREC16/`` or
        ``shrec_partial_train/`` (split ``"train"``), ``SHREC16_test/`` or
        ``shrec_partial_test/`` (split ``"test"``). None: ``$GEOFEAT_DATA``.
    split : {"train", "test"}
        Only used to pick the split's folder inside ``root``; a dataset folder given directly
        is used as it is.
    partiality : {"cuts", "holes"}
    layout : {"auto", "original", "ulrssm", "dpfm"}
        On-disk layout; ``"auto"`` takes the first that the folder holds, in the order
        ulrssm (``null/off/``), original (``null/``), dpfm (``shapes/``, ``maps/``).
    shapes : sequence of str, path-like or None
        Only these partial shapes (names with or without ``.off``, as the layout names them:
        ``cuts_cat_shape_1``, or ``cuts-cat1`` in DPFM's layout), or a text file with one name
        per line (such as a published test subset). None: all.
    mesh_cache_size : int or None
        See `PairDataset`.
    """

    title = "SHREC'16 Partial"
    source = SOURCE

    def __init__(
        self,
        root: str | os.PathLike | None = None,
        split: str = "test",
        *,
        partiality: str = "cuts",
        layout: str = "auto",
        shapes: Sequence[str] | str | os.PathLike | None = None,
        mesh_cache_size: int | None = None,
    ):
        check_split(split, ("train", "test"), self.title)
        if partiality not in PARTIALITIES:
            raise DatasetError(f"{self.title}: partiality must be 'cuts' or 'holes'; found {partiality!r}.")
        if layout not in LAYOUTS:
            raise DatasetError(f"{self.title}: layout must be one of {LAYOUTS}; found {layout!r}.")
        given = data_root(root, self.title)
        folder, self.layout = self._locate(given, split, partiality, layout)
        super().__init__(folder, split, "p2f", mesh_cache_size=mesh_cache_size)
        self.title = f"SHREC'16 Partial {partiality.upper()}"
        self.partiality = partiality
        if self.layout == "dpfm":
            self._entries = self._dpfm_pairs(shapes)
        else:
            self._entries = self._pairs(self._partial_names(shapes))

    @staticmethod
    def _required(partiality: str, layout: str) -> list[str]:
        if layout == "original":
            return ["null/*.off", f"{partiality}/*.off", f"{partiality}/*.baryc_gt"]
        if layout == "dpfm":
            return ["shapes/*.off", f"maps/{partiality}*.map"]
        return ["null/off/*.off", f"{partiality}/off/*.off", f"{partiality}/corres/*.vts"]

    def _locate(self, given: Path, split: str, partiality: str, layout: str) -> tuple[Path, str]:
        candidates = [given] + [given / name for name in SPLIT_FOLDERS[split]]
        layouts = ("ulrssm", "original", "dpfm") if layout == "auto" else (layout,)
        for folder in candidates:
            for kind in layouts:
                if not missing_items(folder, self._required(partiality, kind)):
                    return folder, kind
        folder, problems = self._closest(given, candidates, layouts, partiality)
        if folder is None:  # no layout is even partly there
            if not given.is_dir() or len(layouts) == 1:
                problems = missing_items(given, self._required(partiality, layouts[0]))
            else:
                problems = [
                    f"not {LAYOUT_TITLES[kind]} ({', '.join(missing_items(given, self._required(partiality, kind)))})"
                    for kind in layouts
                ]
            folder = given
        hint = f"Also looked in: {', '.join(str(c) for c in candidates if c != folder)}."
        raise layout_error(self.title, folder, problems, TREE, self.source, hint)

    def _closest(
        self, given: Path, candidates: list[Path], layouts: Sequence[str], partiality: str
    ) -> tuple[Path | None, list[str]]:
        """The folder and layout that come closest (fewest items missing, some present), with what it lacks."""
        best: tuple[int, Path, str, list[str]] | None = None
        for folder in candidates:
            if not folder.is_dir():
                continue
            for kind in layouts:
                required = self._required(partiality, kind)
                problems = missing_items(folder, required)
                if len(problems) < len(required) and (best is None or len(problems) < best[0]):
                    best = (len(problems), folder, kind, problems)
        if best is None:
            return None, []
        _, folder, kind, problems = best
        return folder, [f"it looks like {LAYOUT_TITLES[kind]}, but {'; '.join(problems)}"]

    def _partial_dir(self) -> Path:
        return self.root / self.partiality / ("off" if self.layout == "ulrssm" else "")

    def _null_path(self, name: str) -> Path:
        return self.root / "null" / ("off" if self.layout == "ulrssm" else "") / f"{name}.off"

    def _partial_names(self, shapes: Sequence[str] | str | os.PathLike | None) -> list[str]:
        available = sorted((p.stem for p in self._partial_dir().glob("*.off")), key=natural_key)
        if shapes is None:
            return available
        wanted = self._wanted(shapes)
        unknown = sorted(set(wanted) - set(available))
        if unknown:
            raise DatasetError(f"{self.title}: shapes not found in {self._partial_dir()}: {unknown[:5]}.")
        return sorted(set(wanted), key=natural_key)

    def _null_name(self, partial: str) -> str:
        parts = partial.split("_")
        if len(parts) < 3 or parts[0] != self.partiality:
            raise DatasetError(
                f"{self.title}: cannot tell the null shape of {partial!r}; partial shapes are named "
                f"'{self.partiality}_<class>_shape_<n>' (for example {self.partiality}_cat_shape_1)."
            )
        return parts[1]

    def _pairs(self, partials: list[str]) -> list[_Pair]:
        pairs = [_Pair(y=name, x=self._null_name(name), gt=self._gt_path(name)) for name in partials]
        for null in sorted({p.x for p in pairs}):
            if not self._null_path(null).is_file():
                raise DatasetError(
                    f"{self.title}: null shape {self._null_path(null)} is missing; the partial shapes of class {null!r} need it."
                )
        missing_gt = [p.y for p in pairs if not p.gt.is_file()]
        if missing_gt:
            raise DatasetError(
                f"{self.title}: {len(missing_gt)} partial shape(s) have no ground-truth file, first "
                f"{self._gt_path(missing_gt[0])}. Restore it, or leave those shapes out with shapes=[...]."
            )
        return pairs

    def _dpfm_pairs(self, shapes: Sequence[str] | str | os.PathLike | None) -> list[_Pair]:
        """One pair per ``maps/<partiality>*.map`` file: (first shape of its name, second shape)."""
        names = {path.stem for path in (self.root / "shapes").glob("*.off")}
        maps = sorted((self.root / "maps").glob(f"{self.partiality}*.map"), key=lambda p: natural_key(p.stem))
        pairs = [_Pair(y=y, x=x, gt=path) for path, (y, x) in zip(maps, split_pair_stems(maps, names, self.title), strict=True)]
        if shapes is not None:
            wanted = set(self._wanted(shapes))
            unknown = sorted(wanted - {p.y for p in pairs})
            if unknown:
                raise DatasetError(f"{self.title}: shapes with no map file in {self.root / 'maps'}: {unknown[:5]}.")
            pairs = [p for p in pairs if p.y in wanted]
        return pairs

    def _wanted(self, shapes: Sequence[str] | str | os.PathLike) -> list[str]:
        """Shape names from a list or a text file of names (``.off`` suffixes dropped)."""
        if isinstance(shapes, (str, os.PathLike)):
            if not Path(shapes).is_file():
                raise DatasetError(
                    f"{self.title}: shapes must be a list of names or a text file of names; {shapes} is not a file."
                )
            shapes = [line.strip() for line in Path(shapes).read_text().splitlines() if line.strip()]
        return [Path(s).stem if str(s).endswith(".off") else str(s) for s in shapes]

    def _gt_path(self, partial: str, sym: bool = False) -> Path:
        if self.layout == "ulrssm":
            return self.root / self.partiality / "corres" / f"{partial}.vts"
        return self._partial_dir() / f"{partial}.baryc_gt{'_sym' if sym else ''}"

    def _load_pair(self, entry: _Pair) -> ShapePair:
        map_yx_sym = None
        if self.layout == "dpfm":
            y = self._mesh(self.root / "shapes" / f"{entry.y}.off")
            x = self._mesh(self.root / "shapes" / f"{entry.x}.off")
            map_yx = self._array(entry.gt, lambda p: self._read_map(p, y.n_vertices, x.n_vertices))
        elif self.layout == "ulrssm":
            y = self._mesh(self._partial_dir() / f"{entry.y}.off")
            x = self._mesh(self._null_path(entry.x))
            map_yx = self._array(entry.gt, lambda p: self._read_vts(p, y.n_vertices, x.n_vertices))
        else:
            y = self._mesh(self._partial_dir() / f"{entry.y}.off")
            null_path = self._null_path(entry.x)
            x = self._mesh(null_path)
            # cached under a key of its own: the triangles as the file stores them, not x.faces
            triangles = self._array(Path(f"{null_path}#triangles"), lambda _: file_triangles(null_path))
            map_yx = self._array(entry.gt, lambda p: baryc_to_vertex_map(p, y.n_vertices, triangles))
            sym_path = self._gt_path(entry.y, sym=True)
            if sym_path.is_file():
                map_yx_sym = self._array(sym_path, lambda p: baryc_to_vertex_map(p, y.n_vertices, triangles))
        sym = None if map_yx_sym is None else map_yx_sym.copy()
        return ShapePair(x=x, y=y, map_yx=map_yx.copy(), overlap_y=has_counterpart(map_yx), map_yx_sym=sym, protocol="p2f")

    @staticmethod
    def _read_vts(path: Path, n_partial: int, n_null: int) -> np.ndarray:
        values = read_indices(path)
        check_length(values, n_partial, path, "one null-shape vertex per partial vertex")
        return from_one_based(values, n_null, path)

    @staticmethod
    def _read_map(path: Path, n_partial: int, n_null: int) -> np.ndarray:
        values = read_indices(path)
        check_length(values, n_partial, path, "one null-shape vertex per partial vertex")
        return check_zero_based(values, n_null, path)


def file_triangles(path: Path) -> np.ndarray:
    """The triangles of an OFF file exactly as stored, row for row.

    `Mesh` drops triangles that name a vertex twice and repeats of a triangle; ground truth
    that indexes triangles (``.baryc_gt``) counts the file's rows, so it needs this list.
    Vertex indices are the same in both (vertices are never dropped or reordered).

    Parameters
    ----------
    path : Path
        An OFF file of triangles.

    Returns
    -------
    numpy.ndarray, shape (F, 3), int64
        F = the face count of the file.
    """
    try:
        _, faces = read_mesh_arrays(path)
    except MeshError as err:
        raise DatasetError(f"cannot read the triangles of the null shape: {err}") from None
    if faces is None:
        raise DatasetError(f"{path}: the null shape has no triangles; its .baryc_gt ground truth names triangles.")
    return faces


def baryc_to_vertex_map(path: Path, n_partial: int, null_faces: np.ndarray) -> np.ndarray:
    """Read a SHREC'16 ``.baryc_gt`` file as a vertex-to-vertex map.

    Parameters
    ----------
    path : Path
        One row per partial vertex: 1-based triangle index into the null shape, then three
        barycentric weights.
    n_partial : int
        Vertex count of the partial shape (the number of rows expected).
    null_faces : numpy.ndarray, shape (F, 3), int64
        Triangles of the null shape as its file stores them (`file_triangles`, not
        ``Mesh.faces``, which may have dropped some).

    Returns
    -------
    numpy.ndarray, shape (n_partial,), int64
        For each partial vertex the corner of its triangle with the largest weight (first
        corner on ties), -1 where the row names no triangle of the null shape.
    """
    rows = read_table(path, 4)
    check_length(rows, n_partial, path, "one row per partial vertex")
    triangle = rows[:, 0]
    if np.any(triangle != np.round(triangle)):
        raise DatasetError(f"{path}: the first column must hold integer (1-based) triangle indices.")
    triangle = triangle.astype(np.int64) - 1
    valid = (triangle >= 0) & (triangle < len(null_faces))
    if not valid.all():
        log.warning(
            "%s: %d of %d rows name no triangle of the null shape (it has %d); those vertices get -1",
            path,
            int((~valid).sum()),
            valid.size,
            len(null_faces),
        )
    corner = np.argmax(rows[:, 1:], axis=1)
    out = np.full(n_partial, -1, dtype=np.int64)
    out[valid] = null_faces[triangle[valid], corner[valid]]
    return out
