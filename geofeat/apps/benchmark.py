"""Run matching pipelines on a benchmark and report geodesic error, PCK, mIoU and chirality.

With no arguments it runs the main job, offline, in about 10 seconds: six training-free
pipelines (nearest neighbour and functional maps on WKS, HKS and SHOT) and the two reference rows
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

from geofeat.adapters.base import Head
from geofeat.adapters.heads import load_head, make_head
from geofeat.apps.machine import machine
from geofeat.apps.main_job import MAIN_PCK_MAX, REFERENCE_PIPELINES, HeadMatch, ReferenceMatch, main_job, pipeline_label
from geofeat.checks import parse_key_values
from geofeat.datasets import dataset_names, load_dataset
from geofeat.datasets.base import DATA_ENV
from geofeat.descriptors.registry import make_descriptor
from geofeat.errors import DescriptorError, GeofeatError
from geofeat.evaluation.metrics import pck_curve
from geofeat.evaluation.protocol import SUMMARY_COLUMNS, default_workers, evaluate_dataset, summarize
from geofeat.evaluation.report import markdown_table, plot_pairs, plot_pck
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.storage.files import atomic_write

LEARNED_PIPELINES = ("ulrssm", "dpfm", "echomatch")
TRAINING_RECORD = "training.json"  # how a head saved by a run was trained
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


def _say(line: str = "") -> None:
    sys.stdout.write(line + "\n")


def build_head(args, params: dict) -> Head:
    """The head of ``--pipeline`` with the input descriptor, ``--head-param`` settings and ``--quick`` sizes."""
    settings = {"descriptor": args.descriptor, "descriptor_params": params, "progress": not args.no_progress}
    if args.pipeline in ("nn", "fmap", "fmap_zoomout"):
        zoomout = {"zoomout": True} if args.pipeline == "fmap_zoomout" else {}
        return make_head("fmap" if zoomout else args.pipeline, **settings, **zoomout)
    if args.checkpoint:
        return load_head(
            args.pipeline,
            checkpoint=args.checkpoint,
            progress=not args.no_progress,
            **descriptor_params(args.head_param, what="--head-param"),
        )
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
    parser.add_argument("--data-root", default=None, help=f"the folder holding the datasets (default ${DATA_ENV})")
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


def output_folder(args: argparse.Namespace, runs: str | os.PathLike = "runs") -> Path:
    """``--out``, else ``<runs>/main`` for the main job and ``<runs>/<pipeline>_<dataset>_<descriptor>`` for one pipeline."""
    if args.out:
        return Path(args.out)
    return Path(runs) / ("main" if args.main_job else f"{args.pipeline}_{args.dataset}_{args.descriptor}")


#: Options of both kinds of run; any other option given makes a run of one pipeline.
MAIN_JOB_OPTIONS = ("out", "limit", "seed", "workers", "no_geodesic_store", "no_progress")
SINGLE_RUN_DEFAULTS = {"pipeline": "nn", "dataset": "synthetic_cuts", "descriptor": "wks"}


def descriptor_params(pairs: list[str], what: str = "--param") -> dict:
    """``["k=v", ...]`` to a dict (`geofeat.checks.parse_key_values`: JSON values when they parse; a key given twice is refused)."""
    return parse_key_values(pairs, what, error=DescriptorError)


def main(argv: list[str] | None = None, runs: str | os.PathLike = "runs") -> int:
    """The command of ``benchmarks/run.py``: the main job, or one pipeline on one benchmark.

    Parameters
    ----------
    argv : list of str or None
        The options (None: ``sys.argv[1:]``).
    runs : path-like
        Where runs write without ``--out`` (``benchmarks/run.py`` gives the repository's
        ``runs/``, ignored by git).

    Returns
    -------
    int
        The exit status: 0 done, 1 a pair could not be read or matched once the run had
        started, 2 bad input, 130 interrupted.
    """
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    if args.main_job:
        try:
            return main_job(args, output_folder(args, runs))
        except GeofeatError as err:
            sys.stderr.write(f"run.py: error: {err}\n")
            return 2
    try:
        if args.checkpoint and args.pipeline not in ("ulrssm", "dpfm"):
            raise GeofeatError(f"--checkpoint loads ulrssm and dpfm release checkpoints, not {args.pipeline}")
        if args.checkpoint and args.load:
            raise GeofeatError("give --checkpoint or --load, not both")
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
    except GeofeatError as err:
        sys.stderr.write(f"run.py: error: {err}\n")
        return 2
    try:
        return run_pairs(args, argv, dataset, head, params, output_folder(args, runs))
    except GeofeatError as err:  # a pair that cannot be read or matched, found after work started
        sys.stderr.write(f"run.py: error: {err}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write("run.py: interrupted; no results written (the caches keep the features and geodesics computed).\n")
        return 130


def run_pairs(args: argparse.Namespace, argv: list[str] | None, dataset, head: Head | None, params: dict, out: Path) -> int:
    """Train the head when it learns, match and score the pairs, write the results folder ``out``."""
    n_pairs = len(dataset) if args.limit is None else min(args.limit, len(dataset))
    if args.quick:
        n_pairs = min(n_pairs, QUICK_TEST_PAIRS)
    out.mkdir(parents=True, exist_ok=True)
    training = train_head(head, args, out) if args.pipeline in LEARNED_PIPELINES else {}

    if head is None:
        match = ReferenceMatch(args.pipeline, args.seed)
    else:
        match = HeadMatch(head)
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
        "machine": machine(),
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
    _say(table)
    trained = (
        f"trained {training['train_steps']} steps on {training['train_pairs']} pairs in {training['train_seconds']:.1f} s; "
        if "train_steps" in training
        else ""
    )
    _say(f"{trained}{n_pairs} pairs in {seconds:.1f} s; written to {out}")
    return 0
