"""The table scripts of the docs: tables/release.py and tables/summarize.py's machine line, on small made-up records."""

import argparse
import json
import subprocess
import sys

import markdown_tables as md
from shapes import REPO

RELEASE_TABLE = [sys.executable, "-m", "benchmarks.tables.release"]
SUMMARIZE = [sys.executable, "-m", "benchmarks.tables.summarize"]


def _run_record(checkpoint, dataset, errors, tta=0, protocol="template", n_evaluated=None, pipeline="ulrssm"):
    """A results.json of run.py --checkpoint with per-pair errors (equal weights unless n_evaluated is given)."""
    n_evaluated = n_evaluated or [5000] * len(errors)
    pooled = sum(e * n for e, n in zip(errors, n_evaluated, strict=True)) / sum(n_evaluated)
    return {
        "pipeline": pipeline,
        "dataset": dataset,
        "descriptor": "wks",
        "date": "2026-01-02",
        "pairs_option": "combinations",
        "protocol": protocol,
        "release_checkpoint": f"/somewhere/{checkpoint}",
        "head": {"name": pipeline, "config": {"tta_steps": tta, "interpolation": "reference"}},
        "n_pairs": len(errors),
        "geodesic_error": pooled,
        "pck_auc": 0.9,
        "chirality_accuracy": 0.98,
        "pairs": [
            {"pair": f"p{i}", "geodesic_error": e, "n_evaluated": n}
            for i, (e, n) in enumerate(zip(errors, n_evaluated, strict=True))
        ],
    }


def _results_tree(tmp_path, reference_pairs=3):
    release = tmp_path / "release"
    for name, record in {
        "ulrssm_faust_r": _run_record("faust_scape.pth", "faust_r", [1.0, 2.0, 3.0]),
        "ulrssm_tta_faust_r": _run_record("faust_scape.pth", "faust_r", [0.5, 1.5], tta=15),
        "ulrssm_cuts": _run_record("shrec16_cuts.pth", "faust_r_cuts", [10.0, 40.0], protocol="vertices"),
        "ulrssm_cuts_tta": _run_record("shrec16_cuts.pth", "faust_r_cuts", [5.0], tta=15, protocol="vertices", n_evaluated=[100]),
    }.items():
        (release / name).mkdir(parents=True)
        (release / name / "results.json").write_text(json.dumps(record))
    published = [
        {"head": "ulrssm", "checkpoint": "faust_scape.pth", "dataset": "faust_r", "published": "about 2", "cite": "paper"},
    ]
    (release / "published_figures.json").write_text(json.dumps(published))
    (tmp_path / "swap_in").mkdir()
    swap_in = {
        "checkpoint": "/elsewhere/faust_scape.pth",
        "x_before_y": {"pairs": reference_pairs, "error_own_x100": 2.001},
        "machine": "test machine",
        "date": "2026-01-03",
        "complete": True,
    }
    (tmp_path / "swap_in" / "results.json").write_text(json.dumps(swap_in))
    return release


def _release_table(tmp_path):
    return subprocess.run([*RELEASE_TABLE, "--results", str(tmp_path)], capture_output=True, text=True, cwd=REPO)


def test_release_summary_puts_the_reference_beside_geofeat(tmp_path):
    release = _results_tree(tmp_path)
    result = _release_table(tmp_path)
    assert result.returncode == 0, result.stderr
    summary = (release / "summary.md").read_text().splitlines()
    rows = [line for line in summary if line.startswith("| ULRSSM")]
    # one row per reproduced checkpoint: no TTA row, no transfer checkpoint (no published figure on that data)
    assert rows == ["| ULRSSM `faust_scape.pth` | faust_r | 3 | 2.000 | 2.001 | about 2 |"]
    text = "\n".join(summary)
    assert "Authors' code: `benchmarks/swap_in.py` (ULRSSM), 2026-01-03, test machine." in text
    # the run.py records above hold no machine: their date alone, and nothing the site's checks refuse
    assert "geofeat: `benchmarks/run.py --checkpoint`, 2026-01-02." in text
    assert "not recorded" not in text
    # the dates and machines come before the table
    assert text.index("2026-01-03, test machine") < text.index("| checkpoint |")


def test_release_details_give_the_same_pairs_without_tta_pooled_over_vertices(tmp_path):
    release = _results_tree(tmp_path)
    assert _release_table(tmp_path).returncode == 0
    details = (release / "details.md").read_text().splitlines()
    tta_full = next(line for line in details if "faust_scape.pth" in line and "15 test-time" in line)
    # pairs p0, p1 of the plain run: (1.0 + 2.0) / 2 with equal weights
    assert "| first 2 of 3 | 1.00 | 1.50 |" in tta_full
    tta_cuts = next(line for line in details if "shrec16_cuts.pth" in line and "15 test-time" in line)
    # pair p0 of the plain run alone (the TTA run has one pair): 10.0
    assert "| first 1 of 2 | 5.00 | 10.00 |" in tta_cuts


def test_release_details_are_two_narrow_tables_under_their_dates_and_machines(tmp_path):
    release = _results_tree(tmp_path)
    machined = json.loads((release / "ulrssm_faust_r" / "results.json").read_text())
    (release / "ulrssm_faust_r" / "results.json").write_text(json.dumps({**machined, "machine": "box B", "date": "2026-01-05"}))
    assert _release_table(tmp_path).returncode == 0
    text = (release / "details.md").read_text()
    tables = md.tables(text)
    assert len(tables) == 2
    assert all(md.columns(t[0]) <= 7 for t in tables)
    for table in tables:  # the same key columns and rows in both
        assert table[0].startswith("| checkpoint | setting | benchmark |")
        assert len(table) == 2 + 4
    first_line = text.splitlines()[0]
    assert "2026-01-05 on box B (1 run)" in first_line
    assert "2026-01-02 (3 runs)" in first_line
    assert "not recorded" not in text
    assert text.index(first_line) < text.index("| checkpoint |")


def test_release_summary_refuses_a_reference_on_other_pairs(tmp_path):
    release = _results_tree(tmp_path, reference_pairs=190)
    result = _release_table(tmp_path)
    assert result.returncode == 0, result.stderr
    assert "on other pairs" in result.stderr
    row = next(line for line in (release / "summary.md").read_text().splitlines() if line.startswith("| ULRSSM"))
    assert row.endswith("| 2.000 | - | about 2 |")


def test_summarize_states_the_machines_the_runs_recorded(tmp_path):
    base = {"dataset": "faust_r", "descriptor": "wks", "date": "2026-01-02", "n_pairs": 1, "geodesic_error": 25.0}
    curve = {"pck_thresholds": [0.0, 0.25], "pck": [0.2, 0.8], "head": None}
    (tmp_path / "a.json").write_text(json.dumps({**base, **curve, "pipeline": "nn", "machine": "box A"}))
    (tmp_path / "b.json").write_text(json.dumps({**base, **curve, "pipeline": "fmap"}))
    result = subprocess.run(
        [*SUMMARIZE, str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--out", str(tmp_path / "s")],
        capture_output=True,
        text=True,
        cwd=REPO,
    )
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "s.md").read_text()
    assert "Machine: box A (1 of the 2 runs recorded none)." in text
    assert text.index("Machine: box A") < text.index("| dataset |")


def test_summarize_writes_two_narrow_tables_without_empty_columns(tmp_path):
    curve = {"pck_thresholds": [0.0, 0.25], "pck": [0.2, 0.8], "head": None}
    base = {"dataset": "faust_r", "descriptor": "wks", "date": "2026-01-02", "n_pairs": 1, "geodesic_error": 25.0, **curve}
    full = {
        **base,
        "pck_auc": 0.5,
        "miou": 0.7,
        "overlap_auc": 0.6,
        "chirality_accuracy": 0.9,
        "train_steps": 10,
        "seconds": 3.0,
    }
    (tmp_path / "a.json").write_text(json.dumps({**full, "pipeline": "dpfm"}))
    (tmp_path / "b.json").write_text(json.dumps({**base, "pipeline": "nn", "seconds": 1.0}))
    command = [*SUMMARIZE, str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--out", str(tmp_path / "s"), "--tables-only"]
    result = subprocess.run(command, capture_output=True, text=True, cwd=REPO)
    assert result.returncode == 0, result.stderr
    text = (tmp_path / "s.md").read_text()
    assert text.splitlines()[0] == "Runs of 2026-01-02; per-run settings in each results.json."
    tables = md.tables(text)
    assert [md.columns(t[0]) for t in tables] == [7, 7]
    assert all(t[0].startswith("| dataset | descriptor | matcher |") for t in tables)
    assert not list(tmp_path.glob("*.png"))  # --tables-only draws no plot
    # without the head run, the mIoU, overlap AUC and training steps columns are empty and left out
    command = [*SUMMARIZE, str(tmp_path / "b.json"), "--out", str(tmp_path / "t"), "--tables-only"]
    assert subprocess.run(command, capture_output=True, text=True, cwd=REPO).returncode == 0
    second = md.tables((tmp_path / "t.md").read_text())[1]
    assert second[0] == "| dataset | descriptor | matcher | time (s) |"


REAL_FILES = [sys.executable, "-m", "benchmarks.real_files"]


def test_real_files_tables_list_each_published_source_once_under_its_rows(tmp_path):
    run = tmp_path / "psmal" / "nn_wks"
    run.mkdir(parents=True)
    record = {
        "pipeline": "nn",
        "descriptor": "wks",
        "split": "test",
        "date": "2026-01-02",
        "n_pairs": 2,
        "geodesic_error": 12.5,
        "pck_auc": 0.4,
        "pck_thresholds": [0.0, 0.1, 0.2],
        "pck": [0.0, 0.5, 1.0],
        "pairs": [],
    }
    (run / "results.json").write_text(json.dumps(record))
    figure = {"metric": "error", "benchmark": "PSMAL P2P"}
    published = [
        figure | {"method": "A", "published": "1.0", "source": "paper one", "benchmarks": {"psmal": "differs a"}},
        figure | {"method": "B", "published": "2.0", "source": "paper two", "benchmarks": {"psmal": "differs b"}},
        figure | {"method": "C", "published": "3.0", "source": "paper one", "benchmarks": {"psmal": "differs c"}},
        figure | {"method": "D", "published": "4.0", "source": "paper three", "benchmarks": {"becos_p2p": "x"}},
    ]
    (tmp_path / "published_figures.json").write_text(json.dumps(published))

    done = subprocess.run(
        [*REAL_FILES, "--tables-only", "--out", str(tmp_path)],
        capture_output=True,
        text=True,
        check=False,
        cwd=REPO,
    )

    assert done.returncode == 0, done.stderr
    text = (tmp_path / "psmal.md").read_text()
    assert "| nn | WKS | 2 | 12.50 |" in text
    assert "| A | PSMAL P2P | error | 1.0 | [1] | differs a |" in text
    assert "| B | PSMAL P2P | error | 2.0 | [2] | differs b |" in text
    assert "| C | PSMAL P2P | error | 3.0 | [1] | differs c |" in text
    assert text.count("\\[1\\] paper one") == 1 and text.count("\\[2\\] paper two") == 1  # escaped: not a reference link
    assert "paper three" not in text and "| D |" not in text
    assert not (tmp_path / "becos_p2p.md").exists()


def test_real_files_tables_are_narrow_and_dated_above(tmp_path):
    common = {"descriptor": "wks", "split": "test", "n_pairs": 2, "geodesic_error": 12.5, "pck_auc": 0.4}
    common |= {"pck_thresholds": [0.0, 0.1], "pck": [0.0, 1.0], "pairs": [], "miou": 0.5}
    records = {
        "nn_wks": {**common, "pipeline": "nn", "date": "2026-01-02", "machine": "box D"},
        "dpfm": {**common, "pipeline": "dpfm", "date": "2026-01-03", "machine": "box D", "overlap_auc": 0.6}
        | {"train_steps": 10, "train_pairs": 5, "train_seconds": 60.0},
    }
    for name, record in records.items():
        (tmp_path / "psmal" / name).mkdir(parents=True)
        (tmp_path / "psmal" / name / "results.json").write_text(json.dumps(record))
    command = [*REAL_FILES, "--tables-only", "--no-plots", "--out", str(tmp_path)]
    done = subprocess.run(command, capture_output=True, text=True, check=False, cwd=REPO)
    assert done.returncode == 0, done.stderr
    text = (tmp_path / "psmal.md").read_text()
    assert "Runs of 2026-01-02, 2026-01-03; box D." in text
    tables = md.tables(text)
    assert len(tables) == 2
    assert all(md.columns(t[0]) <= 7 and t[0].startswith("| pipeline | input |") for t in tables)
    assert text.index("Runs of") < text.index("| pipeline |")
    assert "| DPFM | WKS | 0.500 | 0.600 | 10 steps (2.0 passes) on 5 pairs of train, 1.0 min |" in text
    assert not list(tmp_path.glob("*.png"))  # --no-plots


def test_real_files_plan_runs_shot_with_its_radius_on_becos(tmp_path):
    from benchmarks.real_files import plan

    args = argparse.Namespace(
        psmal=tmp_path,
        psmal_sample=None,
        becos=tmp_path,
        shrec16=None,
        ulrssm_checkpoint=None,
        seed=0,
        workers=1,
        only=None,
        train_minutes=1.0,
        tta_pairs=0,
        out=tmp_path,
    )
    runs = {(r.benchmark, r.name): r.argv for r in plan(args)}
    for bench, radius in (("becos_p2f", 0.5), ("becos_p2p", 0.5), ("psmal", 0.3)):
        for pipeline in ("nn", "fmap"):
            argv = runs[bench, f"{pipeline}_shot"]
            assert argv[:6] == ("--pipeline", pipeline, "--descriptor", "shot", "--param", f"radius={radius}")
        assert runs[bench, "nn_wks"][:4] == ("--pipeline", "nn", "--descriptor", "wks")
