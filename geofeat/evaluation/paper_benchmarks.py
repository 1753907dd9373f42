"""The GeoLoRA paper's benchmarks, evaluated as its official evaluation code evaluates them.

The official release of "Teaching DINOv3 About Partial 3D Geometry" (``vikiehm/geo-lora``)
has one test configuration per benchmark (``config/test/*.yaml``) and evaluation dataset
classes (``utils/shape_dataset.py``), but no evaluation script. A `PaperBenchmark` says, for
each configuration, how those classes and ``validation_partial_full`` (``train.py``) turn the
benchmark's files into pairs and errors, in geofeat's terms:

- the geofeat dataset that reads the same files (`geofeat.datasets.load_dataset`): the same
  pairs with the same ground truth (checked pair by pair against the official classes,
  ``benchmarks/parity/paper.py``);
- ``frame``: the rotation the official class applies to both shapes before their features
  are computed (SHREC'16: 90 degrees about x; PSMAL: 180 degrees about x); geodesic errors
  do not depend on it. `framed` applies it;
- ``points``: ``"vertices"``, every vertex of the partial shape ``y`` with a counterpart, or
  ``"template"``, every template point the partial shape kept (PFAUST), a partial vertex
  counting once per template point on it;
- ``distances``: what the geodesic distances on ``x`` (Dijkstra on the edge graph) are
  divided by: ``"sqrt_area"``, the square root of ``x``'s surface area; ``"recorded"``, the
  length BeCoS records for ``x`` (the square root of the area of the full shape ``x`` was
  cut from); ``"raw"``, nothing (mesh units);
- ``lora``: the release checkpoint (``saved_models/<lora>``) that serves the benchmark.

Errors are pooled over the evaluated points of all pairs (`geofeat.evaluation.summarize`),
as the official code concatenates them before one mean, and reported x100.

geofeat's own protocol, the default of `geofeat.evaluation.evaluate_dataset`, differs only in
``distances`` and ``points``: it divides every error by ``sqrt(area(x))`` (BeCoS: by the
recorded length) and evaluates each partial vertex with a counterpart once (PFAUST too).
`paper_pairs` gives the pairs with the official choices.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError
from geofeat.mesh import Mesh

__all__ = ["DISTANCES", "PAPER_BENCHMARKS", "PaperBenchmark", "PaperPairs", "framed", "paper_pairs"]

#: What geodesic errors on ``x`` are divided by (see the module notes).
DISTANCES = ("sqrt_area", "recorded", "raw")

#: 90 degrees about x, as the official SHREC'16 class turns its shapes (``verts @ ROTATE_X_90``).
ROTATE_X_90 = ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 1.0, 0.0))
#: 180 degrees about x, the official ``SMAL_FLIP`` (SMAL shapes are stored upside down).
FLIP_X_180 = ((1.0, 0.0, 0.0), (0.0, -1.0, 0.0), (0.0, 0.0, -1.0))


@dataclass(frozen=True)
class PaperBenchmark:
    """One benchmark of the GeoLoRA paper, as its official test configuration evaluates it.

    Attributes
    ----------
    name : str
        The official configuration's name (``config/test/<name>.yaml``).
    title : str
        How the paper's tables name it.
    dataset : str
        The geofeat dataset that reads its files (test split).
    points : {"vertices", "template"}
        Evaluated points (`geofeat.evaluation.evaluate_pair`'s ``protocol``).
    distances : {"sqrt_area", "recorded", "raw"}
        What the geodesic errors are divided by.
    lora : str
        The release LoRA checkpoint that serves it (``saved_models/<lora>``).
    frame : tuple of tuple of float, optional
        3 x 3 matrix ``R``: the features are computed on ``verts @ R``; None: as stored.
    data : str
        Where its files come from, for a user who lacks them.
    """

    name: str
    title: str
    dataset: str
    points: str
    distances: str
    lora: str
    frame: tuple[tuple[float, float, float], ...] | None = None
    data: str = field(default="", repr=False)

    def __post_init__(self) -> None:
        if self.points not in ("vertices", "template"):
            raise DatasetError(f"{self.name}: points must be 'vertices' or 'template'; found {self.points!r}.")
        if self.distances not in DISTANCES:
            raise DatasetError(f"{self.name}: distances must be one of {DISTANCES}; found {self.distances!r}.")


_BECOS = (
    "the BeCoS generator, https://github.com/NafieAmrani/becos-code (its source datasets FAUST, SCAPE, SMAL, DT4D, "
    "KIDS, SHREC'20 and TOSCA must be downloaded from their owners; `geofeat data prepare becos` runs it)"
)
_PFAUST = (
    "https://github.com/ABracha/PFAUST (partial shapes and their template correspondences) beside FAUST_r; the "
    "template masks come with the PFAUST data of https://github.com/ABracha/Wormhole (see `geofeat data check pfaust_m`)"
)
_SHREC16 = "the SHREC'16 Partial Matching test set, in the layout of ULRSSM and GeoLoRA (null/off, cuts/off, cuts/corres)"

#: The eight benchmarks of the official release, by configuration name.
PAPER_BENCHMARKS: dict[str, PaperBenchmark] = {
    b.name: b
    for b in (
        PaperBenchmark("becos_p2f", "BeCoS P2F", "becos_p2f", "vertices", "sqrt_area", "becos.pth", data=_BECOS),
        PaperBenchmark("becos_p2p", "BeCoS P2P", "becos_p2p", "vertices", "recorded", "becos.pth", data=_BECOS),
        PaperBenchmark("pfaust_medium", "PFAUST-M P2F", "pfaust_m", "template", "sqrt_area", "faust.pth", data=_PFAUST),
        PaperBenchmark("pfaust_hard", "PFAUST-H P2F", "pfaust_h", "template", "sqrt_area", "faust.pth", data=_PFAUST),
        PaperBenchmark(
            "psmal",
            "PSMAL P2P",
            "psmal",
            "vertices",
            "raw",
            "smal.pth",
            FLIP_X_180,
            data="https://github.com/vikiehm/gc-ppsm (folder PARTIALSMAL/test)",
        ),
        PaperBenchmark(
            "shrec16_cuts",
            "SHREC'16 CUTS P2F",
            "shrec16_cuts",
            "vertices",
            "raw",
            "becos_without_shrec16.pth",
            ROTATE_X_90,
            data=_SHREC16,
        ),
        PaperBenchmark(
            "shrec16_holes",
            "SHREC'16 HOLES P2F",
            "shrec16_holes",
            "vertices",
            "raw",
            "becos_without_shrec16.pth",
            ROTATE_X_90,
            data=_SHREC16,
        ),
        PaperBenchmark(
            "cp2p",
            "CP2P P2P",
            "cp2p24",
            "vertices",
            "raw",
            "becos_without_shrec16.pth",
            data="CP2P24's test subset of 100 pairs (CP2P24_test_subset_100; CP2P24 is published on Hugging Face, "
            "xieyizheng/CP2P24)",
        ),
    )
}


def framed(mesh: Mesh, benchmark: PaperBenchmark) -> Mesh:
    """``mesh`` in the frame the official class computes features in (vertex order, faces and name kept).

    Parameters
    ----------
    mesh : Mesh
        V vertices.
    benchmark : PaperBenchmark

    Returns
    -------
    Mesh
        ``verts @ benchmark.frame``; ``mesh`` itself when the benchmark turns nothing.
    """
    if benchmark.frame is None:
        return mesh
    return Mesh(mesh.verts @ np.asarray(benchmark.frame, dtype=np.float64), mesh.faces, name=mesh.name)


class PaperPairs(Sequence):
    """A dataset's pairs with the error scale of the official evaluation (see `paper_pairs`).

    Parameters
    ----------
    pairs : sequence of ShapePair
        A geofeat dataset (its ``pair_names`` are kept, so `geofeat.evaluation.evaluate_dataset`
        groups the pairs by target without loading them).
    benchmark : PaperBenchmark
    indices : sequence of int, optional
        The pairs of ``pairs`` to keep, in this order; default all.
    """

    def __init__(self, pairs: Sequence[ShapePair], benchmark: PaperBenchmark, indices: Sequence[int] | None = None):
        self.pairs = pairs
        self.benchmark = benchmark
        self.indices = list(range(len(pairs))) if indices is None else list(indices)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return official_scale(self.pairs[self.indices[index]], self.benchmark)

    @property
    def pair_names(self) -> list[str]:
        """``"<y>-><x>"`` of every pair, from the dataset."""
        names = list(self.pairs.pair_names)
        return [names[i] for i in self.indices]


def official_scale(pair: ShapePair, benchmark: PaperBenchmark) -> ShapePair:
    """``pair`` with the ``error_scale`` that gives the official evaluation's distances (`PaperBenchmark.distances`).

    Raises
    ------
    DatasetError
        ``"recorded"`` on a pair whose dataset records no length.
    """
    if benchmark.distances == "sqrt_area":
        return replace(pair, error_scale=None)
    if benchmark.distances == "raw":
        return replace(pair, error_scale=1.0)
    if pair.error_scale is None:
        raise DatasetError(
            f"{benchmark.title}: pair {pair.name} has no recorded length for x (BeCoS's _info.pkl files), which the "
            "official evaluation divides the geodesic errors by."
        )
    return pair


def paper_pairs(
    benchmark: str | PaperBenchmark,
    root: str | os.PathLike | None = None,
    *,
    split: str = "test",
    cuts_list: str | os.PathLike | None = None,
) -> PaperPairs:
    """The pairs of a benchmark of the paper, with the official evaluation's error scale.

    Parameters
    ----------
    benchmark : str or PaperBenchmark
        A key of `PAPER_BENCHMARKS` (``"becos_p2f"``, ...).
    root : path-like, optional
        The benchmark's data folder (see `geofeat.datasets.load_dataset`).
    split : str
        ``"test"``, the paper's; another split of the dataset for checks.
    cuts_list : path-like, optional
        SHREC'16 CUTS only: a file of partial shape file names, one per line (the official
        code's ``assets/shrec16_cuts_list.txt``, which its release does not contain): only
        those partial shapes are evaluated. Default: every CUTS shape.

    Returns
    -------
    PaperPairs
        Evaluate them with ``protocol=benchmark.points``.

    Raises
    ------
    DatasetError
        An unknown benchmark, a list given for another benchmark or naming no shape of the
        data, or the dataset's own errors (missing files, with where to get them).
    """
    from geofeat.datasets import load_dataset

    benchmark = paper_benchmark(benchmark)
    pairs = load_dataset(benchmark.dataset, root=root, split=split)
    if cuts_list is None:
        return PaperPairs(pairs, benchmark)
    if benchmark.name != "shrec16_cuts":
        raise DatasetError(f"a list of CUTS shapes applies to SHREC'16 CUTS only, not to {benchmark.title}.")
    listed = {line.strip() for line in open(cuts_list, encoding="utf-8") if line.strip()}
    names = list(pairs.pair_names)
    keep = [i for i, name in enumerate(names) if f"{name.split('->', 1)[0]}.off" in listed]
    if not keep:
        raise DatasetError(f"{cuts_list} names none of the {len(names)} CUTS shapes of {root} (one .off file name a line).")
    return PaperPairs(pairs, benchmark, keep)


def paper_benchmark(name: str | PaperBenchmark) -> PaperBenchmark:
    """The `PaperBenchmark` of a name (a `PaperBenchmark` is returned as it is).

    Raises
    ------
    DatasetError
        An unknown name; the message lists the known ones.
    """
    if isinstance(name, PaperBenchmark):
        return name
    if name not in PAPER_BENCHMARKS:
        raise DatasetError(f"unknown benchmark of the GeoLoRA paper {name!r}; known: {', '.join(PAPER_BENCHMARKS)}.")
    return PAPER_BENCHMARKS[name]
