"""Tables of the authors' release checkpoints run in geofeat, beside the authors' code and the published figures.

Reads what other scripts wrote and writes two Markdown tables (nothing is measured here):

- ``benchmarks/results/release/*/results.json``: `run.py` with ``--checkpoint`` (geofeat's
  heads loaded with the authors' weights);
- ``benchmarks/results/release/dpfm_transfer/results.json``: ``transfer_dpfm_partial.py``;
- the authors' own code on the same pairs: ``benchmarks/results/swap_in/results.json``
  (``swap_in.py``: ULRSSM's test pipeline with its own WKS, ``error_own_x100``) and
  ``benchmarks/results/release/dpfm_faust_r/reference.json`` (``reference_dpfm_faust_r.py``);
- ``benchmarks/results/release/published_figures.json``: the figures the authors published,
  typed in by hand from the paper or README named in each entry's ``source`` (``cite``: the
  short name shown in the table's notes).

Writes ``summary.md`` (one row per reproduced checkpoint, the headline table) and
``details.md`` (every release run, test-time adaptation and transfer runs included, as two
tables that share the key columns checkpoint, setting and benchmark: the error, then the other
scores). Above the tables: the dates of the runs and the machines they recorded (a run that
kept no date is dated by the commit that recorded it)::

    python -m benchmarks.tables.release [--results benchmarks/results]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from benchmarks.common import RESULTS, commit_date
from geofeat.evaluation.report import markdown_table

TITLES = {"ulrssm": "ULRSSM", "dpfm": "DPFM", "echomatch": "EchoMatch"}
#: A geofeat run and the reference run it is compared with must agree on these.
PROTOCOL_KEYS = ("dataset", "n_pairs")
log = logging.getLogger("benchmarks.tables.release")


def _read(path: Path):
    return json.loads(path.read_text())


def _pooled_error(pairs: list[dict], names: set[str] | None = None) -> float:
    """Mean geodesic error x100 over the evaluated vertices of ``pairs`` (those named in ``names``)."""
    chosen = [p for p in pairs if names is None or p["pair"] in names]
    if names is not None and len(chosen) != len(names):
        raise SystemExit(f"the comparison run lacks {len(names) - len(chosen)} of the pairs")
    weights = [p.get("n_evaluated", 1) for p in chosen]
    return sum(p["geodesic_error"] * w for p, w in zip(chosen, weights, strict=True)) / sum(weights)


def release_runs(folder: Path) -> list[dict]:
    """The `run.py` records of ``folder/*/results.json`` that evaluated a release checkpoint."""
    runs = []
    for path in sorted(folder.glob("*/results.json")):
        record = _read(path)
        if isinstance(record, dict) and record.get("release_checkpoint"):
            record["_path"] = path
            runs.append(record)
    return runs


def _setting(record: dict) -> str:
    config = record["head"]["config"]
    if record["pipeline"] == "ulrssm":
        steps = config.get("tta_steps", 0)
        return f"{steps} test-time adaptation steps" if steps else "no test-time adaptation"
    interpolation = config.get("interpolation")
    return "reference preset" if interpolation == "reference" else f'`interpolation="{interpolation}"`'


def _pairs_label(record: dict, full: dict[tuple, int]) -> str:
    n = record["n_pairs"]
    total = full.get((record["dataset"], record.get("pairs_option"), record.get("protocol")))
    return f"first {n} of {total}" if total and n < total else str(n)


def details_rows(runs: list[dict], transfer: list[dict]) -> list[dict]:
    """One row per release run: checkpoint, setting, benchmark, pairs, metrics, and the same pairs without TTA."""
    full: dict[tuple, int] = {}
    for r in runs:
        key = (r["dataset"], r.get("pairs_option"), r.get("protocol"))
        full[key] = max(full.get(key, 0), r["n_pairs"])
    rows = []
    for r in runs:
        row = {
            "checkpoint": f"{TITLES[r['pipeline']]} `{Path(r['release_checkpoint']).name}`",
            "setting": _setting(r),
            "dataset": r["dataset"],
            "protocol": "template points" if r.get("protocol") == "template" else "vertices",
            "pairs": _pairs_label(r, full),
            **{k: r.get(k) for k in ("geodesic_error", "pck_auc", "miou", "overlap_auc", "chirality_accuracy")},
        }
        if r["head"]["config"].get("tta_steps"):
            base = [
                b
                for b in runs
                if b is not r
                and b["release_checkpoint"] == r["release_checkpoint"]
                and b["dataset"] == r["dataset"]
                and b.get("protocol") == r.get("protocol")
                and not b["head"]["config"].get("tta_steps")
            ]
            if base:
                row["without_tta"] = _pooled_error(base[0]["pairs"], {p["pair"] for p in r["pairs"]})
        rows.append(row)
    for t in transfer:
        rows.append(
            {
                "checkpoint": f"DPFM `{t['checkpoint']}`",
                "setting": "reference preset" if t["interpolation"] == "reference" else f'`interpolation="{t["interpolation"]}"`',
                "dataset": t["dataset"],
                "protocol": "vertices",
                "pairs": str(t["n_pairs"]),
                **{k: t.get(k) for k in ("geodesic_error", "pck_auc", "miou", "overlap_auc", "chirality_accuracy")},
            }
        )
    rows.sort(key=lambda x: (x["dataset"] != "faust_r", x["checkpoint"], x["dataset"], x["setting"]))
    return rows


def reference_figures(results: Path) -> dict[tuple[str, str], dict]:
    """The authors' code run by our scripts: (head, checkpoint file name) -> record with the error x100."""
    found = {}
    swap_in = results / "swap_in" / "results.json"
    if swap_in.is_file():
        record = _read(swap_in)
        if record.get("complete", True):
            part = record["x_before_y"]
            found[("ulrssm", Path(record["checkpoint"]).name)] = {
                "error": part["error_own_x100"],
                "n_pairs": part["pairs"],
                "dataset": "faust_r",
                "script": "benchmarks/swap_in.py",
                "machine": record.get("machine"),
                "date": record.get("date"),
            }
    for path in sorted((results / "release").glob("*/reference.json")):
        record = _read(path)
        found[(record.get("head", "dpfm"), record["checkpoint"])] = {
            "error": record["geodesic_error"],
            "n_pairs": record["n_pairs"],
            "dataset": record.get("dataset", "faust_r"),
            "script": "benchmarks/reference_dpfm_faust_r.py",
            "machine": record.get("machine"),
            "date": record.get("date"),
        }
    return found


def summary_rows(runs: list[dict], references: dict, published: list[dict]) -> tuple[list[dict], list[str]]:
    """Headline rows (release checkpoints on the data they were trained for, no TTA) and the provenance lines."""
    rows, ours, theirs, settings = [], [], [], set()
    for r in runs:
        if r["head"]["config"].get("tta_steps"):
            continue
        name = Path(r["release_checkpoint"]).name
        pub = next((p for p in published if p["head"] == r["pipeline"] and p["checkpoint"] == name), None)
        if pub is None or pub["dataset"] != r["dataset"]:
            continue  # a transfer to other data: details.md only
        ref = references.get((r["pipeline"], name))
        if ref is not None and any(ref[k] != r[k] for k in PROTOCOL_KEYS):
            log.warning("%s: the reference run is on other pairs (%s); not compared", name, ref)
            ref = None
        rows.append(
            {
                "checkpoint": f"{TITLES[r['pipeline']]} `{name}`",
                "dataset": r["dataset"],
                "n_pairs": r["n_pairs"],
                "geodesic_error": r["geodesic_error"],
                "reference": None if ref is None else ref["error"],
                "published": pub["published"],
            }
        )
        settings.add((r.get("pairs_option"), r.get("protocol")))
        ours.append((r["date"], r.get("machine")))
        if ref is not None:
            theirs.append((f"`{ref['script']}` ({TITLES[r['pipeline']]})", ref["date"], ref["machine"]))
    if settings == {("combinations", "template")}:
        notes = [
            "Mean geodesic error x100 over all test pairs i < j (`--pairs combinations`), at the template points "
            "(`--protocol template`): the authors' protocol; no test-time adaptation"
        ]
    else:
        notes = ["Mean geodesic error x100, no test-time adaptation; pairs and protocol in each results.json"]
    notes.append("geofeat: `benchmarks/run.py --checkpoint`, " + _when_where(ours))
    if theirs:
        scripts = ", ".join(dict.fromkeys(script for script, _, _ in theirs))
        notes.append(f"Authors' code: {scripts}, " + _when_where([(d, m) for _, d, m in theirs]))
    return rows, notes


def _when_where(runs: list[tuple[str | None, str | None]]) -> str:
    """``date(s), machine`` of runs, each machine once; the dates alone for runs that kept no machine.

    Where those runs ran is said in the results folder's README.md, not on the page.
    """
    machines = dict.fromkeys(m for _, m in runs)
    parts = []
    for m in sorted(machines, key=lambda m: m is None):
        dates = ", ".join(sorted({d for d, mm in runs if mm == m and d})) or "date unknown"
        parts.append(f"{dates}, {m}" if m else dates)
    return "; ".join(parts)


SUMMARY_COLUMNS = [
    ("checkpoint", "checkpoint", "s"),
    ("dataset", "dataset", "s"),
    ("n_pairs", "pairs", "d"),
    ("geodesic_error", "geofeat, error x100", ".3f"),
    ("reference", "authors' code, same pairs", ".3f"),
    ("published", "published", "s"),
]
#: The columns that name a row of details.md, in both of its tables.
DETAILS_KEY_COLUMNS = [
    ("checkpoint", "checkpoint", "s"),
    ("setting", "setting", "s"),
    ("dataset", "benchmark", "s"),
]
#: details.md, first table: what was evaluated and the geodesic error.
DETAILS_ERROR_COLUMNS = [
    *DETAILS_KEY_COLUMNS,
    ("protocol", "evaluated", "s"),
    ("pairs", "pairs", "s"),
    ("geodesic_error", "error x100", ".2f"),
    ("without_tta", "same pairs, no TTA", ".2f"),
]
#: details.md, second table: the other scores of the same runs.
DETAILS_SCORE_COLUMNS = [
    *DETAILS_KEY_COLUMNS,
    ("pck_auc", "PCK AUC", ".3f"),
    ("miou", "mIoU", ".3f"),
    ("overlap_auc", "overlap AUC", ".3f"),
    ("chirality_accuracy", "chirality acc.", ".3f"),
]


def details_text(details: list[dict], dated: list[tuple[str | None, str | None]]) -> str:
    """details.md: the dates and machines of the runs (``dated``: (date, machine) per run), then its two tables."""
    groups = []
    for m in sorted(dict.fromkeys(m for _, m in dated), key=lambda m: m is None):
        runs = [d for d, mm in dated if mm == m]
        dates = ", ".join(sorted({d for d in runs if d})) or "date unknown"
        groups.append(f"{dates}{f' on {m}' if m else ''} ({len(runs)} {'run' if len(runs) == 1 else 'runs'})")
    return (
        f"geofeat runs: {'; '.join(groups)}. Settings, per-pair errors and, where the run recorded it, the machine"
        " in each results.json under `benchmarks/results/release/` (see its README.md); the DPFM transfer rows"
        " from `transfer_dpfm_partial.py` (`release/dpfm_transfer/results.json`).\n\n"
        "Geodesic error:\n\n"
        + markdown_table(details, DETAILS_ERROR_COLUMNS)
        + "\n\nThe other scores of the same runs:\n\n"
        + markdown_table(details, DETAILS_SCORE_COLUMNS)
        + "\n"
    )


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--results", type=Path, default=RESULTS, help="the benchmarks/results folder")
    args = parser.parse_args(argv)
    folder = args.results / "release"
    runs = release_runs(folder)
    if not runs:
        parser.error(f"no results.json of run.py --checkpoint under {folder}")
    transfer_path = folder / "dpfm_transfer" / "results.json"
    transfer = _read(transfer_path) if transfer_path.is_file() else []
    published = _read(folder / "published_figures.json")

    rows, notes = summary_rows(runs, reference_figures(args.results), published)
    sources = ", ".join(f"{p['cite']} ({p['published']})" for p in published)
    summary = (
        "".join(f"{line}.  \n" for line in notes)
        + f"Published: {sources}; typed in from `published_figures.json`, whose entries name their sources.\n\n"
        + markdown_table(rows, SUMMARY_COLUMNS)
        + "\n"
    )
    (folder / "summary.md").write_text(summary)

    details = details_rows(runs, transfer)
    transfer_date = commit_date(transfer_path) if transfer_path.is_file() else None
    dated = [(r["date"], r.get("machine")) for r in runs]
    dated += [(t.get("date") or transfer_date, t.get("machine")) for t in transfer]
    text = details_text(details, dated)
    (folder / "details.md").write_text(text)
    print(summary)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
