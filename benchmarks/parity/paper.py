"""geofeat's evaluation of the GeoLoRA paper's benchmarks against the official evaluation code, pair by pair.

For one benchmark (`geofeat.evaluation.paper_benchmarks.PAPER_BENCHMARKS`), both sides score
the same predicted maps (seeded random maps, one per pair, the same arrays for both):

- geofeat: `paper_pairs` (the dataset's pairs with the official error scale), evaluated with
  `geofeat.evaluation.evaluate_pair` at the benchmark's points, pooled by `summarize`;
- the official code: ``benchmarks/official/geolora_eval.py``, which runs the official dataset
  classes and ``validation_partial_full`` of ``vikiehm/geo-lora`` in their own environment
  (``--official-python``; see that script for how to set it up).

It reports the pairs each side has, the pairs whose evaluated point counts or mean errors
differ, the largest per-pair difference and both pooled errors, into ``OUT.json`` and a row of
``OUT.md``; ``--table`` rebuilds ``parity.md`` from every ``parity_*.json`` beside it.

    python -m benchmarks.parity.paper psmal --data /data/PARTIALSMAL/test \\
        --official-python /ref/venv/bin/python --geo-lora /ref/geo-lora --out benchmarks/results/paper/parity_psmal
    python -m benchmarks.parity.paper --table benchmarks/results/paper
"""

from __future__ import annotations

import argparse
import datetime
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.common import BENCHMARKS, RESULTS, machine
from geofeat.datasets.records import Match, ShapePair
from geofeat.evaluation import evaluate_pair, summarize
from geofeat.evaluation.paper_benchmarks import PAPER_BENCHMARKS, PaperBenchmark, paper_benchmark, paper_pairs

HARNESS = BENCHMARKS / "official" / "geolora_eval.py"
#: Per-pair mean errors (unscaled) that differ by more than this count as differing.
TOLERANCE = 1e-6


def official_key(pair: ShapePair, benchmark: PaperBenchmark) -> str:
    """The key the official harness gives the pair: ``"<partial stem>|<full stem>"`` (BeCoS: ``"<folder>/..."``).

    geofeat names a BeCoS shape ``<pair folder>_<file stem>`` (``0_1_victoria10``); the official
    dataset gives the folder and the stem apart.
    """
    if benchmark.dataset.startswith("becos"):
        folder, partial = pair.y.name.split("_", 1)
        _, full = pair.x.name.split("_", 1)
        return f"{folder}/{partial}|{full}"
    return f"{pair.y.name}|{pair.x.name}"


def random_maps(pairs, benchmark: PaperBenchmark, seed: int) -> dict[str, np.ndarray]:
    """One seeded random map per pair, ``(V_y,)`` int64 vertices of x, by official key."""
    maps = {}
    for index in range(len(pairs)):
        pair = pairs[index]
        rng = np.random.default_rng([seed, index])
        maps[official_key(pair, benchmark)] = rng.integers(0, pair.x.n_vertices, pair.y.n_vertices, dtype=np.int64)
    return maps


def geofeat_side(pairs, benchmark: PaperBenchmark, maps: dict[str, np.ndarray]) -> dict:
    """geofeat's evaluation of the maps with the official protocol, per pair (by key) and pooled; and with its own.

    Returns
    -------
    dict
        ``pairs``: key -> evaluated count and mean error; ``pooled_error`` (unscaled);
        ``pooled_default_x100``: the same maps under geofeat's own protocol (the dataset's
        pairs as they are, every vertex with a counterpart once, errors over ``sqrt(area(x))``).
    """
    records, default, rows = [], [], {}
    for index in range(len(pairs)):
        pair = pairs[index]
        key = official_key(pair, benchmark)
        match = Match(maps[key], np.ones(maps[key].size, dtype=bool))
        record = evaluate_pair(pair, match, protocol=benchmark.points)
        records.append(record)
        rows[key] = {"n_evaluated": record.n_evaluated, "error_mean": float(record.errors.mean())}
        default.append(evaluate_pair(pairs.pairs[pairs.indices[index]], match))
    return {
        "pairs": rows,
        "pooled_error": summarize(records).geodesic_error / 100,
        "pooled_default_x100": summarize(default).geodesic_error,
    }


def official_side(args, data: Path, predictions: Path, out: Path) -> dict:
    """Run the official harness in its environment on the predictions; its JSON output."""
    command = [args.official_python, str(HARNESS), args.benchmark, "--data", str(data), "--predictions", str(predictions)]
    command += ["--out", str(out), "--geo-lora", args.geo_lora] + list(args.official_arg)
    done = subprocess.run(command, capture_output=True, text=True)
    if not out.is_file():
        raise SystemExit(f"the official harness failed (exit {done.returncode}):\n{done.stderr[-3000:]}")
    return json.loads(out.read_text())


def compare(ours: dict, official: dict) -> dict:
    """Pairs of each side, pairs that differ, the largest per-pair difference, both pooled errors."""
    theirs = {p["key"]: p for p in official["pairs"]}
    common = sorted(set(ours["pairs"]) & set(theirs))
    count_differs = [k for k in common if ours["pairs"][k]["n_evaluated"] != theirs[k]["n_evaluated"]]
    gaps = {k: abs(ours["pairs"][k]["error_mean"] - theirs[k]["error_mean"]) for k in common}
    largest = max(gaps.values(), default=0.0)
    return {
        "pairs_geofeat": len(ours["pairs"]),
        "pairs_official": len(theirs),
        "pairs_only_geofeat": sorted(set(ours["pairs"]) - set(theirs)),
        "pairs_only_official": sorted(set(theirs) - set(ours["pairs"])),
        "pairs_count_differs": count_differs,
        "pairs_error_differs": [k for k in common if gaps[k] > TOLERANCE],
        "largest_pair_difference": largest,
        "pooled_geofeat_x100": 100 * ours["pooled_error"],
        "pooled_official_x100": 100 * official["pooled_error"],
        "pooled_geofeat_own_protocol_x100": ours["pooled_default_x100"],
    }


def table(folder: Path) -> str:
    """``parity.md``: one row per ``parity_*.json`` in ``folder``."""
    results = [json.loads(p.read_text()) for p in sorted(folder.glob("parity_*.json"))]
    lines = [
        "geofeat's evaluation of the GeoLoRA paper's benchmarks (`geofeat.evaluation.paper_benchmarks`) beside the "
        "official dataset classes and `validation_partial_full` of the official release, on the same seeded random "
        f"maps; a pair differs when its evaluated points differ in number or its mean error by more than {TOLERANCE:g} "
        "(unscaled). The last column scores the same maps with geofeat's own protocol (every vertex with a counterpart "
        "once, errors over the square root of the target's area). `python -m benchmarks.parity.paper`; data and dates "
        "per row below.",
        "",
        "| benchmark | pairs (geofeat / official) | pairs that differ | largest per-pair difference | pooled x100, geofeat | "
        "pooled x100, official | geofeat's own protocol, same maps |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        c = r["comparison"]
        differ = len(set(c["pairs_count_differs"]) | set(c["pairs_error_differs"]))
        differ += len(c["pairs_only_geofeat"]) + len(c["pairs_only_official"])
        lines.append(
            f"| {r['title']} | {c['pairs_geofeat']} / {c['pairs_official']} | {differ} | {c['largest_pair_difference']:.1e} | "
            f"{c['pooled_geofeat_x100']:.6f} | {c['pooled_official_x100']:.6f} | "
            f"{c.get('pooled_geofeat_own_protocol_x100', float('nan')):.2f} |"
        )
    lines += ["", "Data and notes:", ""]
    lines += [f"- {r['title']}: {r['data_note']} ({r['date']}, {r['machine']})." for r in results]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("benchmark", nargs="?", choices=sorted(PAPER_BENCHMARKS))
    parser.add_argument("--data", help="the benchmark's test folder (what both sides are given)")
    parser.add_argument("--official-python", help="the Python of the official code's environment")
    parser.add_argument("--geo-lora", help="a copy of vikiehm/geo-lora (for the harness)")
    parser.add_argument("--official-arg", action="append", default=[], help="an argument passed on to the harness (repeatable)")
    parser.add_argument("--data-note", default="", help="where the data come from, for the table")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="writes OUT.json (default benchmarks/results/paper/parity_<benchmark>)")
    parser.add_argument("--table", metavar="FOLDER", help="only rebuild FOLDER/parity.md from the parity_*.json there")
    args = parser.parse_args(argv)
    if args.table:
        folder = Path(args.table)
        (folder / "parity.md").write_text(table(folder) + "\n")
        print(table(folder))
        return 0
    if not (args.benchmark and args.data and args.official_python and args.geo_lora):
        parser.error("a benchmark, --data, --official-python and --geo-lora are needed (or --table)")
    benchmark = paper_benchmark(args.benchmark)
    out = Path(args.out or RESULTS / "paper" / f"parity_{benchmark.name}")
    pairs = paper_pairs(benchmark, args.data)
    maps = random_maps(pairs, benchmark, args.seed)
    ours = geofeat_side(pairs, benchmark, maps)
    with tempfile.TemporaryDirectory() as tmp:
        np.savez(Path(tmp) / "predictions.npz", **maps)
        official = official_side(args, Path(args.data), Path(tmp) / "predictions.npz", Path(tmp) / "official.json")
    result = {
        "benchmark": benchmark.name,
        "title": benchmark.title,
        "data": str(args.data),
        "data_note": args.data_note or str(args.data),
        "seed": args.seed,
        "official_notes": official.get("notes", []),
        "error_expression": official.get("error_expression"),
        "comparison": compare(ours, official),
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_name(f"{out.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result["comparison"], indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
