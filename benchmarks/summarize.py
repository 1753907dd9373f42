"""Gather the results.json files of several `run.py` runs into one table and one PCK plot.

Usage::

    python benchmarks/summarize.py benchmarks/results/*/results.json --out benchmarks/results/summary
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from geofeat.evaluation import SUMMARY_COLUMNS
from geofeat.report import markdown_table, plot_pck

COLUMNS = [
    ("dataset", "dataset", "s"),
    ("descriptor", "descriptor", "s"),
    ("matcher", "matcher", "s"),
    *SUMMARY_COLUMNS,
    ("train_steps", "training steps", "d"),
    ("seconds", "time (s)", ".0f"),
]


def matcher_label(row: dict) -> str:
    """The pipeline name, with the head settings that tell runs of one trained head apart."""
    config = (row.get("head") or {}).get("config", {})
    label = row["pipeline"]
    if "tta_steps" in config:
        label += f", TTA {config['tta_steps']}" if config["tta_steps"] else ", no TTA"
    if config.get("pointmap") == "features":
        label += ", feature map"
    return label


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", type=Path, help="results.json files")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.md and OUT_pck_<dataset>.png")
    args = parser.parse_args(argv)
    rows = [json.loads(path.read_text()) for path in args.results]
    for row in rows:
        row["matcher"] = matcher_label(row)
    rows.sort(key=lambda r: (r["dataset"], r["descriptor"], r["matcher"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    dates = sorted({r["date"] for r in rows})
    text = markdown_table(rows, COLUMNS) + f"\n\nRuns of {', '.join(dates)}; per-run settings in each results.json.\n"
    args.out.with_suffix(".md").write_text(text)
    for dataset in sorted({r["dataset"] for r in rows}):
        curves = {
            f"{r['descriptor']} + {r['matcher']}": (np.array(r["pck_thresholds"]), np.array(r["pck"]))
            for r in rows
            if r["dataset"] == dataset
        }
        plot_pck(curves, args.out.parent / f"{args.out.name}_pck_{dataset}.png", dataset)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
