"""Benchmarks on the published files: PSMAL, BeCoS-TOSCA and SHREC'16, beside the published figures.

Runs `run.py` once per pipeline and benchmark on data folders that you pass, then writes one
table per benchmark. Nothing here is downloaded; give only the folders you have, the other
benchmarks are left out::

    python -m benchmarks.real_files \\
        --psmal PATH/gc-ppsm/PARTIALSMAL \\                         # the full PSMAL (train + test)
        --psmal-sample ../shared/data/PSMAL_sample/PARTIALSMAL \\    # its 3-pair sample
        --becos PATH/becos-code/output \\                            # what the BeCoS generator wrote
        --shrec16 ../shared/data/SHREC16_dpfm_sample \\              # SHREC'16 in DPFM's layout
        --ulrssm-checkpoint PATH/shrec16_cuts.pth \\                 # ULRSSM's release checkpoint
        --out benchmarks/results/real_files

The runs (each a folder ``<out>/<benchmark>/<run>/`` with run.py's ``results.json``, whose
``command`` is the exact run.py call):

- ``psmal`` (full PSMAL, test split, 100 pairs): ``nn`` and ``fmap`` on WKS, HKS and SHOT, ``random``,
  and the DPFM and EchoMatch heads trained here on the train split for ``--train-minutes``;
- ``psmal_sample`` (the sample's 3 train pairs): the same pipelines; the heads are those trained
  on the full PSMAL when ``--psmal`` is given, else trained on the 3 sample pairs themselves;
- ``becos_p2f``, ``becos_p2p`` (test split of the generator's ``partial_full`` and
  ``partial_partial``): ``nn`` and ``fmap`` on WKS, HKS and SHOT, ``random``, and ULRSSM with the
  release checkpoint (no test-time adaptation; with ``--tta-pairs N`` > 0 also 15 steps on
  the first N P2F pairs, the authors' SHREC'16 test setting);
- ``shrec16_sample`` (SHREC'16 CUTS in DPFM's layout): ULRSSM with the checkpoint, with and
  without 15 steps of test-time adaptation, beside ``random``.

SHOT (DeepShapeMatchingKit's parameters) gets an absolute radius per benchmark, `SHOT_RADIUS`:
on BeCoS-TOSCA 0.5, 0.367 sqrt(area) of a full shape (sqrt(area) 1.33 to 1.36), what
DeepShapeMatchingKit's 0.3 is on FAUST_r (tr_reg_080: area 0.669). Absolute, so that a partial
shape keeps its full shape's radius. On PSMAL DeepShapeMatchingKit's 0.3 as it is: only cuts
ship (sqrt(area) 0.59 to 0.81), so the whole animals' area is not known here.

``mirrored_truth`` needs a left-right map of the shapes; neither PSMAL nor the BeCoS output
nor SHREC'16 in DPFM's layout ships one, so that row is listed as not available.

A run whose ``results.json`` exists is not repeated (``--force`` repeats it), so an
interrupted call continues where it stopped; ``--tables-only`` rewrites the tables from what
is there. The published figures are typed in by hand, each with its source, in
``<out>/published_figures.json`` (``source``: where it was read; ``cite``: how the tables name it, with a link;
``benchmarks``: for each benchmark table the entry is shown
in, how our setting differs from the published one); each table numbers the sources of its
published rows and lists them once below them.

BeCoS divides geodesic distances on a shape by the square root of the area of the full shape
it was cut from, also when the target is partial (P2P). The BeCoS loader records that length
on every pair (``ShapePair.error_scale``) and geofeat's evaluation divides by it, so the
BeCoS tables are in BeCoS's normalisation; the other benchmarks divide by the square root of
the target's own area.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks.common import BENCHMARKS, REPO, RESULTS
from geofeat.evaluation.report import markdown_table, plot_pck

log = logging.getLogger("benchmarks.real_files")

TRAINING_FREE = (("nn", "wks"), ("nn", "hks"), ("fmap", "wks"), ("fmap", "hks"))
#: SHOT's absolute support radius on the benchmarks that have SHOT rows (see the module docstring).
SHOT_RADIUS = {"becos_p2f": 0.5, "becos_p2p": 0.5, "psmal": 0.3}


def training_free(benchmark: str) -> tuple[tuple[str, str], ...]:
    """The training-free (pipeline, descriptor) runs of a benchmark: WKS and HKS, and SHOT where it has a radius."""
    shot = (("nn", "shot"), ("fmap", "shot")) if benchmark in SHOT_RADIUS else ()
    return TRAINING_FREE + shot


def descriptor_args(benchmark: str, descriptor: str) -> tuple[str, ...]:
    """run.py's ``--descriptor`` option, with SHOT's radius on this benchmark."""
    if descriptor == "shot":
        return ("--descriptor", "shot", "--param", f"radius={SHOT_RADIUS[benchmark]}")
    return ("--descriptor", descriptor)


#: Head settings of the heads trained here (the settings of benchmarks/results/heads/ on FAUST_r P2P).
HEAD_PARAMS = {"dpfm": ["fmap_features=extracted"], "echomatch": ["width=64"]}
#: ULRSSM's SHREC'16 test setting (options/test/shrec16_cuts.yaml of its repository: ``refine: 15``).
ULRSSM_TTA = 15
TITLES = {
    "psmal": "PSMAL (PARTIALSMAL), test split: partial-to-partial",
    "psmal_sample": "PSMAL sample (3 pairs of the train split): partial-to-partial",
    "becos_p2f": "BeCoS-TOSCA, partial_full, test split: partial-to-full",
    "becos_p2p": "BeCoS-TOSCA, partial_partial, test split: partial-to-partial",
    "shrec16_sample": "SHREC'16 CUTS, the real pair of DPFM's layout (cuts-cat1 to cuts-cat)",
}
NOT_AVAILABLE = {
    "psmal": "PSMAL ships no left-right (symmetry) map of its animals",
    "psmal_sample": "PSMAL ships no left-right (symmetry) map of its animals",
    "becos_p2f": "the BeCoS generator writes no left-right map for its pairs",
    "becos_p2p": "the BeCoS generator writes no left-right map for its pairs",
    "shrec16_sample": "DPFM's layout has no .sym / .baryc_gt_sym files",
}
#: What the geodesic errors are divided by, where it is not the target shape's own area.
AREA_OF = {
    "becos_p2f": "the area of the full shape the target was cut from, as BeCoS records it",
    "becos_p2p": "the area of the full shape the target was cut from, as BeCoS records it",
}


@dataclasses.dataclass(frozen=True)
class Run:
    """One call of run.py: ``<out>/<benchmark>/<name>/``."""

    benchmark: str
    name: str
    argv: tuple[str, ...]
    after: str | None = None  # a run of the same call whose head folder this one loads


def plan(args: argparse.Namespace) -> list[Run]:
    """The runs that the given folders allow, in the order they are made."""
    runs: list[Run] = []
    common = ("--no-progress", "--seed", str(args.seed), "--workers", str(args.workers))
    heads = ("dpfm", "echomatch")

    def training(pipeline: str) -> tuple[str, ...]:
        params = [item for param in HEAD_PARAMS[pipeline] for item in ("--head-param", param)]
        return (
            "--descriptor",
            "wks",
            "--train-split",
            "train",
            "--epochs",
            "100",
            "--max-minutes",
            str(args.train_minutes),
            *params,
        )

    if args.psmal:
        base = ("--dataset", "psmal", "--data-root", str(args.psmal), "--split", "test", *common)
        runs += [
            Run("psmal", f"{p}_{d}", ("--pipeline", p, *descriptor_args("psmal", d), *base)) for p, d in training_free("psmal")
        ]
        runs.append(Run("psmal", "random", ("--pipeline", "random", *base)))
        runs += [Run("psmal", p, ("--pipeline", p, *training(p), *base)) for p in heads]
    if args.psmal_sample:
        base = ("--dataset", "psmal", "--data-root", str(args.psmal_sample), "--split", "train", *common)
        runs += [Run("psmal_sample", f"{p}_{d}", ("--pipeline", p, "--descriptor", d, *base)) for p, d in TRAINING_FREE]
        runs.append(Run("psmal_sample", "random", ("--pipeline", "random", *base)))
        for p in heads:
            if args.psmal:
                head = args.out / "psmal" / p / "head"
                runs.append(Run("psmal_sample", p, ("--pipeline", p, "--load", str(head), *base), after=f"psmal/{p}"))
            else:
                runs.append(Run("psmal_sample", f"{p}_trained_on_sample", ("--pipeline", p, *training(p), *base)))
    if args.becos:
        for kind in ("p2f", "p2p"):
            bench = f"becos_{kind}"
            base = ("--dataset", bench, "--data-root", str(args.becos), "--split", "test", *common)
            runs += [
                Run(bench, f"{p}_{d}", ("--pipeline", p, *descriptor_args(bench, d), *base)) for p, d in training_free(bench)
            ]
            runs.append(Run(bench, "random", ("--pipeline", "random", *base)))
            if args.ulrssm_checkpoint:
                ckpt = ("--pipeline", "ulrssm", "--checkpoint", str(args.ulrssm_checkpoint))
                runs.append(Run(bench, "ulrssm_release", (*ckpt, *base)))
                if kind == "p2f" and args.tta_pairs:
                    tta = ("--head-param", f"tta_steps={ULRSSM_TTA}", "--limit", str(args.tta_pairs))
                    runs.append(Run(bench, f"ulrssm_release_tta{ULRSSM_TTA}", (*ckpt, *tta, *base)))
    if args.shrec16:
        base = ("--dataset", "shrec16_cuts", "--data-root", str(args.shrec16), "--split", "test", *common)
        runs.append(Run("shrec16_sample", "random", ("--pipeline", "random", *base)))
        if args.ulrssm_checkpoint:
            ckpt = ("--pipeline", "ulrssm", "--checkpoint", str(args.ulrssm_checkpoint))
            runs.append(Run("shrec16_sample", "ulrssm_release", (*ckpt, *base)))
            runs.append(
                Run(
                    "shrec16_sample", f"ulrssm_release_tta{ULRSSM_TTA}", (*ckpt, "--head-param", f"tta_steps={ULRSSM_TTA}", *base)
                )
            )
    if args.only:
        runs = [r for r in runs if r.benchmark in args.only]
    return runs


def execute(run: Run, out: Path, force: bool) -> bool:
    """Run one call of run.py into ``out/<benchmark>/<name>``; False when it failed."""
    folder = out / run.benchmark / run.name
    if (folder / "results.json").is_file() and not force:
        log.info("%s/%s: results.json exists, kept (--force repeats it)", run.benchmark, run.name)
        return True
    if run.after and not (out / run.after / "head").is_dir():
        log.error("%s/%s needs the head of %s, which is missing", run.benchmark, run.name, run.after)
        return False
    command = [sys.executable, str(BENCHMARKS / "run.py"), *run.argv, "--out", str(folder)]
    log.info("running %s", shlex.join(command))
    start = time.perf_counter()
    done = subprocess.run(command, cwd=REPO, check=False)
    log.info("%s/%s: exit %d after %.0f s", run.benchmark, run.name, done.returncode, time.perf_counter() - start)
    return done.returncode == 0


# ----------------------------------------------------------------------------- tables

#: The columns that name a row, in both tables of a benchmark.
KEY_COLUMNS = [
    ("label", "pipeline", "s"),
    ("input", "input", "s"),
]
#: The first table: the accuracy of the maps.
ACCURACY_COLUMNS = [
    *KEY_COLUMNS,
    ("n_pairs", "pairs", "d"),
    ("geodesic_error", "geodesic error x100", ".2f"),
    ("same_pairs_no_tta", "same pairs, no TTA", ".2f"),
    ("pck_auc", "PCK AUC", ".3f"),
]
#: The second table: the partial-shape scores and the training of the same runs.
OTHER_COLUMNS = [
    *KEY_COLUMNS,
    ("miou", "mIoU", ".3f"),
    ("overlap_auc", "overlap AUC", ".3f"),
    ("training", "training", "s"),
]
#: Every column, in the order of the two tables.
COLUMNS = ACCURACY_COLUMNS + OTHER_COLUMNS[len(KEY_COLUMNS) :]
ORDER = ("nn", "fmap", "dpfm", "echomatch", "ulrssm", "random")


def _label(record: dict) -> str:
    pipeline = record["pipeline"]
    if pipeline == "ulrssm" and record.get("release_checkpoint"):
        steps = record["head"]["config"].get("tta_steps", 0)
        label = f"ULRSSM `{Path(record['release_checkpoint']).name}`"
        return label + (f", {steps} TTA steps" if steps else ", no TTA")
    return {"dpfm": "DPFM", "echomatch": "EchoMatch"}.get(pipeline, pipeline)


def _training(record: dict) -> str:
    if record.get("release_checkpoint"):
        return "authors' release weights"
    if "train_steps" in record:
        text = (
            f"{record['train_steps']} steps ({record['train_steps'] / max(record['train_pairs'], 1):.1f} passes) "
            f"on {record['train_pairs']} pairs of {record.get('train_split', 'train')}, "
            f"{record['train_seconds'] / 60:.1f} min"
        )
        return text + (" (loaded)" if record.get("loaded_from") else "")
    return "-"


def _pooled(pairs: list[dict]) -> float:
    """Mean error x100 over all evaluated points of ``pairs`` (each pair's mean weighted by its points)."""
    weights = np.array([p["n_evaluated"] for p in pairs], dtype=np.float64)
    errors = np.array([p["geodesic_error"] for p in pairs])
    return float((errors * weights).sum() / weights.sum())


def table_rows(folder: Path) -> list[dict]:
    """The table rows of one benchmark folder, from its runs' results.json."""
    rows = []
    for path in sorted(folder.glob("*/results.json")):
        record = json.loads(path.read_text())
        row = dict(record)
        row["label"] = _label(record)
        descriptor = record.get("descriptor") or "none"
        row["input"] = "-" if descriptor == "none" else descriptor.upper() if descriptor != "xyz" else "xyz"
        row["training"] = _training(record)
        row["_run"] = path.parent.name
        rows.append(row)
    most = max(r["n_pairs"] for r in rows)
    for row in rows:
        if row["n_pairs"] < most:
            row["label"] += f" (first {row['n_pairs']} of {most} pairs)"
        if row["pipeline"] == "ulrssm" and row["head"]["config"].get("tta_steps"):
            base = [
                r
                for r in rows
                if r is not row
                and r.get("release_checkpoint") == row.get("release_checkpoint")
                and not r["head"]["config"].get("tta_steps")
            ]
            if base:
                names = {p["pair"] for p in row["pairs"]}
                chosen = [p for p in base[0]["pairs"] if p["pair"] in names]
                if len(chosen) == len(names):
                    row["same_pairs_no_tta"] = _pooled(chosen)
    rows.sort(key=lambda r: (ORDER.index(r["pipeline"]) if r["pipeline"] in ORDER else 99, r["input"], r["label"]))
    return rows


def _when_where(rows: list[dict]) -> str:
    """The runs' dates, then the machines they recorded (runs that kept none are given their date alone)."""
    machines = sorted({r["machine"] for r in rows if r.get("machine")})
    dates = ", ".join(sorted({r["date"] for r in rows}))
    return f"{dates}; {'; '.join(machines)}" if machines else dates


def _cite(published: dict) -> str:
    """How a table names the source of a published figure: ``cite`` (short, with a link), else ``source``."""
    return published.get("cite") or published["source"]


def write_table(out: Path, benchmark: str, published: list[dict], invocation: str, plots: bool = True) -> str | None:
    """``<out>/<benchmark>.md`` and (``plots``) ``<out>/<benchmark>_pck.png``; returns the Markdown (None: no runs).

    Two tables that share the pipeline and input columns (the accuracy, then the partial-shape
    scores and the training; columns no run fills are left out), under the runs' dates and machines.
    """
    folder = out / benchmark
    rows = table_rows(folder) if folder.is_dir() else []
    if not rows:
        return None

    def filled(columns):
        return [c for c in columns if c in KEY_COLUMNS or any(r.get(c[0]) is not None for r in rows)]

    lines = [
        f"### {TITLES[benchmark]}",
        "",
        f"Runs of {_when_where(rows)}.",
        "",
        markdown_table(rows, filled(ACCURACY_COLUMNS)),
        "",
    ]
    other = filled(OTHER_COLUMNS)
    if len(other) > len(KEY_COLUMNS):
        lines += ["The same runs' partial-shape scores and training:", "", markdown_table(rows, other), ""]
    divided_by = AREA_OF.get(benchmark, "the target shape's area")
    lines.append(
        f"`mirrored_truth`: not available ({NOT_AVAILABLE[benchmark]}). "
        "Geodesic error: mean over every evaluated vertex of all pairs, in hundredths of the square root "
        f"of {divided_by} (geofeat's protocol, see Concepts in the documentation)."
    )
    splits = sorted({r["split"] for r in rows})
    lines.append(
        f"Split evaluated: {', '.join(splits)}. Each run's exact `run.py` command and settings are in "
        f"`{benchmark}/<run>/results.json`. Written by `{invocation}` (the call and the data: "
        f"`benchmarks/results/real_files/README.md`)."
    )
    mine = [p | {"differs": p["benchmarks"][benchmark]} for p in published if benchmark in p["benchmarks"]]
    if mine:
        sources = list(dict.fromkeys(_cite(p) for p in mine))
        for p in mine:
            p["cited"] = f"[{sources.index(_cite(p)) + 1}]"
        lines += [
            "",
            "Published figures (typed in from `published_figures.json`; not the same setting, see the last column):",
            "",
        ]
        pub_columns = [
            ("method", "method", "s"),
            ("benchmark", "published on", "s"),
            ("metric", "metric", "s"),
            ("published", "figure", "s"),
            ("cited", "source", "s"),
            ("differs", "how our setting differs", "s"),
        ]
        lines += [markdown_table(mine, pub_columns), ""]
        lines += [f"\\[{n}\\] {source}" + ("  " if n < len(sources) else "") for n, source in enumerate(sources, 1)]
    text = "\n".join(lines) + "\n"
    (out / f"{benchmark}.md").write_text(text)
    if not plots:
        return text
    curves = {
        f"{r['label']}{'' if r['input'] == '-' else ' + ' + r['input']}": (np.array(r["pck_thresholds"]), np.array(r["pck"]))
        for r in rows
    }
    plot_pck(curves, out / f"{benchmark}_pck.png", TITLES[benchmark])
    return text


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--psmal", type=Path, help="the full PARTIALSMAL folder (train/ and test/), from vikiehm/gc-ppsm")
    parser.add_argument("--psmal-sample", type=Path, help="the PSMAL sample (PARTIALSMAL/ with train/ only)")
    parser.add_argument("--becos", type=Path, help="the BeCoS generator's output folder (partial_full/, partial_partial/)")
    parser.add_argument("--shrec16", type=Path, help="SHREC'16 in DPFM's layout (shrec_partial_test/)")
    parser.add_argument("--ulrssm-checkpoint", type=Path, help="ULRSSM's shrec16_cuts.pth (never committed)")
    parser.add_argument("--train-minutes", type=float, default=8.0, help="training budget of each PSMAL head (default 8)")
    parser.add_argument(
        "--tta-pairs", type=int, default=0, help="BeCoS P2F pairs also run with ULRSSM's 15 TTA steps (default 0)"
    )
    parser.add_argument("--workers", type=int, default=1, help="run.py --workers (default 1)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", nargs="+", choices=sorted(TITLES), help="run only these benchmarks")
    parser.add_argument("--force", action="store_true", help="repeat runs whose results.json exists")
    parser.add_argument("--tables-only", action="store_true", help="run nothing; rewrite the tables from the results")
    parser.add_argument("--no-plots", action="store_true", help="write the tables, not the PCK plots")
    parser.add_argument("--out", type=Path, default=RESULTS / "real_files")
    args = parser.parse_args(argv)
    for name in ("psmal", "psmal_sample", "becos", "shrec16", "ulrssm_checkpoint"):
        path = getattr(args, name)
        if path is not None and not path.exists():
            parser.error(f"--{name.replace('_', '-')} {path}: no such file or folder")
    args.out.mkdir(parents=True, exist_ok=True)

    failed = []
    if not args.tables_only:
        runs = plan(args)
        if not runs:
            parser.error("no data given: pass at least one of --psmal, --psmal-sample, --becos, --shrec16")
        for run in runs:
            if not execute(run, args.out, args.force):
                failed.append(f"{run.benchmark}/{run.name}")

    published_path = args.out / "published_figures.json"
    published = json.loads(published_path.read_text()) if published_path.is_file() else []
    for benchmark in TITLES:
        text = write_table(args.out, benchmark, published, "python -m benchmarks.real_files", plots=not args.no_plots)
        if text is not None:
            print(text)
    if failed:
        log.error("runs that failed: %s", ", ".join(failed))
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
