import argparse
import json
from pathlib import Path

from benchmarks.scans_vs_cuts import BENCHMARKS, plan, side_by_side


def test_plan_runs_both_benchmarks_alike_and_trains_the_head_first(tmp_path):
    args = argparse.Namespace(data=Path("/data"), seed=0, workers=2, pairs=40, train_minutes=3.0, out=tmp_path)
    runs = plan(args)
    for benchmark in BENCHMARKS:
        names = {r.name for r in runs if r.benchmark == benchmark}
        assert {"nn_wks", "nn_hks", "nn_shot", "fmap_wks", "fmap_hks", "fmap_shot", "random", "mirrored_truth"} <= names
    for run in runs:
        assert run.argv[run.argv.index("--limit") + 1] == "40" and run.argv[run.argv.index("--split") + 1] == "test"
    order = [f"{r.benchmark}/{r.name}" for r in runs]
    loaded = next(r for r in runs if "--load" in r.argv)
    assert loaded.benchmark == "faust_r_scans" and order.index(loaded.after) < order.index("faust_r_scans/" + loaded.name)
    assert loaded.argv[loaded.argv.index("--load") + 1] == str(tmp_path / loaded.after / "head")


def test_side_by_side_pairs_the_rows_of_both_benchmarks(tmp_path):
    for benchmark, error in (("faust_r_scans", 50.0), ("faust_r_cuts", 40.0)):
        for run, descriptor in (("nn_wks", "wks"), ("random", None)):
            folder = tmp_path / benchmark / run
            folder.mkdir(parents=True)
            record = {"pipeline": run.split("_")[0], "descriptor": descriptor, "n_pairs": 10, "geodesic_error": error,
                      "pck_auc": 0.1, "chirality_accuracy": 0.5, "seconds": 1.0, "date": "2026-11-27"}  # fmt: skip
            (folder / "results.json").write_text(json.dumps(record))
    rows = side_by_side(tmp_path)
    assert [r["label"] for r in rows] == ["nn + WKS", "random"]
    assert rows[0]["scans_error"] == 50.0 and rows[0]["cuts_error"] == 40.0
