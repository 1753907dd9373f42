"""Run a matching pipeline on a benchmark and report geodesic error, PCK, mIoU and chirality.

With no arguments it runs offline on the built-in synthetic collection::

    python benchmarks/run.py
    python benchmarks/run.py --pipeline fmap --dataset faust_r_cuts --descriptor wks --data-root ../shared/data

Writes into ``--out`` (default ``benchmarks/results/<pipeline>_<dataset>_<descriptor>``):
``results.json``, ``results.md``, ``pck.png`` and ``pairs.png``.
"""

from __future__ import annotations

import argparse
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
from geofeat.adapters import matchers  # noqa: E402
from geofeat.datasets import dataset_names, load_dataset  # noqa: E402
from geofeat.descriptors.registry import make_descriptor  # noqa: E402
from geofeat.geometry.geodesic import geodesic_matrix  # noqa: E402

log = logging.getLogger("benchmarks.run")

REFERENCE_PIPELINES = ("random", "mirrored_truth")
PIPELINES = ("nn", "fmap", "fmap_zoomout", *REFERENCE_PIPELINES)
N_PICTURES = 3


def match(
    pipeline: str, pair, feat_x: np.ndarray | None, feat_y: np.ndarray | None, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted map Y -> X (V_y,) and predicted overlap on Y (V_y,) bool.

    The training-free matchers predict no overlap: every vertex of Y counts as overlapping.
    Two reference pipelines ignore the features: ``random`` (a uniformly random vertex of X,
    seeded) and ``mirrored_truth`` (the left-right mirrored ground truth: the cost of a
    perfect but flipped map; needs a dataset with chirality ground truth).
    """
    if pipeline == "random":
        predicted = np.random.default_rng(seed).integers(0, pair.x.n_vertices, pair.y.n_vertices)
    elif pipeline == "mirrored_truth":
        if pair.map_yx_sym is None:
            raise geofeat.DatasetError("pipeline 'mirrored_truth' needs a dataset with a mirrored ground truth")
        predicted = np.where(pair.map_yx_sym >= 0, pair.map_yx_sym, -1)
    elif pipeline == "nn":
        predicted = matchers.nn_match(feat_x, feat_y)
    elif pipeline in ("fmap", "fmap_zoomout"):
        predicted = matchers.fmap_match(pair.x, pair.y, feat_x, feat_y, zoomout=pipeline == "fmap_zoomout")
    else:
        raise ValueError(f"unknown pipeline {pipeline!r}; expected one of {PIPELINES}")
    return predicted, np.ones(pair.y.n_vertices, dtype=bool)


def evaluate_pair(pair, predicted: np.ndarray, overlap_pred: np.ndarray) -> dict:
    """Per-pair metrics; ``errors`` is the array of per-vertex geodesic errors."""
    dist_x = geodesic_matrix(pair.x, method="dijkstra", normalize=True)
    errors = metrics.geodesic_errors(predicted, pair.map_yx, dist_x)
    record = {"pair": f"{pair.y.name}->{pair.x.name}", "errors": errors, "n_evaluated": int(errors.size)}
    if pair.map_yx_sym is not None:
        record["chirality_accuracy"] = metrics.chirality_accuracy(predicted, pair.map_yx, pair.map_yx_sym, dist_x)
    if pair.overlap_y is not None:
        record["iou"] = metrics.overlap_iou(overlap_pred, pair.overlap_y)
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
    with_iou = [r for r in records if "iou" in r]
    if with_iou:
        summary["miou"] = float(np.mean([r["iou"] for r in with_iou]))
    return summary


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
    parser.add_argument("--data-root", default=os.environ.get("GEOFEAT_DATA", str(HERE.parent.parent / "shared" / "data")))
    parser.add_argument("--split", default="test")
    parser.add_argument("--limit", type=int, default=None, help="evaluate the first N pairs only")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    parser.add_argument("--no-progress", action="store_true")
    return parser.parse_args(argv)


def descriptor_params(pairs: list[str]) -> dict:
    """``["k=v", ...]`` to a dict; values parsed as JSON when they parse (numbers, booleans, null), else strings."""
    params = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise geofeat.DescriptorError(f"--param takes KEY=VALUE, found {pair!r}")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        dataset = load_dataset(args.dataset, root=args.data_root, split=args.split, seed=args.seed)
        params = descriptor_params(args.param)
        if args.pipeline in REFERENCE_PIPELINES:
            args.descriptor = "none"  # reference pipelines use no features
        else:
            make_descriptor(args.descriptor, **params)  # unknown names, parameters and missing extras fail before any work
    except geofeat.GeofeatError as err:
        sys.stderr.write(f"run.py: error: {err}\n")
        return 2
    n_pairs = len(dataset) if args.limit is None else min(args.limit, len(dataset))
    out = Path(args.out or HERE / "results" / f"{args.pipeline}_{args.dataset}_{args.descriptor}")
    out.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    records, pictures = [], []
    for i in tqdm(range(n_pairs), desc=f"{args.pipeline} on {args.dataset}", unit="pair", disable=args.no_progress):
        pair = dataset[i]
        if args.pipeline in REFERENCE_PIPELINES:  # they ignore features
            feat_x = feat_y = None
        else:
            feat_x = geofeat.compute(pair.x, args.descriptor, **params)
            feat_y = geofeat.compute(pair.y, args.descriptor, **params)
        predicted, overlap_pred = match(args.pipeline, pair, feat_x, feat_y, seed=args.seed * 100003 + i)
        records.append(evaluate_pair(pair, predicted, overlap_pred))
        if len(pictures) < N_PICTURES:
            pictures.append((pair, predicted, f"{args.descriptor} + {args.pipeline}"))
    seconds = time.perf_counter() - start

    summary = summarize(records)
    result = {
        "pipeline": args.pipeline,
        "dataset": args.dataset,
        "descriptor": args.descriptor,
        "descriptor_params": params,
        "split": args.split,
        "seed": args.seed,
        "date": datetime.date.today().isoformat(),
        "seconds": seconds,
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
    print(f"{n_pairs} pairs in {seconds:.1f} s; written to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
