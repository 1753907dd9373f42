"""Gather the results.json files of several `run.py` runs into two tables and one PCK plot per dataset.

The tables share the key columns (dataset, descriptor, matcher) so that each fits a laptop's
width: the accuracy of the maps, then the partial-shape scores (mIoU, overlap AUC), training
steps and time, without the columns that no run fills. Above them, the dates of the runs and
the machines they recorded.

Usage::

    python -m benchmarks.tables.summarize benchmarks/results/*/results.json --out benchmarks/results/summary

``--tables-only`` rewrites ``OUT.md`` and leaves the plots as they are.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np

from geofeat.evaluation.protocol import SUMMARY_COLUMNS
from geofeat.evaluation.report import markdown_table, plot_pck

KEY_COLUMNS = [
    ("dataset", "dataset", "s"),
    ("descriptor", "descriptor", "s"),
    ("matcher", "matcher", "s"),
]
_METRICS = {column[0]: column for column in SUMMARY_COLUMNS}
#: The first table: how good the maps are.
ACCURACY_COLUMNS = [
    *KEY_COLUMNS,
    *(_METRICS[key] for key in ("n_pairs", "geodesic_error", "pck_auc", "chirality_accuracy")),
]
#: The second table: partial-shape scores, training and time (columns no row fills are left out).
OTHER_COLUMNS = [
    *KEY_COLUMNS,
    *(_METRICS[key] for key in ("miou", "overlap_auc")),
    ("train_steps", "training steps", "d"),
    ("seconds", "time (s)", ".0f"),
]
#: Every column, in the order of the two tables.
COLUMNS = ACCURACY_COLUMNS + OTHER_COLUMNS[len(KEY_COLUMNS) :]
#: Keys every results.json of `run.py` has; other scripts' results.json (speed, parity, profile) lack them.
RUN_KEYS = ("pipeline", "dataset", "descriptor", "date", "pck_thresholds", "pck")
log = logging.getLogger("benchmarks.tables.summarize")


def matcher_label(row: dict) -> str:
    """The pipeline name, with the head settings that tell runs of one trained head apart."""
    config = (row.get("head") or {}).get("config", {})
    label = row["pipeline"]
    if "tta_steps" in config:
        label += f", TTA {config['tta_steps']}" if config["tta_steps"] else ", no TTA"
    if config.get("pointmap") == "features":
        label += ", feature map"
    return label


def read_runs(paths: list[Path]) -> list[dict]:
    """The records of `run.py` among ``paths``; other JSON files (the speed, parity and profile scripts') are skipped with a warning."""
    rows = []
    for path in paths:
        row = json.loads(path.read_text())
        missing = [key for key in RUN_KEYS if not isinstance(row, dict) or key not in row]
        if missing:
            log.warning("skipping %s: not a results.json of run.py (no %s)", path, ", ".join(missing))
            continue
        rows.append(row)
    return rows


def provenance(rows: list[dict]) -> str:
    """One line: the dates of the runs and the machines they recorded."""
    dates = sorted({r["date"] for r in rows})
    text = f"Runs of {', '.join(dates)}; per-run settings in each results.json."
    machines = sorted({r["machine"] for r in rows if r.get("machine")})
    if machines:
        unrecorded = sum(1 for r in rows if not r.get("machine"))
        text += (
            f" Machine: {'; '.join(machines)}"
            + (f" ({unrecorded} of the {len(rows)} runs recorded none)" if unrecorded else "")
            + "."
        )
    return text


def tables(rows: list[dict]) -> str:
    """The Markdown of ``OUT.md``: the provenance line, then the accuracy table and the partial/training/time table."""
    other = [c for c in OTHER_COLUMNS if c in KEY_COLUMNS or any(r.get(c[0]) is not None for r in rows)]
    parts = [provenance(rows), "Accuracy:", markdown_table(rows, ACCURACY_COLUMNS)]
    if len(other) > len(KEY_COLUMNS):
        names = ", ".join(header for _, header, _ in other[len(KEY_COLUMNS) :])
        parts += [f"Same runs, {names}:", markdown_table(rows, other)]
    return "\n\n".join(parts) + "\n"


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", type=Path, help="results.json files")
    parser.add_argument("--out", type=Path, required=True, help="writes OUT.md and OUT_pck_<dataset>.png")
    parser.add_argument("--tables-only", action="store_true", help="write OUT.md only, not the plots")
    args = parser.parse_args(argv)
    rows = read_runs(args.results)
    if not rows:
        parser.error("none of the files is a results.json of benchmarks/run.py")
    for row in rows:
        row["matcher"] = matcher_label(row)
    rows.sort(key=lambda r: (r["dataset"], r["descriptor"], r["matcher"]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    text = tables(rows)
    args.out.with_suffix(".md").write_text(text)
    datasets = [] if args.tables_only else sorted({r["dataset"] for r in rows})
    for dataset in datasets:
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
