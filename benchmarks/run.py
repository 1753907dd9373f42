"""Run matching pipelines on a benchmark and report geodesic error, PCK, mIoU and chirality.

With no arguments it runs the main job, offline, in about 10 seconds: four training-free
pipelines (nearest neighbour and functional maps on WKS and HKS) and the two reference rows
(``random``: chance; ``mirrored_truth``: the true map flipped left-right) on full-to-full
and on CUTS partial-to-full pairs of the built-in synthetic humans::

    python benchmarks/run.py                          # writes runs/main/
    python benchmarks/run.py --out benchmarks/results/main

One pipeline on one benchmark (any of the options below but --out, --limit, --seed,
--workers, --no-progress and --no-geodesic-store makes a run of this kind; the defaults are
``--pipeline nn --dataset synthetic_cuts --descriptor wks``)::

    python benchmarks/run.py --pipeline fmap --dataset faust_r_cuts --descriptor wks --data-root ../shared/data
    python benchmarks/run.py --pipeline ulrssm --dataset faust_r_cuts --descriptor wks --max-minutes 30
    python benchmarks/run.py --pipeline dpfm --quick          # a smoke run of a learned head, < 2 min on a CPU

Learned heads (ulrssm, dpfm, echomatch) are trained first on ``--train-split`` of the same
dataset (or loaded with ``--load``) and saved into ``<out>/head``. Every run writes into
``--out`` (default ``runs/main`` for the main job, ``runs/<pipeline>_<dataset>_<descriptor>``
otherwise; ``runs/`` is ignored by git): ``results.json``, ``results.md``, ``pck.png`` and
``pairs.png``.

Pairs are evaluated target shape by target shape (`geofeat.evaluation.evaluate_dataset`), in
``--workers`` forked processes for the training-free pipelines, with the same numbers for
any number of workers. The targets' geodesic matrices are kept on disk in
``<geofeat cache>/geodesics`` (``$GEOFEAT_CACHE_DIR``, default ``~/.cache/geofeat``) and the
descriptors in ``<geofeat cache>/features``, so a second run reads them back; the run ends
by saying where both are and how large they are (``geofeat cache info``, ``geofeat cache clear``).

Exit status 0: done; 1: a pair could not be read or matched once the run had started (one
line says which and why); 2: bad input (unknown dataset, descriptor or option); 130:
interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

import geofeat
from geofeat.adapters.base import Head
from geofeat.adapters.heads import load_head, make_head
from geofeat.datasets.records import Match
from geofeat.checks import parse_key_values
from geofeat.datasets import dataset_names, load_dataset
from geofeat.datasets.records import ShapePair
from geofeat.descriptors.registry import make_descriptor
from geofeat.evaluation.metrics import pck_curve
from geofeat.evaluation.protocol import SUMMARY_COLUMNS, default_workers, evaluate_dataset, map_forked, summarize
from geofeat.evaluation.report import PairPicture, markdown_table, plot_matches, plot_pairs, plot_pck
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.storage.files import atomic_write

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
#: Where runs write without --out (ignored by git).
RUNS = REPO / "runs"
log = logging.getLogger("benchmarks.run")

REFERENCE_PIPELINES = ("random", "mirrored_truth")
LEARNED_PIPELINES = ("ulrssm", "dpfm", "echomatch")
TRAINING_RECORD = "training.json"  # how a head saved by this script was trained
PIPELINES = ("nn", "fmap", "fmap_zoomout", *LEARNED_PIPELINES, *REFERENCE_PIPELINES)
N_PICTURES = 3
#: --quick: settings small enough to train and evaluate end to end in well under 2 minutes on a CPU.
QUICK = {
    "ulrssm": {"n_eig": 30, "n_fmap": 20, "diffusion_eig": 30, "width": 16, "width_out": 16, "n_blocks": 2, "tta_steps": 1},
    "dpfm": {"n_eig": 30, "n_fmap": 20, "width": 16, "n_blocks": 2, "attention_dim": 16, "max_samples": 100},
    "echomatch": {"n_eig": 30, "n_fmap": 20, "width": 16, "n_blocks": 2},
}
QUICK_TRAIN_PAIRS = 3
QUICK_TEST_PAIRS = 2


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
        raise geofeat.DatasetError("pipeline 'mirrored_truth' needs a dataset with a mirrored ground truth")
    return Match(np.where(pair.map_yx_sym >= 0, pair.map_yx_sym, -1), all_y)


def build_head(args, params: dict) -> Head:
    """The head of ``--pipeline`` with the input descriptor, ``--head-param`` settings and ``--quick`` sizes."""
    settings = {"descriptor": args.descriptor, "descriptor_params": params, "progress": not args.no_progress}
    if args.pipeline in ("nn", "fmap", "fmap_zoomout"):
        zoomout = {"zoomout": True} if args.pipeline == "fmap_zoomout" else {}
        return make_head("fmap" if zoomout else args.pipeline, **settings, **zoomout)
    if args.checkpoint:
        return load_head(
            args.pipeline, checkpoint=args.checkpoint, progress=not args.no_progress,
            **descriptor_params(args.head_param, what="--head-param"),
        )  # fmt: skip
    settings |= {"seed": args.seed, "epochs": args.epochs, "max_minutes": args.max_minutes}
    if args.quick:
        settings |= QUICK[args.pipeline] | {"max_minutes": min(args.max_minutes or 0.5, 0.5)}
    settings |= descriptor_params(args.head_param, what="--head-param")
    return make_head(args.pipeline, **settings)


def train_head(head: Head, args, out: Path) -> dict:
    """Train a learned head on ``--train-split`` (or load ``--load``); returns a summary for the report.

    The summary is also saved as ``training.json`` in the head folder, so that a report on a
    loaded head still says how it was trained.
    """
    if args.checkpoint:
        return {"release_checkpoint": str(args.checkpoint)}
    if args.load:
        record = Path(args.load) / TRAINING_RECORD
        return {"loaded_from": args.load, **(json.loads(record.read_text()) if record.is_file() else {})}
    train = load_dataset(args.dataset, root=args.data_root, split=args.train_split, seed=args.seed)
    n_train = len(train) if args.train_limit is None else min(args.train_limit, len(train))
    if args.quick:
        n_train = min(n_train, QUICK_TRAIN_PAIRS)
    start = time.perf_counter()
    losses = head.fit(_Pairs(train, n_train))
    record = {
        "train_split": args.train_split,
        "train_pairs": n_train,
        "train_steps": len(losses),
        "train_seconds": time.perf_counter() - start,
        "final_loss": losses[-1] if losses else None,
        "train_losses": [round(v, 5) for v in losses],
    }
    head.save(out / "head")
    atomic_write(out / "head" / TRAINING_RECORD, lambda tmp: tmp.write_text(json.dumps(record)))
    return record


class _HeadMatch:
    """``match(index, pair)`` of `geofeat.evaluation.evaluate_dataset` for a head."""

    def __init__(self, head: Head):
        self.head = head

    def __call__(self, index: int, pair) -> Match:
        return self.head.match(pair)


class _ReferenceMatch:
    """``match(index, pair)`` of a reference pipeline, seeded by the pair index."""

    def __init__(self, pipeline: str, seed: int):
        self.pipeline, self.seed = pipeline, seed

    def __call__(self, index: int, pair) -> Match:
        return reference_match(self.pipeline, pair, seed=self.seed * 100003 + index)


class _Pairs:
    """The first ``n`` pairs of a dataset as a sequence, loaded on access."""

    def __init__(self, dataset, n: int):
        self.dataset, self.n = dataset, n

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, i: int):
        if not 0 <= i < self.n:
            raise IndexError(i)
        return self.dataset[i]


def _positive_count(unit: str, hint: str = ""):
    """argparse type: a whole number >= 1 of ``unit`` (``hint`` follows the message for a number below 1)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a positive whole number of {unit}, found {text!r}") from None
        if value < 1:
            raise argparse.ArgumentTypeError(f"expected a positive number of {unit} (at least 1), found {value}{hint}")
        return value

    return parse


# ----------------------------------------------------------------------------- the main job

#: The main job's training-free pipelines: (head, descriptor).
MAIN_PIPELINES = (("nn", "wks"), ("nn", "hks"), ("fmap", "wks"), ("fmap", "hks"))
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
    "whole and as a CUTS partial shape"
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
        self._meshes: dict[int, geofeat.Mesh] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    @property
    def pair_names(self) -> list[str]:
        names = self.humans.names
        return [f"{names[a]}->{names[b]}" for a, b in self.pairs]

    def _mesh(self, index: int) -> geofeat.Mesh:
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


_PREPARE: tuple[list[geofeat.Mesh], list[geofeat.Descriptor], GeodesicStore | None] | None = None


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
    mesh are computed in one process, so that they share its spectral basis. Returns the
    number of meshes that had work and the number of meshes.
    """
    global _PREPARE
    from geofeat.descriptors.cache import FeatureCache
    from geofeat.descriptors.compute import entry_key

    features = FeatureCache()
    made = [make_descriptor(name) for name in descriptors]
    meshes: dict[str, tuple[geofeat.Mesh, bool]] = {}
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


def main_job(args) -> int:
    """The default run: training-free pipelines against the references on full and CUTS pairs (see the module notes)."""
    from common import machine

    from geofeat.descriptors.cache import FeatureCache

    start = time.perf_counter()
    out = output_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    progress = not args.no_progress
    kinds = main_pairs(args.seed, args.limit)
    heads = {
        (name, descriptor): make_head(
            name, descriptor=descriptor, progress=progress, **({"n_eig": MAIN_FMAP_EIG} if name == "fmap" else {})
        )
        for name, descriptor in MAIN_PIPELINES
    }
    workers = args.workers or default_workers()
    store = None if args.no_geodesic_store else GeodesicStore()
    descriptors = tuple(dict.fromkeys(descriptor for _, descriptor in MAIN_PIPELINES))
    computed, n_meshes = prepare_inputs([pair for pairs in kinds.values() for pair in pairs], descriptors, store, workers)
    caches = "empty" if computed == n_meshes else "filled" if computed == 0 else "partly filled"

    matchers = {pipeline_label(*key): _HeadMatch(head) for key, head in heads.items()}
    matchers |= {name: _ReferenceMatch(name, args.seed) for name in REFERENCE_PIPELINES}
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
        "n_pairs": n_pairs,
        "pck_plot_thresholds": [round(value, 5) for value in plot_thresholds.tolist()],
        "rows": rows,
    }
    atomic_write(out / "results.json", lambda tmp: tmp.write_text(json.dumps(result, indent=1) + "\n"))  # never half-written
    (out / "results.md").write_text(markdown)

    print(READING_GUIDE)
    print()
    print(table)
    print()
    print(f"{sum(n_pairs.values())} pairs in {seconds:.1f} s ({caches} caches).")
    print(f"Results: {out}/ (results.md, results.json, pck.png, pairs.png)")
    features = FeatureCache()
    print("Caches, read back by the next run (`geofeat cache info`, `geofeat cache clear`):")
    print(f"  features   {features.root}  {_megabytes(features.info().bytes)}")
    if store is not None:
        print(f"  geodesics  {store.folder}  {_megabytes(store.info().bytes)}")
    return 0


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pipeline", default=None, choices=PIPELINES, help="one pipeline (default nn); none: the main job")
    parser.add_argument(
        "--dataset", default=None, help=f"one of: {', '.join(dataset_names())} (default synthetic_cuts; none: the main job)"
    )
    parser.add_argument(
        "--descriptor", default=None, help="any registered descriptor (geofeat descriptors; default wks; none: the main job)"
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="descriptor parameter, repeatable (VALUE read as JSON when it parses, else as a string): --param n_descr=64",
    )
    parser.add_argument("--head-param", action="append", default=[], metavar="KEY=VALUE", help="head setting, repeatable")
    parser.add_argument("--train-split", default="train", help="learned heads: the training split")
    parser.add_argument("--train-limit", type=int, default=None, help="learned heads: train on the first N pairs")
    parser.add_argument("--epochs", type=int, default=1, help="learned heads: passes over the training pairs")
    parser.add_argument("--max-minutes", type=float, default=None, help="learned heads: training time budget")
    parser.add_argument("--load", default=None, help="learned heads: a saved head folder instead of training")
    parser.add_argument(
        "--checkpoint",
        default=None,
        help="ulrssm, dpfm: the authors' release checkpoint (.pth); the head gets its 'reference' preset, no training",
    )
    parser.add_argument(
        "--protocol",
        default="vertices",
        choices=("vertices", "template"),
        help="evaluated points: every vertex with a counterpart, or the template points (the references' FAUST_r/SCAPE_r protocol)",
    )
    parser.add_argument(
        "--pairs",
        default=None,
        help="faust_r/scape_r: which pairs: all (ordered), combinations (i < j, as the references), file (test_pairs.txt)",
    )
    parser.add_argument("--quick", action="store_true", help="smoke run: tiny head, few pairs, under 2 minutes on a CPU")
    parser.add_argument("--data-root", default=os.environ.get("GEOFEAT_DATA", str(HERE.parent.parent / "shared" / "data")))
    parser.add_argument("--split", default="test")
    parser.add_argument(
        "--limit",
        type=_positive_count("pairs", "; leave --limit out for all pairs"),
        default=None,
        help="evaluate the first N pairs only (N >= 1); the main job: N pairs of each kind",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--out", default=None, help="output folder (default runs/main, or runs/<pipeline>_<dataset>_<descriptor>)"
    )
    parser.add_argument(
        "--workers",
        type=_positive_count("processes"),
        default=None,
        help="processes that evaluate target shapes side by side (default: the usable CPU cores; 1 for learned heads)",
    )
    parser.add_argument(
        "--no-geodesic-store",
        action="store_true",
        help="compute the targets' geodesic matrices in memory instead of keeping them in <geofeat cache>/geodesics",
    )
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    args.main_job = all(args.__dict__[name] == parser.get_default(name) for name in vars(args) if name not in MAIN_JOB_OPTIONS)
    for name, value in SINGLE_RUN_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    return args


def output_folder(args: argparse.Namespace) -> Path:
    """``--out``, else ``runs/main`` for the main job and ``runs/<pipeline>_<dataset>_<descriptor>`` for one pipeline."""
    if args.out:
        return Path(args.out)
    return RUNS / ("main" if args.main_job else f"{args.pipeline}_{args.dataset}_{args.descriptor}")


#: Options of both kinds of run; any other option given makes a run of one pipeline.
MAIN_JOB_OPTIONS = ("out", "limit", "seed", "workers", "no_geodesic_store", "no_progress")
SINGLE_RUN_DEFAULTS = {"pipeline": "nn", "dataset": "synthetic_cuts", "descriptor": "wks"}


def descriptor_params(pairs: list[str], what: str = "--param") -> dict:
    """``["k=v", ...]`` to a dict (`geofeat.checks.parse_key_values`: JSON values when they parse; a key given twice is refused)."""
    return parse_key_values(pairs, what, error=geofeat.DescriptorError)


def _machine() -> str:
    """`common.machine` (benchmarks/common.py), importable when this file runs as a script or is loaded from a test."""
    if str(HERE) not in sys.path:
        sys.path.insert(0, str(HERE))
    from common import machine

    return machine()


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.main_job:
        try:
            return main_job(args)
        except geofeat.GeofeatError as err:
            sys.stderr.write(f"run.py: error: {err}\n")
            return 2
    try:
        if args.checkpoint and args.pipeline not in ("ulrssm", "dpfm"):
            raise geofeat.GeofeatError(f"--checkpoint loads ulrssm and dpfm release checkpoints, not {args.pipeline}")
        if args.checkpoint and args.load:
            raise geofeat.GeofeatError("give --checkpoint or --load, not both")
        pair_option = {} if args.pairs is None else {"pairs": args.pairs}
        dataset = load_dataset(args.dataset, root=args.data_root, split=args.split, seed=args.seed, **pair_option)
        params = descriptor_params(args.param)
        head = None
        if args.pipeline in REFERENCE_PIPELINES:
            args.descriptor = "none"  # reference pipelines use no features
        else:
            if args.descriptor != "xyz" and not args.checkpoint:
                make_descriptor(args.descriptor, **params)  # unknown names, parameters and missing extras fail before any work
            head = load_head(args.load) if args.load else build_head(args, params)
            if args.checkpoint:
                args.descriptor = head.config.descriptor
            if args.load and args.head_param:  # e.g. --head-param tta_steps=0 on a trained ULRSSM
                head.config = dataclasses.replace(head.config, **descriptor_params(args.head_param, what="--head-param"))
    except geofeat.GeofeatError as err:
        sys.stderr.write(f"run.py: error: {err}\n")
        return 2
    try:
        return run_pairs(args, argv, dataset, head, params)
    except geofeat.GeofeatError as err:  # a pair that cannot be read or matched, found after work started
        sys.stderr.write(f"run.py: error: {err}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("run.py: interrupted; no results written (the caches keep the features and geodesics computed).\n")
        return 130


def run_pairs(args, argv, dataset, head, params) -> int:
    """Train the head when it learns, match and score the pairs, write the results folder."""
    n_pairs = len(dataset) if args.limit is None else min(args.limit, len(dataset))
    if args.quick:
        n_pairs = min(n_pairs, QUICK_TEST_PAIRS)
    out = output_folder(args)
    out.mkdir(parents=True, exist_ok=True)
    training = train_head(head, args, out) if args.pipeline in LEARNED_PIPELINES else {}

    if head is None:
        match = _ReferenceMatch(args.pipeline, args.seed)
    else:
        match = _HeadMatch(head)
    workers = args.workers or (1 if args.pipeline in LEARNED_PIPELINES else default_workers())
    store = None if args.no_geodesic_store else GeodesicStore()
    label = pipeline_label(args.pipeline, args.descriptor)

    start = time.perf_counter()
    records, kept = evaluate_dataset(
        dataset,
        match,
        n_pairs,
        protocol=args.protocol,
        store=store,
        workers=workers,
        keep=range(N_PICTURES),
        progress=not args.no_progress,
        desc=f"{args.pipeline} on {args.dataset}",
    )
    seconds = time.perf_counter() - start
    plot_pairs([(pair, m.map_yx, label, records[i].geodesic_error) for i, (pair, m) in kept.items()], out / "pairs.png")

    summary = summarize(records)
    result = {
        "pipeline": args.pipeline,
        "dataset": args.dataset,
        "descriptor": args.descriptor,
        "descriptor_params": params,
        "split": args.split,
        "pairs_option": args.pairs,
        "protocol": args.protocol,
        "seed": args.seed,
        "date": datetime.date.today().isoformat(),
        "machine": _machine(),
        "command": shlex.join(["python", "benchmarks/run.py", *(sys.argv[1:] if argv is None else argv)]),
        "seconds": seconds,
        "head": None if head is None else {"name": head.name, "config": head.config.to_dict()},
        **training,
        **summary.to_dict(),
        "pairs": [record.to_dict() for record in records],
    }
    atomic_write(out / "results.json", lambda tmp: tmp.write_text(json.dumps(result, indent=1) + "\n"))  # never half-written
    columns = [("pipeline", "pipeline", "s"), ("descriptor", "descriptor", "s"), ("dataset", "dataset", "s"), *SUMMARY_COLUMNS]
    table = markdown_table([result], columns)
    (out / "results.md").write_text(table + "\n")
    curve = pck_curve(np.concatenate([r.errors for r in records]), np.linspace(0.0, MAIN_PCK_MAX, 201))
    plot_pck({label: curve}, out / "pck.png", f"PCK, {args.dataset}: {n_pairs} pairs", xmax=MAIN_PCK_MAX)
    print(table)
    trained = (
        f"trained {training['train_steps']} steps on {training['train_pairs']} pairs in {training['train_seconds']:.1f} s; "
        if "train_steps" in training
        else ""
    )
    print(f"{trained}{n_pairs} pairs in {seconds:.1f} s; written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
