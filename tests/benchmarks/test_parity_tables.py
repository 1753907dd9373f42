"""The parity tables of benchmarks/parity/shot.py and ray_reference.py, rendered from made-up records."""

import markdown_tables as md

from benchmarks.parity.shot import table

ROW = {
    "shape": "FAUST_r tr_reg_080",
    "params": "dsmk",
    "vertices": 5000,
    "max_abs": 0.3,
    "max_abs_without_ties": 3e-7,
    "max_abs_reference": 0.62,
    "share_over_tol": 0.0002,
    "over_tol_without_ties": 0,
    "sign_ties": 4,
    "ties_over_tol": 1,
    "ties_over_tol_flipped": 0,
    "nan_rows_reference": 0,
    "zero_rows_ours": 0,
    "zero_rows_reference": 0,
    "seconds_ours": 0.67,
    "seconds_reference": 1.73,
}


def test_shot_parity_is_two_narrow_tables_under_the_date_and_machine():
    record = {"date": "2026-01-02T10:00:00+00:00", "machine": "box C", "tolerance": 1e-5, "rows": [ROW, {**ROW, "params": "x"}]}
    text = table(record)
    assert text.splitlines()[0].startswith("Run of 2026-01-02, box C;")
    tables = md.tables(text)
    assert len(tables) == 2
    for lines in tables:
        assert lines[0].count("|") - 1 <= 7
        assert lines[0].startswith("| shape | parameters |")
        assert len(lines) == 2 + 2
    assert tables[1][2].endswith("| 0.67 / 1.73 |")


def test_shot_parity_without_a_machine_gives_the_date_alone():
    text = table({"date": "2026-01-02T10:00:00+00:00", "tolerance": 1e-5, "rows": [ROW]})
    assert text.splitlines()[0].startswith("Run of 2026-01-02;")
    assert "not recorded" not in text


def test_ray_parity_tables_are_narrow_under_the_date_and_machine():
    from benchmarks.parity.ray_reference import table as ray_table

    stats = {"mean": 0.5, "p10": 0.1, "p90": 0.9}
    shape = {
        "shape": "FAUST_r tr_reg_080",
        "n_vertices": 5000,
        "scale": 1.0,
        "draws": 3,
        "eyes_equal": 3,
        "identical": 2,
        "same_hits": 2,
        "differing": 1,
        "reasons": {"hit triangles differ": 1},
        "differing_rays_by_cause": {"grazes an edge or vertex": 2},
        "draws_crossing_camera_plane": 0,
        "draws_with_filled_holes": 3,
        "draws_with_repeated_filled_triangle": 0,
        "duplicate_positions": 0,
        "draws_gt_differs_from_source_index": 0,
        "vertices_gt_differs_from_source_index": 0,
        "distributions": {"official": {"keep": stats, "boundary": stats, "components": stats}},
    }
    speed = {"shape": "tr_reg_080", "repeats": 5, "official_median_s": 0.1, "reference_median_s": 0.2}
    speed["official_versions"] = {"open3d": "0", "trimesh": "0"}
    text = ray_table({"date": "2026-01-02", "machine": "box E", "seed": 0, "shapes": [shape], "speed": speed})
    assert text.index("2026-01-02; box E.") < text.index("| shape |")
    tables = md.tables(text)
    assert len(tables) == 3
    assert all(lines[0].count("|") - 1 <= 7 and lines[0].startswith("| shape |") for lines in tables)
    assert "| FAUST_r tr_reg_080 | 2 | 2 | 1 | hit triangles differ: 1 |" in text
    assert text.endswith("geofeat reference 200 ms.")  # no load average in this record
