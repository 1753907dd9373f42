import json
import subprocess
import sys
from pathlib import Path

import pytest
from shapes import REPO

from benchmarks.run import RUNS
from geofeat.apps import benchmark
from geofeat.errors import DescriptorError

RUN = REPO / "benchmarks" / "run.py"
SUMMARIZE = [sys.executable, "-m", "benchmarks.tables.summarize"]


def run(*args):
    return subprocess.run([sys.executable, str(RUN), "--no-progress", *args], capture_output=True, text=True, cwd=REPO)


MAIN_LABELS = [
    "nn + WKS",
    "nn + HKS",
    "fmap + WKS",
    "fmap + HKS",
    "nn + SHOT",
    "fmap + SHOT",
    "random",
    "mirrored_truth",
]
RESULT_NAMES = {"results.json", "results.md", "pck.png", "pairs.png"}


def result_files() -> dict:
    """The report files under benchmarks/results, with their size and modification time."""
    return {
        path: (path.stat().st_size, path.stat().st_mtime_ns)
        for path in (REPO / "benchmarks" / "results").rglob("*")
        if path.name in RESULT_NAMES and path.is_file()
    }


def test_main_job_compares_the_pipelines_with_the_references_on_full_and_partial_pairs(tmp_path, isolated_cache):
    before = result_files()
    result = run("--limit", "2", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert result_files() == before  # nothing written under benchmarks/results
    report = json.loads((tmp_path / "results.json").read_text())
    assert report["job"] == "main" and report["n_pairs"] == {"full": 2, "cuts": 2}
    assert report["descriptor_params"] == {"shot": {"radius": 0.5}}
    rows = {(row["kind"], row["label"]): row for row in report["rows"]}
    assert sorted(rows) == sorted((kind, label) for kind in ("full", "cuts") for label in MAIN_LABELS)
    for row in rows.values():
        assert row["n_pairs"] == len(row["pairs"]) == 2
        assert 0 < row["geodesic_error"] < 200 and 0 <= row["pck_auc"] <= 1
        assert row["pck_plot"] == sorted(row["pck_plot"]) and len(row["pck_plot"]) == len(report["pck_plot_thresholds"])
    for kind in ("full", "cuts"):
        assert rows[kind, "mirrored_truth"]["chirality_accuracy"] == 0.0
        assert (
            rows[kind, "random"]["descriptor"] == "none"
            and rows[kind, "nn + WKS"]["descriptor"] == "wks"
            and rows[kind, "fmap + SHOT"]["descriptor"] == "shot"
        )
    cut_sources = [p["pair"].split("->")[0] for p in rows["cuts", "nn + WKS"]["pairs"]]
    full_sources = [p["pair"].split("->")[0] for p in rows["full", "nn + WKS"]["pairs"]]
    assert [name.rsplit("_cuts", 1)[0] for name in cut_sources] == full_sources  # the same shapes, cut
    # the markdown fragment: reading guide, table (a row per pipeline and kind), date and machine; no heading
    markdown = (tmp_path / "results.md").read_text()
    assert not markdown.startswith("#") and "`random` is chance level" in markdown
    assert markdown.count("| full-to-full |") == markdown.count("| CUTS partial-to-full |") == len(MAIN_LABELS)
    assert report["date"] in markdown and "cores" in markdown
    for picture in ("pck.png", "pairs.png"):
        assert (tmp_path / picture).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the screen says how to read the table, where the results went and where the caches are
    assert "`random` is chance level" in result.stdout and f"Results: {tmp_path}" in result.stdout
    assert str(isolated_cache / "features") in result.stdout and str(isolated_cache / "geodesics") in result.stdout
    # the geodesic matrix of the one target is kept
    assert len(list((isolated_cache / "geodesics").glob("*-float32-*.npy"))) == 1


def test_runs_write_into_the_ignored_runs_folder_by_default():
    assert RUNS == REPO / "runs"  # what benchmarks/run.py gives the command
    assert benchmark.output_folder(benchmark.parse_args([]), RUNS) == REPO / "runs" / "main"
    assert benchmark.output_folder(benchmark.parse_args(["--limit", "3", "--workers", "1"]), RUNS) == REPO / "runs" / "main"
    one = benchmark.parse_args(["--pipeline", "fmap"])
    assert not one.main_job and (one.dataset, one.descriptor) == ("synthetic_cuts", "wks")
    assert benchmark.output_folder(one, RUNS) == REPO / "runs" / "fmap_synthetic_cuts_wks"
    assert benchmark.parse_args(["--param", "n_descr=16"]).main_job is False
    assert benchmark.output_folder(benchmark.parse_args(["--out", "elsewhere"]), RUNS) == Path("elsewhere")
    ignored = subprocess.run(["git", "check-ignore", "-q", "runs/main/results.json"], cwd=REPO)
    assert ignored.returncode == 0, "runs/ must be ignored by git"


def test_single_pipeline_run_writes_every_report(tmp_path, isolated_cache):
    result = run("--pipeline", "nn", "--limit", "2", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "results.json").read_text())
    for key in ("pipeline", "dataset", "descriptor", "n_pairs", "geodesic_error", "pck_auc", "chirality_accuracy"):
        assert key in report
    assert (report["pipeline"], report["dataset"], report["descriptor"], report["n_pairs"]) == ("nn", "synthetic_cuts", "wks", 2)
    assert 0 < report["geodesic_error"] < 200 and 0 <= report["pck_auc"] <= 1
    assert "| nn | wks | synthetic_cuts | 2 |" in (tmp_path / "results.md").read_text()
    for picture in ("pck.png", "pairs.png"):
        assert (tmp_path / picture).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the targets' geodesic matrices are kept in the cache folder ($GEOFEAT_CACHE_DIR/geodesics)
    assert len(list((isolated_cache / "geodesics").glob("*-float32-*.npy"))) == len(
        {p["pair"].split("->")[1] for p in report["pairs"]}
    )


def test_p2p_run_reports_miou(tmp_path):
    result = run(
        "--dataset", "synthetic_p2p", "--pipeline", "fmap", "--descriptor", "hks", "--limit", "1", "--out", str(tmp_path)
    )
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "results.json").read_text())
    assert 0 < report["miou"] <= 1 and report["pairs"][0]["iou"] == report["miou"]


def test_clear_errors_for_bad_names_and_missing_data(tmp_path):
    result = run("--dataset", "faust_r_cutz", "--out", str(tmp_path))
    assert result.returncode == 2 and "Did you mean 'faust_r_cuts'" in result.stderr
    result = run("--descriptor", "dinov9", "--out", str(tmp_path))
    assert result.returncode == 2 and "unknown descriptor 'dinov9'" in result.stderr
    result = run("--dataset", "faust_r_cuts", "--data-root", str(tmp_path / "nowhere"), "--out", str(tmp_path))
    assert result.returncode == 2 and "off/" in result.stderr and "corres/" in result.stderr


def test_reference_pipelines_bracket_the_metrics(tmp_path):
    for pipeline in ("random", "mirrored_truth"):
        result = run("--pipeline", pipeline, "--limit", "2", "--out", str(tmp_path / pipeline))
        assert result.returncode == 0, result.stderr
    random = json.loads((tmp_path / "random" / "results.json").read_text())
    mirrored = json.loads((tmp_path / "mirrored_truth" / "results.json").read_text())
    assert random["descriptor"] == "none"
    assert mirrored["chirality_accuracy"] == 0.0 and 0.3 < random["chirality_accuracy"] < 0.7
    assert mirrored["geodesic_error"] < random["geodesic_error"]


def test_descriptor_parameters_reach_the_descriptor(tmp_path):
    result = run("--limit", "1", "--param", "n_descr=16", "--param", "n_eig=32", "--out", str(tmp_path))
    assert result.returncode == 0, result.stderr
    assert json.loads((tmp_path / "results.json").read_text())["descriptor_params"] == {"n_descr": 16, "n_eig": 32}
    bad = run("--limit", "1", "--param", "colour=red", "--out", str(tmp_path / "bad"))
    assert bad.returncode == 2 and "unknown parameter(s) ['colour']" in bad.stderr


def test_key_value_options_refuse_a_key_given_twice(tmp_path):
    assert benchmark.descriptor_params(["n_descr=16", "laplacian=cotan"]) == {"n_descr": 16, "laplacian": "cotan"}
    with pytest.raises(DescriptorError, match=r"--head-param lr is given twice"):
        benchmark.descriptor_params(["lr=0.1", "lr=0.2"], what="--head-param")
    result = run("--limit", "1", "--param", "n_descr=16", "--param", "n_descr=8", "--out", str(tmp_path))
    assert result.returncode == 2 and "--param n_descr is given twice (16 and '8')" in result.stderr


def test_results_json_is_written_atomically(tmp_path, monkeypatch, isolated_cache):
    written = []
    real = benchmark.atomic_write

    def recording(path, write, **kwargs):
        written.append(Path(path))
        return real(path, write, **kwargs)

    monkeypatch.setattr(benchmark, "atomic_write", recording)
    assert benchmark.main(["--pipeline", "random", "--limit", "1", "--no-progress", "--out", str(tmp_path)]) == 0
    assert tmp_path / "results.json" in written
    assert json.loads((tmp_path / "results.json").read_text())["pipeline"] == "random"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temporary file left


@pytest.mark.parametrize(
    "pipeline, dataset", [("ulrssm", "synthetic_cuts"), ("dpfm", "synthetic_p2p"), ("echomatch", "synthetic_p2p")]
)
def test_quick_learned_heads_train_evaluate_and_reload(pipeline, dataset, tmp_path):
    result = run("--pipeline", pipeline, "--dataset", dataset, "--quick", "--out", str(tmp_path / "a"))
    assert result.returncode == 0, result.stderr
    report = json.loads((tmp_path / "a" / "results.json").read_text())
    assert report["head"]["name"] == pipeline and report["train_pairs"] == 3 and report["train_steps"] >= 1
    assert report["n_pairs"] == 2 and 0 <= report["geodesic_error"] < 200
    if dataset.endswith("p2p"):
        assert 0 <= report["miou"] <= 1
    again = run(
        "--pipeline",
        pipeline,
        "--dataset",
        dataset,
        "--quick",
        "--load",
        str(tmp_path / "a" / "head"),
        "--out",
        str(tmp_path / "b"),
    )
    assert again.returncode == 0, again.stderr
    reloaded = json.loads((tmp_path / "b" / "results.json").read_text())
    assert reloaded["loaded_from"] == str(tmp_path / "a" / "head")
    assert reloaded["train_steps"] == report["train_steps"] and reloaded["train_losses"] == report["train_losses"]
    assert reloaded["geodesic_error"] == pytest.approx(report["geodesic_error"])


def test_summary_tells_the_test_time_adaptation_apart(tmp_path):
    curve = {"pck_thresholds": [0.0, 0.25], "pck": [0.1, 0.9]}
    base = {"dataset": "faust_r_cuts", "descriptor": "wks", "date": "2026-11-21", "n_pairs": 2, "geodesic_error": 50.0}
    runs = {
        "nn": {**base, "pipeline": "nn", "head": None},
        "tta": {**base, "pipeline": "ulrssm", "train_steps": 12, "head": {"config": {"tta_steps": 5}}},
        "notta": {**base, "pipeline": "ulrssm", "train_steps": 12, "head": {"config": {"tta_steps": 0}}},
    }
    paths = []
    for name, row in runs.items():
        paths.append(tmp_path / f"{name}.json")
        paths[-1].write_text(json.dumps({**row, **curve}))
    result = subprocess.run(
        [*SUMMARIZE, *map(str, paths), "--out", str(tmp_path / "summary")], capture_output=True, text=True, cwd=REPO
    )
    assert result.returncode == 0, result.stderr
    rows = [line for line in (tmp_path / "summary.md").read_text().splitlines() if line.startswith("| faust_r_cuts")]
    # the accuracy table, then the training steps (the only other column a run fills)
    assert rows[0] == "| faust_r_cuts | wks | nn | 2 | 50.00 | - | - |"
    assert "| ulrssm, TTA 5 | 2 |" in rows[1] and "| ulrssm, no TTA | 2 |" in rows[2]
    assert rows[3:] == [
        "| faust_r_cuts | wks | nn | - |",
        "| faust_r_cuts | wks | ulrssm, TTA 5 | 12 |",
        "| faust_r_cuts | wks | ulrssm, no TTA | 12 |",
    ]


def test_summary_skips_the_results_of_other_scripts_and_refuses_when_none_is_a_run(tmp_path):
    run_record = {
        "pipeline": "nn",
        "dataset": "faust_r",
        "descriptor": "wks",
        "date": "2026-11-24",
        "n_pairs": 1,
        "geodesic_error": 25.0,
        "pck_thresholds": [0.0, 0.25],
        "pck": [0.2, 0.8],
        "head": None,
    }
    (tmp_path / "run.json").write_text(json.dumps(run_record))
    (tmp_path / "speed.json").write_text(json.dumps({"machine": "x", "rows": []}))  # e.g. speed/extract.py's results.json

    def summarize(*names):
        paths = [str(tmp_path / name) for name in names]
        return subprocess.run([*SUMMARIZE, *paths, "--out", str(tmp_path / "summary")], capture_output=True, text=True, cwd=REPO)

    result = summarize("speed.json", "run.json")
    assert result.returncode == 0, result.stderr
    assert "skipping" in result.stderr and "speed.json" in result.stderr
    rows = [line for line in (tmp_path / "summary.md").read_text().splitlines() if line.startswith("| faust_r")]
    assert len(rows) == 1 and rows[0].startswith("| faust_r | wks | nn | 1 | 25.00 |")
    refused = summarize("speed.json")
    assert refused.returncode == 2 and "none of the files is a results.json of benchmarks/run.py" in refused.stderr
