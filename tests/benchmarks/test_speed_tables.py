"""The tables of the eigensolver speed scripts, written from records of known content."""

import json

from benchmarks.speed import diffusion_net_operators, large_mesh


def _operator_row(dataset, shape, vertices, reference, ours, before, rows_apart=0):
    agreement = {
        "solver_eigenvalues_relative_each": 1e-13,
        "solver_eigenspace_sine": 1e-8,
        "gradient_rows_apart": rows_apart,
        "laplacian": 1e-5,
        "mass": 5e-8,
        "eigenvalues_relative_each": 2e-6,
        "eigenspace_sine": 1e-4,
        "grad_x": 0.5 if rows_apart else 0.0,
        "grad_y": 0.0,
    }
    return {
        "dataset": dataset,
        "shape": shape,
        "vertices": vertices,
        "reference": reference,
        "defaults": ours,
        "ARPACK, SuperLU, 2k+1 vectors": before,
        "agreement": agreement,
    }


def test_operator_table_gives_median_ratios_and_names_the_rows_apart():
    record = {
        "date": "2026-01-02",
        "machine": "test machine",
        "cholmod": False,
        "rows": [
            _operator_row("FAUST_r", "a", 5000, 0.6, 0.2, 0.3),
            _operator_row("FAUST_r", "b", 5000, 0.8, 0.4, 0.5),
            _operator_row("FAUST_r", "c", 5000, 1.0, 0.25, 0.4),
            _operator_row("PSMAL", "cow", 2700, 0.4, 0.1, 0.2, rows_apart=1),
        ],
    }
    text = diffusion_net_operators.table(record)
    assert "test machine, 2026-01-02; CHOLMOD not installed" in text
    assert "| FAUST_r (3) | 5000 | 0.80 s | 0.25 s | 3.20x | 0.40 s |" in text
    assert "| PSMAL (1) | 2700 | 0.40 s | 0.10 s | 4.00x | 0.20 s |" in text
    assert "Gradient rows more than 0.001 apart: cow (1 of 2700);" in text
    assert "eigenvalues to 1.0e-13 (relative)" in text


def test_large_mesh_table_gives_the_ratio_only_where_both_ran(tmp_path):
    ok = {"seconds": 2.0, "peak_gb": 0.5}
    record = {
        "date": "2026-01-02",
        "machine": "test machine",
        "rows": [
            {"vertices": 20001, "zero_area_faces": 0, "robust": ok, "cotan": ok, "pyfm": {"seconds": 5.0, "peak_gb": 0.5}},
            {"vertices": 200000, "zero_area_faces": 3, "robust": ok, "cotan": {"seconds": None, "error": "x.SpectralError: no"}},
        ],
    }
    (tmp_path / "results.json").write_text(json.dumps(record))
    text = large_mesh.write_table(tmp_path)
    assert "| 20001 | 0 | 2.0 s / 0.50 GB | 2.0 s / 0.50 GB | 5.0 s / 0.50 GB | 2.50x |" in text
    assert "| 200000 | 3 | 2.0 s / 0.50 GB | SpectralError (see results.json) | - | - |" in text
    assert (tmp_path / "results.md").read_text() == text
