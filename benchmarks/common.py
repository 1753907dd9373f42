"""Helpers shared by the benchmark scripts: the machine description, the FAUST_r shapes, writing results."""

from __future__ import annotations

import json
import os
from pathlib import Path

from machine_info import machine  # noqa: F401  (re-exported: the scripts take it from here)

import geofeat

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = os.environ.get("GEOFEAT_DATA", str(HERE.parent.parent / "shared" / "data"))


def faust_test_shapes(data: str | os.PathLike, n_shapes: int) -> list[geofeat.Mesh]:
    """The first ``n_shapes`` FAUST_r test shapes (tr_reg_080 on); exits with a clear message when missing."""
    folder = Path(data) / "FAUST_r" / "off"
    paths = [folder / f"tr_reg_{i:03d}.off" for i in range(80, 80 + n_shapes)]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise SystemExit(f"FAUST_r shapes not found (first missing: {missing[0]}); pass --data or set GEOFEAT_DATA")
    return [geofeat.load_mesh(p) for p in paths]


def write_results(out: str | os.PathLike, result: dict, table: str) -> None:
    """Write ``OUT.json`` (the result record) and ``OUT.md`` (its table), creating the folder; print the table."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(table + "\n")
    print(table)
