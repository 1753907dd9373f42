"""Depth scans against CUTS partial meshes: the same pipelines on ``faust_r_scans`` and ``faust_r_cuts``, side by side.

Every row is a `benchmarks/run.py` call on the test split, on the first ``--pairs`` pairs of
each benchmark. Both order the ordered pairs (A, B) of the test individuals the same way
from the seed, so the two columns hold the same individuals; the partial side is a depth scan
(a point cloud) in one and a CUTS partial mesh in the other. Rows:

- ``nn`` and ``fmap`` on WKS, HKS and SHOT (DeepShapeMatchingKit's radius 0.3, in FAUST_r's units),
  ``random`` and ``mirrored_truth``;
- DPFM trained on CUTS partial meshes (``faust_r_cuts``, train split, ``--train-minutes``), then
  evaluated on CUTS and, as it is, on the scans: what the change from meshes to scans costs a
  learned head.

It also times the DINOv3 descriptor end to end on ``--dino-scans`` scans, with the default
recipe (49 views at 512 x 512) and a small randomly initialised DINOv3 (width 64, 4 blocks):
no weights can be downloaded here, so the features mean nothing; the time is that of the
rendering, the back-projection and a small backbone (a ViT-B/16 adds its forward passes).

Writes (``--out``, default ``benchmarks/results/scans``) ``<out>/<benchmark>/<run>/`` (run.py's outputs; a run whose results.json exists is
kept unless ``--force``), ``<out>/scans_vs_cuts.md`` and ``.json``::

    python -m benchmarks.scans_vs_cuts --data /work/shared/data --workers 2
"""

from __future__ import annotations

import argparse
import datetime
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine, write_results
from benchmarks.real_files import Run, execute
from geofeat.evaluation.report import markdown_table

log = logging.getLogger("benchmarks.scans_vs_cuts")

BENCHMARKS = ("faust_r_scans", "faust_r_cuts")
TRAINING_FREE = (("nn", "wks"), ("nn", "hks"), ("nn", "shot"), ("fmap", "wks"), ("fmap", "hks"), ("fmap", "shot"))
#: SHOT's support radius: DeepShapeMatchingKit's, in FAUST_r's units (a scan keeps its mesh's units).
SHOT_RADIUS = 0.3
#: The randomly initialised DINOv3 of the timings: width 64, 4 blocks.
SMALL_BACKBONE = {"hidden_size": 64, "intermediate_size": 256, "num_hidden_layers": 4, "num_attention_heads": 2}
#: The learned head trained on CUTS partial meshes, with the settings of the PSMAL runs.
HEAD = ("dpfm", ("--descriptor", "wks", "--head-param", "fmap_features=extracted"))


def plan(args: argparse.Namespace) -> list[Run]:
    """The run.py calls, in the order they are made (the head is trained before it is loaded)."""
    runs: list[Run] = []
    common = ("--data-root", str(args.data), "--no-progress", "--seed", str(args.seed), "--workers", str(args.workers))
    test = ("--split", "test", "--limit", str(args.pairs), *common)
    for benchmark in BENCHMARKS:
        base = ("--dataset", benchmark, *test)
        for pipeline, descriptor in TRAINING_FREE:
            shot = ("--param", f"radius={SHOT_RADIUS}") if descriptor == "shot" else ()
            runs.append(
                Run(benchmark, f"{pipeline}_{descriptor}", ("--pipeline", pipeline, "--descriptor", descriptor, *shot, *base))
            )
        runs += [Run(benchmark, reference, ("--pipeline", reference, *base)) for reference in ("random", "mirrored_truth")]
    pipeline, settings = HEAD
    train = ("--train-split", "train", "--epochs", "100", "--max-minutes", str(args.train_minutes))
    runs.append(Run("faust_r_cuts", pipeline, ("--pipeline", pipeline, *settings, *train, "--dataset", "faust_r_cuts", *test)))
    head = str(args.out / "faust_r_cuts" / pipeline / "head")
    loaded = ("--pipeline", pipeline, *settings, "--load", head, "--dataset", "faust_r_scans", *test)
    runs.append(Run("faust_r_scans", f"{pipeline}_trained_on_cuts", loaded, after=f"faust_r_cuts/{pipeline}"))
    return runs


def row_label(record: dict) -> str:
    """How a run is named in the table: pipeline + input, and where a learned head was trained."""
    pipeline, descriptor = record["pipeline"], record.get("descriptor") or "none"
    label = pipeline if descriptor == "none" else f"{pipeline} + {descriptor.upper()}"
    if "train_steps" in record or record.get("loaded_from"):
        label += " (trained on CUTS meshes)"
    return label


def side_by_side(out: Path) -> list[dict]:
    """One row per pipeline with the scans' and the CUTS' figures, from the runs' results.json."""
    rows: dict[str, dict] = {}
    for benchmark in BENCHMARKS:
        for path in sorted((out / benchmark).glob("*/results.json")):
            record = json.loads(path.read_text())
            row = rows.setdefault(row_label(record), {"label": row_label(record)})
            prefix = "scans" if benchmark == "faust_r_scans" else "cuts"
            row[f"{prefix}_pairs"] = record["n_pairs"]
            row[f"{prefix}_error"] = record["geodesic_error"]
            row[f"{prefix}_pck"] = record["pck_auc"]
            row[f"{prefix}_chirality"] = record.get("chirality_accuracy")
            row[f"{prefix}_seconds"] = record["seconds"]
            row[f"{prefix}_date"] = record["date"]
            if "train_steps" in record:
                row["train_steps"] = record["train_steps"]
    order = [f"{p} + {d.upper()}" for p, d in TRAINING_FREE] + ["random", "mirrored_truth"]
    return sorted(rows.values(), key=lambda r: order.index(r["label"]) if r["label"] in order else len(order))


def dino_timings(data: Path, n_scans: int, seed: int) -> list[dict]:
    """Wall time of ``geofeat.compute(scan, "dinov3")`` with a small random backbone, per scan."""
    import geofeat
    from benchmarks.speed.dino import random_dinov3
    from geofeat.datasets.registry import load_dataset

    dataset = load_dataset("faust_r_scans", data, split="test", seed=seed)
    timings = []
    with tempfile.TemporaryDirectory(prefix="geofeat-scans-dino-") as tmp:
        weights = Path(tmp) / "backbone"
        random_dinov3(seed, **SMALL_BACKBONE).model.save_pretrained(weights)
        for index in range(n_scans):
            scan = dataset[index].y
            start = time.perf_counter()
            features = geofeat.compute(scan, "dinov3", weights=str(weights), cache=False)
            timings.append(
                {
                    "scan": scan.name,
                    "points": scan.n_vertices,
                    "seconds": time.perf_counter() - start,
                    "finite": bool(np.isfinite(features).all()),
                    "seen_share": float(np.mean(np.abs(features).sum(axis=1) > 0)),
                }
            )
            log.info("dinov3 on %s (%d points): %.1f s", scan.name, scan.n_vertices, timings[-1]["seconds"])
    return timings


COLUMNS = [
    ("label", "pipeline", "s"),
    ("scans_error", "scans: error x100", ".1f"),
    ("scans_pck", "PCK AUC", ".3f"),
    ("scans_chirality", "chirality", ".2f"),
    ("cuts_error", "CUTS meshes: error x100", ".1f"),
    ("cuts_pck", "PCK AUC", ".3f"),
    ("cuts_chirality", "chirality", ".2f"),
]


def report(rows: list[dict], timings: list[dict], args: argparse.Namespace) -> str:
    """The Markdown of ``scans_vs_cuts.md``."""
    pairs = sorted({r.get(f"{side}_pairs") for r in rows for side in ("scans", "cuts")} - {None})
    dates = sorted({r.get(f"{side}_date") for r in rows for side in ("scans", "cuts")} - {None})
    steps = ", ".join(str(r["train_steps"]) for r in rows if "train_steps" in r) or "no"
    lines = [
        markdown_table(rows, COLUMNS),
        "",
        f"Test split of FAUST_r, the first {', '.join(map(str, pairs))} pairs of each benchmark (the same individuals); "
        "the partial side is a depth scan (a point cloud of 2,000 to 4,000 points) or a CUTS partial mesh, the full side "
        "a FAUST_r mesh. Geodesic error: mean over the evaluated points, in hundredths of sqrt(area) of the full "
        f"shape. SHOT radius {SHOT_RADIUS}. DPFM trained for {args.train_minutes:g} minutes ({steps} steps) on CUTS "
        f"partial meshes (faust_r_cuts, train split) and evaluated as it is on both. Runs of {', '.join(dates)}; {machine()}. "
        "Written by `python -m benchmarks.scans_vs_cuts`.",
    ]
    if timings:
        seconds = np.array([t["seconds"] for t in timings])
        points = [t["points"] for t in timings]
        lines += [
            "",
            f"DINOv3 (the default recipe, a small random backbone: width 64, 4 blocks) on {len(timings)} scans of {min(points)} to "
            f"{max(points)} points: {seconds.mean():.1f} s per scan on average ({seconds.min():.1f} to {seconds.max():.1f}); "
            f"features finite on every scan, {100 * np.mean([t['seen_share'] for t in timings]):.0f}% of points seen.",
        ]
    return "\n".join(lines)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--data", default=DEFAULT_DATA, help="folder with FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--pairs", type=int, default=100, help="test pairs of each benchmark (default 100)")
    parser.add_argument("--train-minutes", type=float, default=6.0, help="DPFM's training budget (default 6)")
    parser.add_argument("--dino-scans", type=int, default=3, help="scans the DINOv3 timing runs on (0: none)")
    parser.add_argument("--workers", type=int, default=1, help="run.py --workers (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--force", action="store_true", help="repeat runs whose results.json exists")
    parser.add_argument("--out", type=Path, default=RESULTS / "scans")
    args = parser.parse_args(argv)
    args.data = data_folder(args.data)
    failed = [f"{r.benchmark}/{r.name}" for r in plan(args) if not execute(r, args.out, args.force)]
    timings = dino_timings(args.data, args.dino_scans, args.seed) if args.dino_scans else []
    rows = side_by_side(args.out)
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    result = {"date": stamp, "machine": machine(), "rows": rows, "dino_timings": timings, "failed": failed}
    write_results(args.out / "scans_vs_cuts", result, report(rows, timings, args))
    if failed:
        log.error("failed runs: %s", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
