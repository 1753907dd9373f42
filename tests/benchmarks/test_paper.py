"""The GeoLoRA paper's benchmarks: the official protocol's settings, its pairs on the shared samples, one command per row."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shapes import data_root

from geofeat.datasets.records import Match
from geofeat.errors import DatasetError
from geofeat.evaluation import evaluate_pair
from geofeat.evaluation.paper_benchmarks import PAPER_BENCHMARKS, ROTATE_X_90, framed, official_scale, paper_pairs
from geofeat.geometry.geodesic import area_normalisation

REPO = Path(__file__).resolve().parents[2]

#: config/test/<name>.yaml of the official release: its dataset and the LoRA file it names
OFFICIAL_CONFIGS = {
    "becos_p2f": "becos.pth",
    "becos_p2p": "becos.pth",
    "cp2p": "becos_without_shrec16.pth",
    "pfaust_hard": "faust.pth",
    "pfaust_medium": "faust.pth",
    "psmal": "smal.pth",
    "shrec16_cuts": "becos_without_shrec16.pth",
    "shrec16_holes": "becos_without_shrec16.pth",
}


def test_every_official_test_configuration_is_a_benchmark_with_its_lora_file():
    assert {name: b.lora for name, b in PAPER_BENCHMARKS.items()} == OFFICIAL_CONFIGS
    # raw geodesics where the official class passes normalize=False; BeCoS P2P by its recorded length
    assert {n for n, b in PAPER_BENCHMARKS.items() if b.distances == "raw"} == {"psmal", "shrec16_cuts", "shrec16_holes", "cp2p"}
    assert PAPER_BENCHMARKS["becos_p2p"].distances == "recorded"
    assert {n for n, b in PAPER_BENCHMARKS.items() if b.points == "template"} == {"pfaust_medium", "pfaust_hard"}


def test_official_scale_divides_as_the_official_code():
    from dataclasses import replace

    pair = paper_pairs("psmal", data_root() / "PSMAL_sample", split="train")[0]
    assert pair.error_scale == 1.0  # raw geodesics
    as_sqrt_area = official_scale(replace(pair, error_scale=3.0), PAPER_BENCHMARKS["becos_p2f"])
    assert as_sqrt_area.error_scale is None  # computed from x, not the recorded value
    with pytest.raises(DatasetError, match="recorded length"):
        official_scale(replace(pair, error_scale=None), PAPER_BENCHMARKS["becos_p2p"])
    # the same map: raw errors are the sqrt(area)-divided ones times sqrt(area(x))
    rng = np.random.default_rng(0)
    guess = Match(rng.integers(0, pair.x.n_vertices, pair.y.n_vertices), np.ones(pair.y.n_vertices, dtype=bool))
    raw = evaluate_pair(pair, guess).errors
    ours = evaluate_pair(replace(pair, error_scale=None), guess).errors
    np.testing.assert_allclose(raw * area_normalisation(pair.x), ours, rtol=1e-6)


def test_shrec16_pairs_turn_the_shapes_for_features_only():
    pairs = paper_pairs("shrec16_cuts", data_root() / "SHREC16_dpfm_sample")
    assert len(pairs) == 1 and pairs.pair_names == ["cuts-cat1->cuts-cat"]
    pair = pairs[0]
    turned = framed(pair.x, PAPER_BENCHMARKS["shrec16_cuts"])
    np.testing.assert_allclose(turned.verts, pair.x.verts @ np.asarray(ROTATE_X_90))
    np.testing.assert_array_equal(turned.faces, pair.x.faces)
    assert framed(pair.x, PAPER_BENCHMARKS["becos_p2f"]) is pair.x


def test_a_cuts_list_keeps_the_listed_shapes(tmp_path):
    root = data_root() / "SHREC16_dpfm_sample"
    (tmp_path / "list.txt").write_text("cuts-cat1.off\n")
    assert len(paper_pairs("shrec16_cuts", root, cuts_list=tmp_path / "list.txt")) == 1
    (tmp_path / "none.txt").write_text("cuts_dog_shape_3.off\n")
    with pytest.raises(DatasetError, match="names none"):
        paper_pairs("shrec16_cuts", root, cuts_list=tmp_path / "none.txt")
    with pytest.raises(DatasetError, match="CUTS only"):
        paper_pairs("psmal", data_root() / "PSMAL_sample", split="train", cuts_list=tmp_path / "list.txt")


def run_paper(tmp_path, *extra):
    command = [sys.executable, "-m", "benchmarks.tables.paper", "--random-weights", str(tmp_path / "weights")]
    command += ["--backbone", "tiny", "--views", "4", "--image-size", "64", "--device", "cpu", "--no-progress", *extra]
    done = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
    assert done.returncode == 0, done.stderr[-3000:]
    return done


def test_one_command_gives_the_rows_with_their_pair_counts_and_lists_the_benchmarks_without_data(tmp_path):
    out = tmp_path / "run"
    root = data_root() / "SHREC16_dpfm_sample"
    run_paper(tmp_path, "--data", f"shrec16={root}", "--out", str(out))
    result = json.loads((out / "paper.json").read_text())
    rows = {r["row"]: r for r in result["rows"]}
    assert set(rows) == {"shrec16_cuts/nn/dinov3", "shrec16_cuts/nn/geolora"}
    assert {(r["n_pairs"], r["n_shapes"]) for r in rows.values()} == {(1, 2)}
    # every partial vertex with a counterpart, once: the official count (gt != -1)
    pair = paper_pairs("shrec16_cuts", root)[0]
    assert {r["n_points"] for r in rows.values()} == {int((pair.map_yx >= 0).sum())}
    assert result["missing"] == ["becos_p2f", "pfaust_hard", "becos_p2p", "psmal"]
    table = (out / "paper.md").read_text()
    assert "| SHREC'16 CUTS P2F | nn/dinov3 | 1 |" in table and "errors mean nothing" in table
    assert "error x100 |" not in table  # random weights: no error column
    assert "- PSMAL P2P: https://github.com/vikiehm/gc-ppsm" in table  # where to get what is missing
    assert (out / "shrec16_cuts.json").is_file()
    again = run_paper(tmp_path, "--data", f"shrec16={root}", "--out", str(out))  # done rows are read back, not rerun
    assert "computed took" not in again.stderr


def test_a_saved_head_adds_its_rows_and_ulrssm_its_adapted_row(tmp_path):
    from geofeat.adapters.heads import make_head

    root = data_root() / "SHREC16_dpfm_sample"
    pair = paper_pairs("shrec16_cuts", root)[0]
    small = {"n_eig": 30, "diffusion_eig": 30, "n_fmap": 20, "width": 8, "width_out": 8, "n_blocks": 1}
    head = make_head("ulrssm", descriptor="wks", descriptor_params={"n_eig": 30}, epochs=1, progress=False, **small)
    head.fit([pair])
    head.save(tmp_path / "ulrssm")
    out = tmp_path / "run"
    run_paper(
        tmp_path,
        "--data",
        f"shrec16={root}",
        "--benchmarks",
        "shrec16_cuts",
        "--head",
        str(tmp_path / "ulrssm"),
        "--tta-steps",
        "1",
        "--out",
        str(out),
    )
    rows = {r["row"]: r for r in json.loads((out / "paper.json").read_text())["rows"]}
    assert {"shrec16_cuts/ulrssm/wks", "shrec16_cuts/ulrssm_tta/wks"} <= set(rows)
    assert rows["shrec16_cuts/ulrssm/wks"]["n_points"] == rows["shrec16_cuts/nn/dinov3"]["n_points"]
