"""The depth-scan scripts: run.py on a scan benchmark, the scan pictures, the point-cloud geodesic comparison."""

import json
import subprocess
import sys

from shapes import REPO, bumpy

from benchmarks import cloud_geodesic

RUN = REPO / "benchmarks" / "run.py"


def test_run_matches_scans_to_full_shapes_and_reports_every_metric(tmp_path):
    for pipeline, descriptor in (("nn", "wks"), ("mirrored_truth", "none")):
        out = tmp_path / pipeline
        command = [sys.executable, str(RUN), "--no-progress", "--dataset", "synthetic_scans", "--limit", "1"]
        command += ["--pipeline", pipeline, "--descriptor", descriptor, "--out", str(out), "--workers", "1"]
        result = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
        assert result.returncode == 0, result.stderr
        report = json.loads((out / "results.json").read_text())
        assert report["dataset"] == "synthetic_scans" and report["n_pairs"] == 1
        assert all("_scan" in pair["pair"] for pair in report["pairs"])
        assert 0 <= report["miou"] <= 1 and (out / "pairs.png").read_bytes()[:4] == b"\x89PNG"
    assert report["chirality_accuracy"] == 0.0  # the mirrored truth


def test_scan_pictures_are_drawn(tmp_path):
    out = tmp_path / "scans.png"
    command = [
        sys.executable,
        "-m",
        "benchmarks.scan_pictures",
        "--dataset",
        "synthetic_scans",
        "--pairs",
        "2",
        "--out",
        str(out),
    ]
    result = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert out.read_bytes()[:4] == b"\x89PNG"


def test_the_cloud_comparison_measures_every_comparison_against_exact_geodesics():
    errors, info = cloud_geodesic.compare_shape(bumpy(0, 3), n_sources=3, seed=0)
    assert set(errors) == {key for key, _ in cloud_geodesic.COMPARISONS}
    assert all(values.size == 3 * (642 - 1) for values in errors.values())
    assert 0.9 < info["area_ratio"] < 1.1
    summaries = {key: cloud_geodesic.summary(values) for key, values in errors.items()}
    assert summaries["points_vs_exact"]["median"] < 0.05 and summaries["mesh_heat_vs_exact"]["median"] < 0.05
    result = {
        "n_shapes": 1,
        "n_points": 642,
        "n_sources": 3,
        "comparisons": summaries,
        "shapes": [info],
        "median_all_pairs_seconds": info["all_pairs_seconds"],
        "date": "2026-01-02",
        "machine": "a machine",
    }
    table = cloud_geodesic.table(result)
    assert table.count("\n| ") == len(cloud_geodesic.COMPARISONS) + 1 and "a machine" in table
