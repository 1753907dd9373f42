"""``geofeat data check``: what geofeat reads from a copy of a benchmark, before a long run.

`check_dataset` opens a dataset the way every geofeat run does (`load_dataset`), reads every
pair, and reports what it found: the folder it used, the pair and shape counts, the vertex
counts, the range of the ground-truth indices and the share of vertices without a
counterpart, which way the maps go, and anything unexpected: pairs that cannot be read
(indices out of range, files of the wrong length, maps whose shapes are missing), pairs with
no ground truth at all, and the files of the folder that no pair reads.

>>> from geofeat.apps.data import check_dataset
>>> report = check_dataset("faust_r", "../shared/data", split="test")
>>> print("\\n".join(report.lines()))       # what ``geofeat data check`` prints
>>> report.ok                                # False when something is wrong
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from geofeat.datasets.records import ShapePair
from geofeat.datasets.registry import dataset_description, dataset_options, load_dataset
from geofeat.errors import DatasetError, GeofeatError, UnknownSplitError
from geofeat.registry import canonical_name
from geofeat.runtime.progress import progress_bar

#: Meshes kept in memory while checking (loaders that take ``mesh_cache_size``).
MESH_CACHE_SIZE = 64
#: Problems listed one by one before "... and N more".
MAX_LISTED = 20


@dataclass
class _Range:
    """Smallest and largest of the values seen so far, with the item each came from."""

    low: float | None = None
    high: float | None = None
    low_at: str = ""
    high_at: str = ""

    def add(self, value: float, at: str = "") -> None:
        if self.low is None or value < self.low:
            self.low, self.low_at = value, at
        if self.high is None or value > self.high:
            self.high, self.high_at = value, at


@dataclass
class DatasetCheck:
    """What `check_dataset` found; `lines` is the text ``geofeat data check`` prints.

    Attributes
    ----------
    name, split : str
        The dataset name (canonical) and split checked.
    description : str
        The registry's one line about the dataset.
    given : Path or None
        The data folder given (None: ``$GEOFEAT_DATA`` or none needed).
    folder : Path or None
        The folder the loader settled on (None for datasets built in memory, or when it
        could not open the data).
    protocol : str or None
    n_pairs : int
        Pairs the dataset lists; ``n_read`` of them could be read.
    n_read : int
    shapes : dict of str to int
        Vertex count of every distinct shape read, by content hash.
    problems : list of str
        What is wrong (the exit status of ``geofeat data check`` is 1 when there is any).
    notes : list of str
        What is worth knowing but not wrong: files of the folder that no pair reads.
    warnings : list of str
        The warnings geofeat logged while reading (each once), such as the faces a mesh
        dropped; not counted as problems.
    """

    name: str
    split: str
    description: str = ""
    given: Path | None = None
    folder: Path | None = None
    protocol: str | None = None
    n_pairs: int = 0
    n_read: int = 0
    example: str = ""
    shapes: dict[str, int] = field(default_factory=dict)
    y_vertices: _Range = field(default_factory=_Range)
    x_vertices: _Range = field(default_factory=_Range)
    index: _Range = field(default_factory=_Range)
    index_share: _Range = field(default_factory=_Range)
    unmatched_share: _Range = field(default_factory=_Range)
    n_unmatched: int = 0
    n_source_vertices: int = 0
    with_reverse: int = 0
    with_overlap_y: int = 0
    with_overlap_x: int = 0
    with_sym: int = 0
    with_template: int = 0
    n_files_read: int | None = None
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when nothing is wrong: every pair read, its ground truth in range and not empty."""
        return not self.problems

    def lines(self) -> list[str]:
        """The report as lines of text (no trailing newlines)."""
        out = [f"dataset: {self.name} ({self.description}), split {self.split}"]
        if self.folder is not None:
            out.append(f"folder: {self.folder}")
        elif self.given is not None:
            out.append(f"data folder given: {self.given}")
        else:
            out.append("folder: none (built in memory)")
        if self.protocol is not None:
            out.append(f"pairs: {self.n_pairs:,} ({self.protocol.upper()}), {self.n_read:,} read")
        if self.n_read:
            out.append(
                f"shapes: {len(self.shapes):,} distinct, {_span(self.y_vertices)} vertices as y (source), "
                f"{_span(self.x_vertices)} as x (target)"
            )
            out.append(
                f"direction: map_yx gives, for each vertex of y, its vertex of x; pair names read 'y->x', "
                f"for example {self.example}"
            )
            out.append(f"reverse pairs: {self.with_reverse:,} of {self.n_read:,} pairs have their reverse (x->y) in the dataset")
            out.append(
                f"ground truth: vertices of x from {_number(self.index.low)} to {_number(self.index.high)}, each below "
                f"its x's vertex count (closest: {self.index_share.high_at})"
            )
            share = self.n_unmatched / max(self.n_source_vertices, 1)
            out.append(
                f"no counterpart (-1): {share:.1%} of the vertices of y overall, per pair "
                f"{self.unmatched_share.low:.1%} to {self.unmatched_share.high:.1%}"
            )
            out.append(
                f"also given: overlap_y in {self.with_overlap_y:,}, overlap_x in {self.with_overlap_x:,}, "
                f"map_yx_sym in {self.with_sym:,}, template points in {self.with_template:,} of {self.n_read:,} pairs"
            )
        if self.n_files_read is not None:
            out.append(f"files read: {self.n_files_read:,}")
        for note in self.notes:
            out.append(f"note: {note}")
        for warning in self.warnings[:MAX_LISTED]:
            out.append(f"warning: {warning}")
        if len(self.warnings) > MAX_LISTED:
            out.append(f"warning: ... and {len(self.warnings) - MAX_LISTED} more")
        if self.problems:
            out.append(f"problems: {len(self.problems)}")
            for problem in self.problems[:MAX_LISTED]:
                first, *rest = problem.splitlines() or [""]
                out += [f"  - {first}", *(f"    {line}" for line in rest)]
            if len(self.problems) > MAX_LISTED:
                out.append(f"  ... and {len(self.problems) - MAX_LISTED} more")
        out.append("result: " + ("clean" if self.ok else f"{len(self.problems)} problem(s); see above"))
        return out


def _number(value: float | None) -> str:
    return "-" if value is None else f"{int(value):,}"


def _span(values: _Range) -> str:
    if values.low == values.high:
        return _number(values.low)
    return f"{_number(values.low)} to {_number(values.high)}"


def check_dataset(
    name: str, root: str | os.PathLike | None = None, split: str = "test", *, progress: bool = False, **options
) -> DatasetCheck:
    """Open a dataset as geofeat runs do, read every pair, and report what was read.

    Parameters
    ----------
    name : str
        A registered dataset name (`geofeat.datasets.dataset_names`).
    root : path-like or None
        The data folder, as for `load_dataset`; None: ``$GEOFEAT_DATA``.
    split : str
        Which split to check.
    progress : bool
        Draw a progress bar over the pairs (on a terminal only).
    **options
        Loader options, as for `load_dataset`.

    Returns
    -------
    DatasetCheck
        Its ``problems`` say what is wrong: the data could not be opened (the loader's
        message, with the layout it expects), pairs that could not be read, ground truth out
        of range, of the wrong length or empty. Its ``notes`` list the files of the folder
        that no pair reads.

    Raises
    ------
    DatasetError
        ``name`` is not a registered dataset, an option is one its loader does not take, or
        ``root`` is given and is not a folder.
    """
    accepted = dataset_options(name)  # unknown name: DatasetError
    if root is not None and not Path(root).expanduser().is_dir():
        raise DatasetError(f"cannot check {name!r}: the data folder {root} does not exist or is not a folder.")
    unknown = sorted(set(options) - accepted) if accepted is not None else []
    if unknown:
        raise DatasetError(
            f"dataset {canonical_name(name)!r} does not take option(s) {', '.join(unknown)}; "
            f"it takes: {', '.join(sorted(accepted)) or 'none'}."
        )
    if accepted is not None and "mesh_cache_size" in accepted:
        options.setdefault("mesh_cache_size", MESH_CACHE_SIZE)
    report = DatasetCheck(name=canonical_name(name), split=split, description=dataset_description(name))
    report.given = Path(root).expanduser() if root is not None else None
    with _warnings_into(report.warnings):
        _read_everything(report, name, root, split, progress, options)
    return report


def _read_everything(report: DatasetCheck, name: str, root, split: str, progress: bool, options: dict) -> None:
    """Open the dataset and fold every pair into ``report``."""
    try:
        dataset = load_dataset(name, root, split, **options)
    except UnknownSplitError:
        raise  # bad input, not a problem of the data
    except GeofeatError as err:
        report.problems.append(f"geofeat cannot open it: {err}")
        return
    report.protocol = getattr(dataset, "protocol", None)
    folder = getattr(dataset, "root", None)
    report.folder = Path(folder) if folder is not None and Path(folder).is_dir() else None
    report.n_pairs = len(dataset)
    if report.n_pairs == 0:
        report.problems.append(f"no pair in split {split!r}.")
    names = list(getattr(dataset, "pair_names", []))
    listed = set(names)
    for position in progress_bar(range(report.n_pairs), show=progress, desc=f"checking {report.name}", unit="pair"):
        label = names[position] if position < len(names) else f"pair {position}"
        try:
            pair = dataset[position]
        except (GeofeatError, OSError) as err:
            report.problems.append(f"{label}: cannot be read: {err}")
            continue
        _add_pair(report, pair, label)
        y_name, _, x_name = label.partition("->")
        report.with_reverse += f"{x_name}->{y_name}" in listed
    if report.folder is not None and hasattr(dataset, "files_read"):
        read = dataset.files_read()
        report.n_files_read = len(read)
        report.notes += _unread_notes(report.folder, read)


@contextmanager
def _warnings_into(found: list[str]) -> Iterator[None]:
    """Collect the warnings geofeat logs (a mesh's dropped faces, ...) into ``found`` instead of printing them."""

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            message = record.getMessage()
            if message not in seen:
                seen.add(message)
                found.append(message)

    seen: set[str] = set()
    logger = logging.getLogger("geofeat")
    handler = Collect(level=logging.WARNING)
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _add_pair(report: DatasetCheck, pair: ShapePair, label: str) -> None:
    """Fold one pair into the report; its problems are added, the pair counted only if its ground truth is usable."""
    n_y, n_x = pair.y.n_vertices, pair.x.n_vertices
    problems = _pair_problems(pair)
    if problems:
        report.problems += [f"{label}: {problem}" for problem in problems]
        return
    report.n_read += 1
    report.example = report.example or label
    report.shapes[pair.y.hash] = n_y
    report.shapes[pair.x.hash] = n_x
    report.y_vertices.add(n_y, label)
    report.x_vertices.add(n_x, label)
    matched = pair.map_yx[pair.map_yx >= 0]
    report.index.add(int(matched.min()), label)
    report.index.add(int(matched.max()), label)
    report.index_share.add(int(matched.max()) / n_x, f"{int(matched.max()):,} of {n_x:,} in {label}")
    unmatched = int(np.count_nonzero(pair.map_yx < 0))
    report.n_unmatched += unmatched
    report.n_source_vertices += n_y
    report.unmatched_share.add(unmatched / n_y, label)
    report.with_overlap_y += pair.overlap_y is not None
    report.with_overlap_x += pair.overlap_x is not None
    report.with_sym += pair.map_yx_sym is not None
    report.with_template += pair.corr_x is not None


def _pair_problems(pair: ShapePair) -> list[str]:
    """What is wrong with one loaded pair's ground truth (the loaders check most of it already)."""
    n_y, n_x = pair.y.n_vertices, pair.x.n_vertices
    problems = []
    for field_name in ("map_yx", "map_yx_sym"):
        values = getattr(pair, field_name)
        if values is None:
            continue
        values = np.asarray(values)
        if values.shape != (n_y,):
            problems.append(f"{field_name} has shape {values.shape}; expected ({n_y},), one entry per vertex of y.")
        elif values.size and (values.min() < -1 or values.max() >= n_x):
            problems.append(
                f"{field_name} holds indices from {values.min()} to {values.max()}; x has {n_x} vertices (0-based, -1 for none)."
            )
    if not problems and not np.any(np.asarray(pair.map_yx) >= 0):
        problems.append("no vertex of y has a counterpart (map_yx is -1 everywhere).")
    for field_name, n in (("overlap_y", n_y), ("overlap_x", n_x)):
        mask = getattr(pair, field_name)
        if mask is not None and np.shape(mask) != (n,):
            problems.append(f"{field_name} has shape {np.shape(mask)}; expected ({n},).")
    if (pair.corr_x is None) != (pair.corr_y is None):
        problems.append("only one of corr_x and corr_y is given.")
    elif pair.corr_x is not None:
        corr_x, corr_y = np.asarray(pair.corr_x), np.asarray(pair.corr_y)
        if corr_x.shape != corr_y.shape:
            problems.append(f"corr_x and corr_y differ in length ({corr_x.size} and {corr_y.size} template points).")
        elif corr_x.size and (corr_x.max() >= n_x or corr_y.max() >= n_y or min(corr_x.min(), corr_y.min()) < -1):
            problems.append("template points (corr_x, corr_y) index vertices that x or y does not have.")
    return problems


def _unread_notes(folder: Path, read: Iterable[Path]) -> list[str]:
    """One note per folder and suffix of the files under ``folder`` that no pair read (hidden files left out)."""
    read = {Path(path).resolve() for path in read}
    groups: dict[tuple[str, str], list[str]] = {}
    for path in sorted(folder.rglob("*")):
        relative = path.relative_to(folder)
        if any(part.startswith(".") for part in relative.parts) or not path.is_file() or path.resolve() in read:
            continue
        where = relative.parent.as_posix()
        groups.setdefault((where, path.suffix or "(no suffix)"), []).append(path.name)
    notes = []
    for (where, suffix), files in groups.items():
        place = "the folder itself" if where == "." else f"{where}/"
        kind = f"*{suffix}" if suffix.startswith(".") else suffix
        examples = ", ".join(files[:3]) + (", ..." if len(files) > 3 else "")
        notes.append(f"not read: {len(files):,} file(s) in {place} ({kind}): {examples}")
    return notes
