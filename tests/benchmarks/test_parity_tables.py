"""The SHOT parity table of benchmarks/parity/shot.py, rendered from a made-up record."""

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


def _tables(text: str) -> list[list[str]]:
    tables, current = [], []
    for line in text.splitlines() + [""]:
        if line.startswith("|"):
            current.append(line)
        elif current:
            tables.append(current)
            current = []
    return tables


def test_shot_parity_is_two_narrow_tables_under_the_date_and_machine():
    record = {"date": "2026-01-02T10:00:00+00:00", "machine": "box C", "tolerance": 1e-5, "rows": [ROW, {**ROW, "params": "x"}]}
    text = table(record)
    assert text.splitlines()[0].startswith("Run of 2026-01-02, box C;")
    tables = _tables(text)
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
