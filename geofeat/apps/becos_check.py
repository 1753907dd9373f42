"""Checking what a run of the BeCoS generator wrote: is it complete, and does it agree with its records?

`check_becos` reads a generator output folder (see `geofeat.datasets.becos` for the layout)
and reports:

* pair folders per split against the pairs the generator drew (its ``pairings.pkl``), with the
  folders that are missing or half-written (a file absent or unreadable) named;
* correspondence files: lengths and index ranges against the two meshes, share of ``-1``;
* the ``_info.pkl`` records against the files: names, which shape is partial, the square root
  of the full shapes' areas (equal to the mesh's own for a full shape, larger for a partial
  one), and the random rotations (equal to those of the pairings, and undoing them brings the
  two shapes of a pair into the same orientation).

`geofeat data check becos` and `geofeat.apps.prepare.prepare_becos` run it.

>>> from geofeat.apps.becos_check import check_becos
>>> report = check_becos("becos-code/output/partial_full")       # doctest: +SKIP
>>> print("\\n".join(report.lines()))                            # doctest: +SKIP
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geofeat.datasets.base import SPLITS
from geofeat.datasets.becos import (
    SETTINGS,
    BeCoS,
    BecosShapeInfo,
    check_roles,
    info_path,
    pair_folder_missing,
    read_becos_map,
    read_becos_pairings,
    read_shape_info,
)
from geofeat.errors import DatasetError, GeofeatError
from geofeat.mesh import load_mesh
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)

__all__ = ["BecosCheck", "SplitCheck", "check_becos"]

#: Relative difference allowed between a full shape's sqrt(area) and the recorded value.
AREA_TOLERANCE = 1e-3
#: Largest median, over a split, of the rotation (degrees) between the two shapes of a pair
#: once their recorded random rotations are undone. A single pair can leave a large rotation
#: in a best rigid fit (different bodies and poses, a small partial view); rotations that were
#: not recorded leave about 90 degrees on average.
ROTATION_LIMIT_DEG = 60.0
#: Fewest checked pairs of a split before its median rotation is judged.
ROTATION_MIN_PAIRS = 8
#: Vertices compared between copies of one full shape in different pairs.
UNROTATED_VERTICES = 500
#: Largest difference (fraction of sqrt(area)) between copies of one full shape with their rotations undone.
UNROTATED_TOLERANCE = 1e-6
#: Problems listed one by one before "... and N more".
MAX_LISTED = 20


@dataclass
class SplitCheck:
    """What `check_becos` found in one split folder of one setting.

    Attributes
    ----------
    setting, split : str
    folder : Path
    expected : int or None
        Pairs the generator drew for the split (its ``pairings.pkl``); None without that file.
    complete : int
        Pair folders with every file present and readable, and consistent.
    incomplete : dict of str to str
        Folder name -> what is missing or unreadable (half-written pairs).
    missing : list of int
        Pair numbers of ``pairings.pkl`` with no folder at all.
    unexpected : list of str
        Numbered folders beyond the drawn pairs.
    problems : list of str
        Inconsistencies in complete folders: indices out of range, areas or rotations that
        disagree with the records, names that disagree with the pairings.
    unmatched : tuple of (float, float) or None
        Smallest and largest share of shape 1's vertices without a counterpart (``corres_10 == -1``).
    index_max_share : float or None
        Largest ``corres_10`` index over shape 0's vertex count (close to 1 when the whole shape is used).
    partial_area : tuple of (float, float) or None
        Smallest and largest ``sqrt(area(partial mesh)) / recorded sqrt area`` of the partial shapes.
    full_area_error : float or None
        Largest relative difference between a full shape's ``sqrt(area)`` and its record.
    rotation_deg : tuple of (float, float) or None
        Median and largest rotation between the pair's shapes after undoing the recorded rotations.
    copies : int
        Full shapes found again in a later pair and compared with their first copy, rotations undone.
    """

    setting: str
    split: str
    folder: Path
    expected: int | None = None
    complete: int = 0
    incomplete: dict[str, str] = field(default_factory=dict)
    missing: list[int] = field(default_factory=list)
    unexpected: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    unmatched: tuple[float, float] | None = None
    index_max_share: float | None = None
    partial_area: tuple[float, float] | None = None
    full_area_error: float | None = None
    rotation_deg: tuple[float, float] | None = None
    copies: int = 0

    @property
    def ok(self) -> bool:
        """Every drawn pair present, complete and consistent."""
        return not (self.incomplete or self.missing or self.problems)

    def lines(self) -> list[str]:
        """This split's part of the report."""
        expected = "" if self.expected is None else f" of {self.expected:,} drawn"
        out = [f"{self.setting}/{self.split}: {self.complete:,} complete pair folder(s){expected} ({self.folder})"]
        if self.unmatched is not None:
            out.append(
                f"  corres_10: indices in range; no counterpart (-1) for {self.unmatched[0]:.1%} to "
                f"{self.unmatched[1]:.1%} of shape 1's vertices; largest index {self.index_max_share:.1%} of shape 0's vertices"
            )
        if self.full_area_error is not None:
            out.append(f"  areas: full shapes match their recorded sqrt(area) within {self.full_area_error:.1e} (relative)")
        if self.partial_area is not None:
            out.append(
                f"  areas: partial shapes have {self.partial_area[0]:.2f} to {self.partial_area[1]:.2f} of their full "
                "shape's recorded sqrt(area) (BeCoS divides geodesic errors by the full shape's)"
            )
        if self.rotation_deg is not None:
            out.append(
                f"  orientation: with the recorded random rotations undone, the best rigid fit of shape 1 onto shape 0 "
                f"rotates by {self.rotation_deg[0]:.0f} degrees (median), {self.rotation_deg[1]:.0f} at most"
            )
        if self.copies:
            copies = "1 later copy of a full shape" if self.copies == 1 else f"{self.copies:,} later copies of full shapes"
            if any("coincide" in problem for problem in self.problems):
                out.append(f"  orientation: {copies} compared with the first copy, recorded random rotations undone")
            else:
                agree = "coincides" if self.copies == 1 else "coincide"
                out.append(f"  orientation: {copies} {agree} with the first copy once the recorded random rotations are undone")
        if self.setting == "partial_partial" and self.complete:
            out.append("  overlap masks: in every complete pair, each record's overlap_mask equals the other shape's map >= 0")
        if self.missing:
            shown = ", ".join(map(str, self.missing[:MAX_LISTED])) + (" ..." if len(self.missing) > MAX_LISTED else "")
            out.append(f"  missing: {len(self.missing):,} pair folder(s) never written: {shown}")
        if self.incomplete:
            out.append(f"  incomplete: {len(self.incomplete):,} pair folder(s) half-written or damaged:")
            out += [f"    {name}/: {what}" for name, what in list(self.incomplete.items())[:MAX_LISTED]]
            if len(self.incomplete) > MAX_LISTED:
                out.append(f"    ... and {len(self.incomplete) - MAX_LISTED} more")
        if self.unexpected:
            out.append(
                f"  unexpected: {len(self.unexpected):,} folder(s) beyond the drawn pairs: {', '.join(self.unexpected[:10])}"
            )
        for problem in self.problems[:MAX_LISTED]:
            out.append(f"  problem: {problem}")
        if len(self.problems) > MAX_LISTED:
            out.append(f"  ... and {len(self.problems) - MAX_LISTED} more problems")
        return out


@dataclass
class BecosCheck:
    """What `check_becos` found; `lines` is the text ``geofeat data check`` prints for BeCoS.

    Attributes
    ----------
    folder : Path
        The folder checked.
    splits : list of SplitCheck
        One per setting and split found.
    problems : list of str
        What makes the folder unusable as a whole (no setting folder, unreadable pairings).
    notes : list of str
        What is worth knowing but not wrong.
    """

    folder: Path
    splits: list[SplitCheck] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when every split is complete and consistent and nothing else is wrong."""
        return not self.problems and bool(self.splits) and all(split.ok for split in self.splits)

    def pair_counts(self) -> dict[str, dict[str, int]]:
        """Complete pair folders by setting and split."""
        counts: dict[str, dict[str, int]] = {}
        for split in self.splits:
            counts.setdefault(split.setting, {})[split.split] = split.complete
        return counts

    def lines(self) -> list[str]:
        """The report as lines of text (no trailing newlines)."""
        out = [f"BeCoS generator output: {self.folder}"]
        for split in self.splits:
            out += split.lines()
        out += [f"note: {note}" for note in self.notes]
        out += [f"problem: {problem}" for problem in self.problems]
        n_bad = len(self.problems) + sum(len(s.problems) + len(s.incomplete) + (1 if s.missing else 0) for s in self.splits)
        if self.ok:
            out.append("result: complete; every pair folder is whole and agrees with its records")
        else:
            out.append(f"result: {n_bad} problem(s); see above")
        return out


def _setting_folders(folder: Path) -> list[tuple[str, Path]]:
    """``(setting, path)`` of the setting folders at ``folder``: the folder itself or its children."""
    if folder.name in SETTINGS or folder.name.split("_archived_")[0] in SETTINGS:
        return [(folder.name.split("_archived_")[0], folder)]
    return [(name, folder / name) for name in SETTINGS if (folder / name).is_dir()]


def check_becos(
    folder: str | os.PathLike,
    *,
    pairings: str | os.PathLike | None = None,
    splits: Sequence[str] = SPLITS,
    progress: bool = False,
) -> BecosCheck:
    """Check a BeCoS generator output folder: complete pairs, index ranges, areas and orientation.

    Parameters
    ----------
    folder : path-like
        A setting folder (``.../output/partial_full``, holding ``train/``, ``val/``, ``test/``)
        or a folder that holds setting folders (the generator's ``output/``, a ``BeCoS/``).
    pairings : path-like, optional
        The pairs the generator drew; default ``<setting folder>/pairings.pkl`` where it exists
        (``main.py`` writes it there before the first pair). Without it, the pair count is what
        was found and names are not compared.
    splits : sequence of str
        Which splits to check; a split folder that does not exist is reported as such when
        the pairings list pairs for it, and skipped otherwise.
    progress : bool
        Draw a progress bar over the pair folders (on a terminal only).

    Returns
    -------
    BecosCheck
        ``ok`` is True when every drawn pair has a whole folder that agrees with its records.

    Raises
    ------
    DatasetError
        When ``folder`` is not a folder.
    """
    root = Path(folder).expanduser()
    if not root.is_dir():
        raise DatasetError(f"cannot check BeCoS output: {root} is not a folder.")
    report = BecosCheck(folder=root)
    found = _setting_folders(root)
    if not found:
        report.problems.append(
            f"no setting folder: expected {root} to be one of {', '.join(SETTINGS)} (the generator writes "
            f"output/<setting>/) or to hold one."
        )
        return report
    for setting, setting_folder in found:
        drawn = _read_pairings(setting_folder, pairings if len(found) == 1 else None, report)
        for split in splits:
            split_folder = setting_folder / split
            if not split_folder.is_dir():
                if drawn is not None and drawn.get(split):
                    check = SplitCheck(setting=setting, split=split, folder=split_folder, expected=len(drawn[split]))
                    check.missing = list(range(len(drawn[split])))
                    report.splits.append(check)
                continue
            report.splits.append(
                _check_split(setting, split, split_folder, None if drawn is None else drawn.get(split, []), progress)
            )
    if not report.splits:
        report.problems.append(f"no split folder ({', '.join(splits)}) in {', '.join(str(p) for _, p in found)}.")
    return report


def _read_pairings(setting_folder: Path, given: str | os.PathLike | None, report: BecosCheck) -> dict | None:
    path = Path(given) if given is not None else setting_folder / "pairings.pkl"
    if not path.is_file():
        if given is not None:
            report.problems.append(f"pairings file {path} does not exist.")
        else:
            report.notes.append(
                f"{setting_folder.name}: no pairings.pkl (the generator writes it unless original_settings is on); "
                "pair counts are what was found, names are not compared with the drawn pairs."
            )
        return None
    try:
        return read_becos_pairings(path)
    except DatasetError as err:
        report.problems.append(str(err))
        return None


@dataclass
class _PairStats:
    unmatched: float
    index_share: float
    partial_area: list[float]
    full_area_error: list[float]
    rotation_deg: float | None
    unrotated: dict[str, np.ndarray] = field(default_factory=dict)
    n_vertices: dict[str, int] = field(default_factory=dict)


def _check_split(setting: str, split: str, folder: Path, drawn: list | None, progress: bool) -> SplitCheck:
    check = SplitCheck(setting=setting, split=split, folder=folder, expected=None if drawn is None else len(drawn))
    folders = {p.name: p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()}
    names = sorted(folders, key=int)
    if drawn is not None:
        check.missing = [k for k in range(len(drawn)) if str(k) not in folders]
        check.unexpected = [name for name in names if int(name) >= len(drawn)]
    with_info = any(next(p.glob("*_info.pkl"), None) is not None for p in folders.values())
    maps = ["corres_10.npy"] if setting == "partial_full" else ["corres_10.npy", "corres_01.npy"]
    stats: list[_PairStats] = []
    copies: dict[str, tuple[np.ndarray, int, str]] = {}
    for name in progress_bar(names, show=progress, desc=f"checking {setting}/{split}", unit="pair"):
        pair_folder = folders[name]
        missing = pair_folder_missing(pair_folder, maps, with_info or drawn is not None)
        if missing:
            check.incomplete[name] = "lacks " + ", ".join(missing)
            continue
        expected = drawn[int(name)] if drawn is not None and int(name) < len(drawn) else None
        try:
            result = _check_pair(setting, pair_folder, expected, with_info or drawn is not None)
        except (GeofeatError, OSError) as err:
            check.incomplete[name] = "unreadable: " + " ".join(str(err).split())
            continue
        if isinstance(result, list):
            check.problems += [f"{name}/: {problem}" for problem in result]
            continue
        check.complete += 1
        _check_copies(check, name, result, copies)
        stats.append(result)
    if stats:
        unmatched = [s.unmatched for s in stats]
        check.unmatched = (min(unmatched), max(unmatched))
        check.index_max_share = max(s.index_share for s in stats)
        partial = [a for s in stats for a in s.partial_area]
        full = [a for s in stats for a in s.full_area_error]
        check.partial_area = (min(partial), max(partial)) if partial else None
        check.full_area_error = max(full) if full else None
        angles = [s.rotation_deg for s in stats if s.rotation_deg is not None]
        check.rotation_deg = (float(np.median(angles)), max(angles)) if angles else None
        if len(angles) >= ROTATION_MIN_PAIRS and check.rotation_deg[0] > ROTATION_LIMIT_DEG:
            check.problems.append(
                f"orientation: with the recorded random rotations undone, the shapes of a pair still differ by "
                f"{check.rotation_deg[0]:.0f} degrees on the median (more than {ROTATION_LIMIT_DEG:.0f}); the meshes "
                "were rotated after generation, or the records belong to other files."
            )
    if check.ok and check.complete:
        try:
            BeCoS(folder, split=split, setting=setting)  # what a geofeat run opens
        except GeofeatError as err:
            check.problems.append(f"geofeat cannot open the split: {err}")
    return check


def _check_copies(check: SplitCheck, name: str, pair: _PairStats, first: dict[str, tuple[np.ndarray, int, str]]) -> None:
    """A full shape used by several pairs is one mesh: with the recorded rotations undone, its copies coincide."""
    for shape, unrotated in pair.unrotated.items():
        n = pair.n_vertices[shape]
        if shape not in first:
            first[shape] = (unrotated, n, name)
            continue
        reference, n_reference, where = first[shape]
        check.copies += n == n_reference
        if n == n_reference and np.abs(unrotated - reference).max() > UNROTATED_TOLERANCE:
            check.problems.append(
                f"{name}/: orientation: {shape} does not coincide with its copy in {where}/ once their recorded "
                "random_rotation is undone; a mesh was rotated after generation, or its record belongs to another file."
            )
    pair.unrotated.clear()


def _check_pair(setting: str, folder: Path, drawn: tuple[dict, dict] | None, with_info: bool) -> _PairStats | list[str]:
    """Read one whole pair folder; its statistics, or the list of what disagrees."""
    files = [next(folder.glob(f"{side}_*.off")) for side in "01"]
    meshes = [load_mesh(path) for path in files]
    n0, n1 = meshes[0].n_vertices, meshes[1].n_vertices
    map_10 = read_becos_map(folder / "corres_10.npy", n1, n0)
    map_01 = read_becos_map(folder / "corres_01.npy", n0, n1) if setting != "partial_full" else None
    problems: list[str] = []
    if not np.any(map_10 >= 0):
        problems.append("corres_10.npy is -1 everywhere: no vertex of shape 1 has a counterpart.")
    if map_01 is not None and not np.any(map_01 >= 0):
        problems.append("corres_01.npy is -1 everywhere: no vertex of shape 0 has a counterpart.")
    stats = _PairStats(
        unmatched=float(np.mean(map_10 < 0)),
        index_share=float(map_10.max() + 1) / n0,
        partial_area=[],
        full_area_error=[],
        rotation_deg=None,
    )
    if not with_info:
        return problems or stats
    infos = (read_shape_info(info_path(files[0])), read_shape_info(info_path(files[1])))
    try:
        check_roles(setting, infos, (n0, n1), folder)
    except DatasetError as err:
        problems.append(str(err))
        return problems
    problems += _check_records(setting, infos, map_10, map_01)
    for info, mesh in zip(infos, meshes, strict=True):
        ratio = float(np.sqrt(mesh.area())) / info.sqrt_area
        if info.partial:
            stats.partial_area.append(ratio)
            if ratio > 1 + AREA_TOLERANCE:
                problems.append(
                    f"{mesh.name}.off (partial) has sqrt(area) {ratio:.3f} times the recorded full shape's; a partial "
                    "shape cannot be larger. The mesh and its record do not belong together."
                )
        else:
            stats.full_area_error.append(abs(ratio - 1))
            if abs(ratio - 1) > AREA_TOLERANCE:
                problems.append(
                    f"{mesh.name}.off has sqrt(area) {np.sqrt(mesh.area()):.6g}; its record says {info.sqrt_area:.6g} "
                    f"(relative difference {abs(ratio - 1):.1e}). The mesh was rescaled after generation, or the record "
                    "belongs to another mesh."
                )
    for side, info in enumerate(infos):
        rotation = info.rotation
        if not (np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) and np.linalg.det(rotation) > 0):
            problems.append(f"{info.path.name}: random_rotation is not a rotation matrix.")
        if drawn is not None:
            expected = drawn[side]
            if str(expected["name"]).replace("/", "_") != info.file_stem:
                problems.append(
                    f"shape {side} is {info.name!r}; the generator drew {expected['name']!r} for this pair. The folder "
                    "belongs to another run (mixed outputs)."
                )
            elif "random_rot" in expected and not np.allclose(np.asarray(expected["random_rot"], float), rotation):
                problems.append(f"{info.path.name}: random_rotation differs from the one the generator drew for the pair.")
    if not problems:
        stats.rotation_deg = _relative_rotation_deg(meshes, infos, map_10)
        for info, mesh in zip(infos, meshes, strict=True):
            if not info.partial:
                stats.unrotated[info.name] = np.asarray(mesh.verts)[:UNROTATED_VERTICES] @ info.rotation.T / info.sqrt_area
                stats.n_vertices[info.name] = mesh.n_vertices
    return problems or stats


def _check_records(
    setting: str, infos: tuple[BecosShapeInfo, BecosShapeInfo], map_10: np.ndarray, map_01: np.ndarray | None
) -> list[str]:
    """The records' overlap masks against the maps (the generator derives both from one computation)."""
    problems = []
    if setting == "partial_partial" and map_01 is not None:
        # each record holds the other shape's mask
        for side, (info, other_map) in enumerate(((infos[0], map_10), (infos[1], map_01))):
            mask = info.overlap_mask
            if mask is not None and (mask.shape != other_map.shape or np.any(mask != (other_map >= 0))):
                problems.append(
                    f"{info.path.name}: overlap_mask does not equal corres_{1 - side}{side}.npy >= 0 (the generator "
                    "stores there the other shape's vertices that have a counterpart)."
                )
    return problems


def _relative_rotation_deg(meshes, infos, map_10: np.ndarray) -> float | None:
    """Angle of the best rigid rotation of shape 1 onto its counterparts on shape 0, both un-rotated."""
    matched = np.flatnonzero(map_10 >= 0)
    if matched.size < 3:
        return None
    source = np.asarray(meshes[1].verts)[matched] @ infos[1].rotation.T
    target = np.asarray(meshes[0].verts)[map_10[matched]] @ infos[0].rotation.T
    source = source - source.mean(axis=0)
    target = target - target.mean(axis=0)
    u, _, vt = np.linalg.svd(source.T @ target)
    d = np.sign(np.linalg.det(u @ vt))
    rotation = u @ np.diag([1.0, 1.0, d]) @ vt
    cosine = (np.trace(rotation) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
