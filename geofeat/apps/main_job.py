"""The main job of ``benchmarks/run.py``: training-free pipelines against two reference rows, on the built-in humans.

Six pipelines (nearest neighbour and functional maps on WKS, HKS and SHOT) and the reference rows
``random`` (chance) and ``mirrored_truth`` (the true map flipped left-right), on full-to-full
and CUTS partial-to-full pairs of the built-in synthetic humans; offline, in seconds. The
reference pipelines and the ``match(index, pair)`` functions are shared with the single runs
of `geofeat.apps.benchmark`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

import numpy as np

from geofeat.adapters.base import Head
from geofeat.adapters.heads import make_head
from geofeat.apps.machine import machine
from geofeat.datasets.records import Match, ShapePair
from geofeat.descriptors.base import Descriptor
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import DatasetError
from geofeat.evaluation.metrics import pck_curve
from geofeat.evaluation.protocol import default_workers, evaluate_dataset, map_forked, summarize
from geofeat.evaluation.report import PairPicture, markdown_table, plot_matches, plot_pck
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.mesh import Mesh
from geofeat.storage.files import atomic_write

REFERENCE_PIPELINES = ("random", "mirrored_truth")


def _say(line: str = "") -> None:
    sys.stdout.write(line + "\n")


def reference_match(pipeline: str, pair, seed: int = 0) -> Match:
    """The reference pipelines that ignore features.

    ``random``: a uniformly random vertex of X (seeded); ``mirrored_truth``: the left-right
    mirrored ground truth, the cost of a perfect but flipped map (needs a dataset with
    chirality ground truth).
    """
    all_y = np.ones(pair.y.n_vertices, dtype=bool)
    if pipeline == "random":
        return Match(np.random.default_rng(seed).integers(0, pair.x.n_vertices, pair.y.n_vertices), all_y)
    if pair.map_yx_sym is None:
        raise DatasetError("pipeline 'mirrored_truth' needs a dataset with a mirrored ground truth")
    return Match(np.where(pair.map_yx_sym >= 0, pair.map_yx_sym, -1), all_y)


class HeadMatch:
    """``match(index, pair)`` of `geofeat.evaluation.evaluate_dataset` for a head."""

    def __init__(self, head: Head):
        self.head = head

    def __call__(self, index: int, pair) -> Match:
        return self.head.match(pair)


class ReferenceMatch:
    """``match(index, pair)`` of a reference pipeline, seeded by the pair index."""

    def __init__(self, pipeline: str, seed: int):
        self.pipeline, self.seed = pipeline, seed

    def __call__(self, index: int, pair) -> Match:
        return reference_match(self.pipeline, pair, seed=self.seed * 100003 + index)


#: The main job's training-free pipelines: (head, descriptor).
MAIN_PIPELINES = (("nn", "wks"), ("nn", "hks"), ("fmap", "wks"), ("fmap", "hks"), ("nn", "shot"), ("fmap", "shot"))
#: SHOT's support radius on the main job's humans, in their units: 0.367 sqrt(area) of a whole
#: human (sqrt(area) 1.35 to 1.38), what DeepShapeMatchingKit's 0.3 is on FAUST_r (tr_reg_080:
#: area 0.669, 0.3 = 0.367 sqrt(area)). Absolute, so that a CUTS partial keeps its whole shape's
#: radius (a share of its own, smaller area would shrink it).
MAIN_SHOT_RADIUS = 0.5
#: Parameters of the main job's descriptors other than their defaults.
MAIN_DESCRIPTOR_PARAMS = {"shot": {"radius": MAIN_SHOT_RADIUS}}
#: Pipelines whose maps pairs.png shows.
MAIN_PICTURED = (("nn", "wks"), ("fmap", "hks"))
#: Eigenpairs of the functional-map bases (the map is 30 x 30; the descriptors keep their 128).
MAIN_FMAP_EIG = 30
#: Marching-cubes spacing of the main job's humans: about 2,000 vertices instead of the
#: 5,300 of the registered synthetic benchmarks, so that a cold run takes seconds and a
#: target's geodesic matrix 17 MB instead of 113 MB.
MAIN_SPACING = 0.035
#: Source poses of the main job's pairs: for each target (pose 0 of a test individual), these
#: poses of the same individual and of the other one, whole (full-to-full) and cut (CUTS).
MAIN_SOURCE_POSES = (1, 2, 3)
#: Pair kinds: key -> how tables and plots name them.
MAIN_KINDS = {"full": "full-to-full", "cuts": "CUTS partial-to-full"}
MAIN_DESCRIPTION = (
    "built-in synthetic humans (the 2 individuals of the test split, meshed with about 2,000 vertices): "
    "to the near-rest pose of each individual, 3 other poses of the same individual and 3 of the other one, "
    "whole and as a CUTS partial shape; SHOT (DeepShapeMatchingKit's parameters) with radius 0.5, "
    "0.367 sqrt(area) of a whole human, as DeepShapeMatchingKit's 0.3 on FAUST_r"
)
READING_GUIDE = (
    "Lower geodesic error (mean distance from the true counterpart, in hundredths of sqrt(area) of the target) "
    "and higher PCK AUC and chirality accuracy are better; `random` is chance level and `mirrored_truth` is the "
    "true map flipped left-right, what confusing the body's two sides costs."
)
MAIN_COLUMNS = [
    ("pairs_kind", "pairs", "s"),
    ("label", "pipeline", "s"),
    ("n_pairs", "n", "d"),
    ("geodesic_error", "geodesic error x100", ".1f"),
    ("pck_auc", "PCK AUC", ".3f"),
    ("chirality_accuracy", "chirality acc.", ".2f"),
]
#: x range of the main job's PCK plot (fractions of sqrt(area)): where the curves rise.
MAIN_PCK_MAX = 1.0


def pipeline_label(pipeline: str, descriptor: str | None) -> str:
    """``"nn + WKS"``; a reference pipeline is its own name."""
    return pipeline if descriptor in (None, "none") else f"{pipeline} + {descriptor.upper()}"


class _FullPairs:
    """Full-to-full pairs of a `SyntheticHumans` family: identity ground truth, mirror map for chirality."""

    def __init__(self, humans, pairs: list[tuple[int, int]]):
        self.humans, self.pairs = humans, pairs
        self._meshes: dict[int, Mesh] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def pair_names(self) -> list[str]:
        names = self.humans.names
        return [f"{names[a]}->{names[b]}" for a, b in self.pairs]

    def _mesh(self, index: int) -> Mesh:
        if index not in self._meshes:
            self._meshes[index] = self.humans.shape(index)
        return self._meshes[index]

    def __getitem__(self, i: int) -> ShapePair:
        a, b = self.pairs[i]
        mirror = self.humans.mirror
        identity = np.arange(mirror.size, dtype=np.int64)
        return ShapePair(x=self._mesh(b), y=self._mesh(a), map_yx=identity, map_yx_sym=mirror, protocol="f2f")


def pictured_pair(n_pairs: int) -> int:
    """The index of the pair pairs.png shows: the first with a source of the other individual (where there is one)."""
    return min(len(MAIN_SOURCE_POSES), n_pairs - 1)


def main_pairs(seed: int, limit: int | None) -> dict[str, list[ShapePair]]:
    """The main job's pairs: ``{"full": [...], "cuts": [...]}``, grouped by target, at most ``limit`` of each kind."""
    from geofeat.datasets.derived import (
        SYNTHETIC_INDIVIDUALS,
        SYNTHETIC_POSES,
        SYNTHETIC_TEST_INDIVIDUALS,
        DerivedPartialBenchmark,
        SyntheticCollection,
    )
    from geofeat.datasets.synthetic import SyntheticHumans

    humans = SyntheticHumans(SYNTHETIC_INDIVIDUALS, SYNTHETIC_POSES, seed=0, spacing=MAIN_SPACING)
    first_test = (SYNTHETIC_INDIVIDUALS - SYNTHETIC_TEST_INDIVIDUALS) * SYNTHETIC_POSES
    test = list(range(first_test, len(humans)))
    targets = test[::SYNTHETIC_POSES]  # pose 0 of each test individual: its near-rest pose
    combinations = [
        (first + pose, target)
        for target in targets
        for first in sorted(targets, key=lambda first: first != target)  # the same individual, then the other
        for pose in MAIN_SOURCE_POSES
    ]
    if limit is not None:
        combinations = combinations[:limit]
    full = _FullPairs(humans, combinations)
    cuts = DerivedPartialBenchmark(SyntheticCollection(humans), test, "cuts", "p2f", seed, "synthetic_cuts")
    index = {pair: i for i, pair in enumerate(cuts.pairs)}  # the pairs of the registered order, whose seeds they keep
    return {"full": [full[i] for i in range(len(full))], "cuts": [cuts[index[pair]] for pair in combinations]}


_PREPARE: tuple[list[Mesh], list[Descriptor], GeodesicStore | None] | None = None


def _prepare_one(task: tuple[int, bool]) -> None:
    """In a worker: the descriptors of one mesh (one spectral basis for all) and, for a target, its geodesic matrix."""
    from geofeat.descriptors.compute import compute

    meshes, descriptors, store = _PREPARE
    index, target = task
    for descriptor in descriptors:
        compute(meshes[index], descriptor)
    if target and store is not None:
        store.load(meshes[index])


def prepare_inputs(
    pairs: list[ShapePair], descriptors: tuple[str, ...], store: GeodesicStore | None, workers: int
) -> tuple[int, int]:
    """Fill the feature cache and the geodesic store for these pairs, in ``workers`` forked processes.

    What is cached already is skipped (a warm run starts no process). The descriptors of a
    mesh are computed in one process, so that they share its spectral basis; a descriptor
    takes its parameters from `MAIN_DESCRIPTOR_PARAMS`, as the heads do. Returns the
    number of meshes that had work and the number of meshes.
    """
    global _PREPARE
    from geofeat.descriptors.cache import FeatureCache
    from geofeat.descriptors.compute import entry_key

    features = FeatureCache()
    made = [make_descriptor(name, **MAIN_DESCRIPTOR_PARAMS.get(name, {})) for name in descriptors]
    meshes: dict[str, tuple[Mesh, bool]] = {}
    for pair in pairs:
        meshes[pair.x.hash] = (pair.x, True)
        meshes.setdefault(pair.y.hash, (pair.y, False))
    todo, mesh_list = [], []
    for mesh, target in meshes.values():
        missing = any(not features.path(entry_key(d, mesh)).is_file() for d in made)
        needs_geodesics = target and store is not None and store.path(mesh) is None
        if missing or needs_geodesics:
            todo.append((len(mesh_list), target))
            mesh_list.append(mesh)
    if not todo:
        return 0, len(meshes)
    todo.sort(key=lambda task: (-task[1], -mesh_list[task[0]].n_vertices))  # the longest first
    _PREPARE = (mesh_list, made, store)
    try:
        for _ in map_forked(_prepare_one, todo, workers):
            pass
    finally:
        _PREPARE = None
    return len(todo), len(meshes)


def _import_plotting(kept: dict) -> None:
    """``on_kept`` of `evaluate_dataset`: import what the plots need (about a second) while the workers evaluate."""
    import matplotlib.figure  # noqa: F401
    import mpl_toolkits.mplot3d  # noqa: F401


def _megabytes(n: int) -> str:
    return f"{n / 1e6:,.1f} MB"


def main_job(args: argparse.Namespace, out: Path) -> int:
    """The default run: training-free pipelines against the references on full and CUTS pairs.

    Parameters
    ----------
    args : argparse.Namespace
        The options of `geofeat.apps.benchmark.parse_args`; the main job reads ``limit``,
        ``seed``, ``workers``, ``no_geodesic_store`` and ``no_progress``.
    out : Path
        The results folder, created if missing: ``results.json``, ``results.md``, ``pck.png``
        and ``pairs.png``.

    Returns
    -------
    int
        The exit status, 0.
    """
    from geofeat.descriptors.cache import FeatureCache

    start = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    kinds = main_pairs(args.seed, args.limit)
    heads = {
        (name, descriptor): make_head(
            name,
            descriptor=descriptor,
            descriptor_params=MAIN_DESCRIPTOR_PARAMS.get(descriptor, {}),
            progress=progress,
            **({"n_eig": MAIN_FMAP_EIG} if name == "fmap" else {}),
        )
        for name, descriptor in MAIN_PIPELINES
    }
    workers = args.workers or default_workers()
    store = None if args.no_geodesic_store else GeodesicStore()
    descriptors = tuple(dict.fromkeys(descriptor for _, descriptor in MAIN_PIPELINES))
    computed, n_meshes = prepare_inputs([pair for pairs in kinds.values() for pair in pairs], descriptors, store, workers)
    caches = "empty" if computed == n_meshes else "filled" if computed == 0 else "partly filled"

    matchers = {pipeline_label(*key): HeadMatch(head) for key, head in heads.items()}
    matchers |= {name: ReferenceMatch(name, args.seed) for name in REFERENCE_PIPELINES}
    pictured = [pipeline_label(*key) for key in MAIN_PICTURED]
    rows, pictures = [], []
    plot_thresholds = np.linspace(0.0, MAIN_PCK_MAX, 201)
    for kind, pairs in kinds.items():
        shown = pictured_pair(len(pairs))
        # every matcher on a pair in a row: they share the process's input features and spectral bases
        records, kept = evaluate_dataset(
            pairs, matchers, store=store, workers=workers, keep=[shown], on_kept=_import_plotting, progress=False
        )
        pair, matches = kept[shown]
        pictures.append(
            PairPicture(
                pair,
                [(label, matches[label].map_yx, records[label][shown].geodesic_error) for label in pictured],
                y_title=(
                    f"source Y: {pair.y.name}\nCUTS partial of {pair.y.name.rsplit('_cuts', 1)[0]}, {pair.y.n_vertices:,} vertices"
                    if kind == "cuts"
                    else None
                ),
                row_title=MAIN_KINDS[kind],
            )
        )
        for label, kind_records in records.items():
            summary = summarize(kind_records)
            pipeline, _, descriptor = label.partition(" + ")
            _, fractions = pck_curve(np.concatenate([r.errors for r in kind_records]), plot_thresholds)
            rows.append(
                {
                    "pairs_kind": MAIN_KINDS[kind],
                    "kind": kind,
                    "label": label,
                    "pipeline": pipeline,
                    "descriptor": descriptor.lower() or "none",
                    **summary.to_dict(),
                    "pck_plot": [round(value, 5) for value in fractions.tolist()],
                    "pairs": [record.to_dict() for record in kind_records],
                }
            )
    colors = {label: f"C{i}" for i, label in enumerate(pipeline_label(*key) for key in MAIN_PIPELINES)}
    colors |= {"random": "0.55", "mirrored_truth": "black"}
    curves, styles = {}, {}
    for row in rows:
        name = f"{row['label']}, {'CUTS' if row['kind'] == 'cuts' else 'full'}"
        curves[name] = (plot_thresholds, np.asarray(row["pck_plot"]))
        styles[name] = {"color": colors[row["label"]], "linestyle": "--" if row["kind"] == "cuts" else "-", "linewidth": 1.4}
    title = f"PCK, built-in synthetic humans: {len(kinds['full'])} full-to-full (solid), {len(kinds['cuts'])} CUTS partial-to-full (dashed)"
    plot_pck(
        curves,
        out / "pck.png",
        title,
        styles=styles,
        xmax=MAIN_PCK_MAX,
        legend_columns=2,
        legend_below=True,
        figsize=(6.5, 6),
        dpi=80,
    )
    plot_matches(pictures, out / "pairs.png")

    seconds = time.perf_counter() - start  # the run less Python's start and the imports (about a second)
    when = f"{datetime.date.today().isoformat()}, {machine()}"
    n_pairs = {kind: len(pairs) for kind, pairs in kinds.items()}
    table = markdown_table(rows, MAIN_COLUMNS)
    note = (
        f"{n_pairs['full']} full-to-full and {n_pairs['cuts']} CUTS partial-to-full pairs of the {MAIN_DESCRIPTION}. "
        f"PCK AUC: the area under the PCK curve for thresholds 0 to 0.25, normalised to 1. Run `python benchmarks/run.py` ({seconds:.0f} s with {caches} caches); {when}."
    )
    markdown = f"{READING_GUIDE}\n\n{table}\n\n{note}\n"
    result = {
        "job": "main",
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "seconds": seconds,
        "caches": caches,
        "seed": args.seed,
        "pairs_description": MAIN_DESCRIPTION,
        "spacing": MAIN_SPACING,
        "fmap_n_eig": MAIN_FMAP_EIG,
        "descriptor_params": MAIN_DESCRIPTOR_PARAMS,
        "n_pairs": n_pairs,
        "pck_plot_thresholds": [round(value, 5) for value in plot_thresholds.tolist()],
        "rows": rows,
    }
    atomic_write(out / "results.json", lambda tmp: tmp.write_text(json.dumps(result, indent=1) + "\n"))  # never half-written
    (out / "results.md").write_text(markdown)

    _say(READING_GUIDE)
    _say()
    _say(table)
    _say()
    _say(f"{sum(n_pairs.values())} pairs in {seconds:.1f} s ({caches} caches).")
    _say(f"Results: {out}/ (results.md, results.json, pck.png, pairs.png)")
    features = FeatureCache()
    _say("Caches, read back by the next run (`geofeat cache info`, `geofeat cache clear`):")
    _say(f"  features   {features.root}  {_megabytes(features.info().bytes)}")
    if store is not None:
        _say(f"  geodesics  {store.folder}  {_megabytes(store.info().bytes)}")
    return 0
