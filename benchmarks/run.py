"""Run a matching pipeline on a benchmark and report geodesic error, PCK, mIoU and chirality.

With no arguments it runs offline on the built-in synthetic collection::

    python benchmarks/run.py
    python benchmarks/run.py --pipeline fmap --dataset faust_r_cuts --descriptor wks --data-root ../shared/data
    python benchmarks/run.py --pipeline ulrssm --dataset faust_r_cuts --descriptor wks --max-minutes 30
    python benchmarks/run.py --pipeline dpfm --quick          # a smoke run of a learned head, < 2 min on a CPU

Learned heads (ulrssm, dpfm, echomatch) are trained first on ``--train-split`` of the same
dataset (or loaded with ``--load``) and saved into ``<out>/head``. Writes into ``--out`` (default ``benchmarks/results/<pipeline>_<dataset>_<descriptor>``):
``results.json``, ``results.md``, ``pck.png`` and ``pairs.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import os
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from report import markdown_table, plot_pairs, plot_pck  # noqa: E402

import geofeat  # noqa: E402
from geofeat import metrics  # noqa: E402
from geofeat.adapters.heads import Head, Match, load_head, make_head  # noqa: E402
from geofeat.datasets import dataset_names, load_dataset  # noqa: E402
from geofeat.descriptors.registry import make_descriptor  # noqa: E402
from geofeat.files import atomic_write  # noqa: E402
from geofeat.geometry.geodesic import geodesic_matrix  # noqa: E402

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


def evaluate_pair(pair, match: Match, protocol: str = "vertices") -> dict:
    """Per-pair metrics; ``errors`` is the array of geodesic errors of the evaluated points.

    ``protocol="vertices"`` evaluates every vertex of ``y`` with a counterpart (our default);
    ``"template"`` evaluates the template points of datasets with a common template
    (FAUST_r, SCAPE_r), as the ULRSSM and DPFM references do
    (`geofeat.metrics.template_geodesic_errors`).

    The overlap IoU is the mean over the shapes whose ground-truth overlap the dataset gives; a
    head that predicts no overlap for a shape counts as predicting all of it. Heads that give
    overlap probabilities also get their ROC AUC, averaged over the shapes whose ground truth
    holds both classes.
    """
    dist_x = geodesic_matrix(pair.x, method="dijkstra", normalize=True)
    predicted = match.map_yx
    if protocol == "template":
        if pair.corr_x is None or pair.corr_y is None:
            raise geofeat.DatasetError(
                f"pair {pair.name}: --protocol template needs a dataset with template points (faust_r, scape_r)"
            )
        errors = metrics.template_geodesic_errors(predicted, pair.corr_x, pair.corr_y, dist_x)
        sym = None
        if pair.corr_x_sym is not None:
            sym = (metrics.at_template_points(predicted, pair.corr_y), pair.corr_x, pair.corr_x_sym)
    else:
        errors = metrics.geodesic_errors(predicted, pair.map_yx, dist_x)
        sym = None if pair.map_yx_sym is None else (predicted, pair.map_yx, pair.map_yx_sym)
    record = {"pair": f"{pair.y.name}->{pair.x.name}", "errors": errors, "n_evaluated": int(errors.size)}
    if sym is not None:
        record["chirality_accuracy"] = metrics.chirality_accuracy(*sym, dist_x)
    ious = [
        metrics.overlap_iou(np.ones(truth.shape, dtype=bool) if guess is None else guess, truth)
        for guess, truth in ((match.overlap_y, pair.overlap_y), (match.overlap_x, pair.overlap_x))
        if truth is not None
    ]
    if ious:
        record["iou"] = float(np.mean(ious))
    aucs = [
        metrics.overlap_auc(scores, truth)
        for scores, truth in ((match.overlap_prob_y, pair.overlap_y), (match.overlap_prob_x, pair.overlap_x))
        if scores is not None and truth is not None
    ]
    aucs = [auc for auc in aucs if auc is not None]
    if aucs:
        record["overlap_auc"] = float(np.mean(aucs))
    return record


def summarize(records: list[dict]) -> dict:
    """Pooled metrics over pairs, the way published tables report them."""
    errors = [r["errors"] for r in records]
    thresholds, fractions = metrics.pck_curve(np.concatenate(errors))
    summary = {
        "n_pairs": len(records),
        "n_evaluated_vertices": int(sum(r["n_evaluated"] for r in records)),
        "geodesic_error": metrics.mean_geodesic_error(errors),
        "pck_auc": metrics.pck_auc(np.concatenate(errors)),
        "pck_thresholds": thresholds.tolist(),
        "pck": fractions.tolist(),
    }
    with_chirality = [r for r in records if "chirality_accuracy" in r]
    if with_chirality:
        weights = np.array([r["n_evaluated"] for r in with_chirality], dtype=float)
        values = np.array([r["chirality_accuracy"] for r in with_chirality])
        summary["chirality_accuracy"] = float((weights * values).sum() / weights.sum())
    for key, name in (("iou", "miou"), ("overlap_auc", "overlap_auc")):
        values = [r[key] for r in records if key in r]
        if values:
            summary[name] = float(np.mean(values))
    return summary


def _pair_count(text: str) -> int:
    """argparse type of ``--limit``: a positive whole number of pairs."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive whole number of pairs, found {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"expected a positive number of pairs (at least 1), found {value}; leave --limit out for all pairs"
        )
    return value


def parse_args(argv=None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pipeline", default="nn", choices=PIPELINES)
    parser.add_argument("--dataset", default="synthetic_cuts", help=f"one of: {', '.join(dataset_names())}")
    parser.add_argument("--descriptor", default="wks", help="any registered descriptor (geofeat descriptors)")
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
    parser.add_argument("--limit", type=_pair_count, default=None, help="evaluate the first N pairs only (N >= 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    parser.add_argument("--no-progress", action="store_true")
    return parser.parse_args(argv)


def descriptor_params(pairs: list[str], what: str = "--param") -> dict:
    """``["k=v", ...]`` to a dict; values parsed as JSON when they parse (numbers, booleans, null), else strings."""
    params = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise geofeat.DescriptorError(f"{what} takes KEY=VALUE, found {pair!r}")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
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
    n_pairs = len(dataset) if args.limit is None else min(args.limit, len(dataset))
    if args.quick:
        n_pairs = min(n_pairs, QUICK_TEST_PAIRS)
    out = Path(args.out or HERE / "results" / f"{args.pipeline}_{args.dataset}_{args.descriptor}")
    out.mkdir(parents=True, exist_ok=True)
    training = train_head(head, args, out) if args.pipeline in LEARNED_PIPELINES else {}

    start = time.perf_counter()
    records, pictures = [], []
    for i in tqdm(range(n_pairs), desc=f"{args.pipeline} on {args.dataset}", unit="pair", disable=args.no_progress):
        pair = dataset[i]
        if head is None:
            match = reference_match(args.pipeline, pair, seed=args.seed * 100003 + i)
        else:
            match = head.match(pair)
        records.append(evaluate_pair(pair, match, args.protocol))
        if len(pictures) < N_PICTURES:
            pictures.append((pair, match.map_yx, f"{args.descriptor} + {args.pipeline}"))
    seconds = time.perf_counter() - start

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
        "seconds": seconds,
        "head": None if head is None else {"name": head.name, "config": head.config.to_dict()},
        **training,
        **summary,
        "pairs": [
            {k: v for k, v in r.items() if k != "errors"} | {"geodesic_error": 100 * float(r["errors"].mean())} for r in records
        ],
    }
    (out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    columns = [
        ("pipeline", "pipeline", "s"),
        ("descriptor", "descriptor", "s"),
        ("dataset", "dataset", "s"),
        ("n_pairs", "pairs", "d"),
        ("geodesic_error", "geodesic error x100", ".2f"),
        ("pck_auc", "PCK AUC", ".3f"),
        ("miou", "mIoU", ".3f"),
        ("overlap_auc", "overlap AUC", ".3f"),
        ("chirality_accuracy", "chirality acc.", ".3f"),
    ]
    table = markdown_table([result], columns)
    (out / "results.md").write_text(table + "\n")
    plot_pck(
        {f"{args.descriptor} + {args.pipeline}": (np.array(summary["pck_thresholds"]), np.array(summary["pck"]))},
        out / "pck.png",
        args.dataset,
    )
    plot_pairs(pictures, out / "pairs.png")
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
