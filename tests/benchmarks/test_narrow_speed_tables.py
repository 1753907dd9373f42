"""The speed tables split to at most seven columns, rendered from made-up records."""

import json

import markdown_tables as md

from benchmarks.speed import dino, dsmk_ulrssm, geodesic_memory, geolora, heads, point_clouds

MACHINE = "test machine, 2 cores"


def _narrow(text: str, key: str, parts: int, rows: int) -> list[list[str]]:
    tables = md.tables(text)
    assert len(tables) == parts
    for lines in tables:
        assert md.columns(lines[0]) <= 7
        assert lines[0].startswith(key)
        assert len(lines) == 2 + rows
        assert all(md.columns(line) == md.columns(lines[0]) for line in lines)
    return tables


def test_heads_table_is_two_narrow_tables_under_device_and_date():
    row = {
        "head": "ulrssm",
        "dataset": "faust_r",
        "preset": "reference",
        "steps": 8,
        "seconds": 0.4,
        "steps_per_second": 20.0,
        "first_pass_seconds": 10.9,
        "parameters": 510336,
        "peak_cuda_memory_gib": None,
    }
    record = {"date": "2026-01-02", "machine": MACHINE, "device": "cpu", "rows": [row, {**row, "head": "dpfm"}]}
    text = heads.table(record)
    assert text.splitlines()[0].endswith(f"device cpu ({MACHINE}), 2026-01-02")
    tables = _narrow(text, "| head |", 2, 2)
    assert tables[0][2] == "| ulrssm | reference | faust_r | 8 | 20.00 |"
    assert tables[1][2] == "| ulrssm | 10.9 s | 510,336 | - |"


def test_dsmk_table_is_two_narrow_tables_under_device_and_date():
    timing = {"iterations": 20, "median_ms": 80.0, "mean_ms": 80.0, "min_ms": 70.0, "max_ms": 90.0}
    record = {
        "date": "2026-01-02",
        "machine": MACHINE,
        "gpu": "GPU model X",
        "device": "cuda",
        "dsmk_commit": "0123456789abcdef",
        "options": "options.yaml",
        "shapes": 5,
        "vertices": [4999, 5001],
        "setting": {"batch_size": 1},
        "step": timing,
        "loader": {**timing, "mean_ms": 100.0},
        "peak_cuda_memory_gib": 1.25,
        "parameters": 510336,
        "warmup_iterations": 3,
        "preprocessing_seconds": 4.3,
        "operators_computed": 5,
        "stand_ins": [],
    }
    text = dsmk_ulrssm.table(record)
    assert text.splitlines()[0].endswith("device cuda (GPU model X), 2026-01-02")
    tables = _narrow(text, "| timing |", 2, 2)
    assert tables[1][2] == "| step (batches in memory) | 12.50 | 1.25 GiB |"
    assert tables[1][3] == "| train.py loop (with its data loader) | 10.00 | - |"


def _dino_record(wall: bool = True) -> dict:
    stages = {"render": 0.01, "backbone": 0.02, "backproject": 0.03, "total": 0.06, "first_pass": 0.5, "peak_gib": None}
    if wall:
        stages["wall"] = 0.05
    return {
        "date": "2026-01-02",
        "machine": MACHINE,
        "device": "cpu",
        "shape": "shape a",
        "vertices": 5000,
        "views": 49,
        "image_size": 512,
        "batch_size": "auto",
        "autocast": False,
        "repeats": 5,
        "gpu": None,
        "rows": [{"name": "tiny", **stages}, {"name": "big", **stages}, {"name": "big, torch.compile", **stages}],
        "compile": {"saved_per_shape_s": 0.01, "compile_s": 30.0, "pays_over_100_shapes": False},
    }


def test_dino_table_is_two_narrow_tables_under_machine_and_date():
    text = dino.table(_dino_record())
    assert text.splitlines()[0].endswith(f"2026-01-02, {MACHINE}")
    tables = _narrow(text, "| backbone (random DINOv3 weights) |", 2, 3)
    assert tables[0][2] == "| tiny | 0.010 s | 0.020 s | 0.030 s | 0.060 s | 0.050 s |"
    assert tables[1][2] == "| tiny | 0.50 s |"
    assert "torch.compile: 30.0 s to compile" in text
    assert "| wall |" not in dino.table(_dino_record(wall=False))


def test_dino_table_keeps_the_memory_column_where_a_row_has_memory():
    record = _dino_record()
    record["rows"][1]["peak_gib"] = 4.0
    tables = md.tables(dino.table(record))
    assert tables[1][0] == "| backbone (random DINOv3 weights) | first pass | peak GPU memory |"
    assert tables[1][2] == "| tiny | 0.50 s | - |"
    assert tables[1][3] == "| big | 0.50 s | 4.00 GiB |"


def test_dino_profile_gives_date_machine_and_gpu_and_keeps_the_written_tables(tmp_path):
    record = {**_dino_record(), "device": "cuda:0", "gpu": "GPU model X"}
    record["profile"] = {"wall_s": 0.2, "kernel_s": 0.1, "kernel_launches": 3000}
    kernels = ["| kernel | calls | device time | share of kernel time |", "|---|---|---|---|", "| `k` | 2 | 1.00 ms | 50% |"]
    (tmp_path / "run_profile.md").write_text("\n".join(["old line", "", *kernels]) + "\n")
    (tmp_path / "run.json").write_text(json.dumps(record))
    dino.render_only(tmp_path / "run")
    lines = (tmp_path / "run_profile.md").read_text().splitlines()
    assert lines[0] == f"Run of 2026-01-02, {MACHINE}; device GPU model X."
    assert "One pass of the big backbone under torch.profiler" in lines[2]
    assert "3000 kernel launches." in lines[2]
    assert lines[4:] == kernels
    assert len(md.tables((tmp_path / "run.md").read_text())) == 2


def _geolora_record(cuda: bool) -> dict:
    phases = ("geodesics", "partial", "render", "forward", "backproject", "loss", "backward", "optimizer")
    record = {
        "model": "small",
        "image_size": 128,
        "views": [9, 4],
        "partials_per_step": 2,
        "device": "cuda:0" if cuda else "cpu",
        "amp": "auto",
        "steps_timed": 20,
        "median_seconds": {phase: 0.01 for phase in phases},
        "median_step_seconds": 0.08,
        "steps_per_second": 12.5,
        "peak_cuda_memory_gib": 2.0 if cuda else None,
        "machine": MACHINE,
        "date": "2026-01-02",
    }
    if cuda:
        record.update(preset="default", workers=4, wall_steps_per_second=10.0, hours_for_50000_steps=1.4)
    return record


def test_geolora_cpu_table_drops_the_gpu_and_wall_columns():
    text = geolora.table(_geolora_record(cuda=False))
    assert text.splitlines()[0].endswith(f"{MACHINE}, 2026-01-02")
    tables = md.tables(text)
    assert [lines[0] for lines in tables] == [
        "| geodesics | partial | render | forward | backproject |",
        "| loss | backward | optimizer | step | steps/s |",
    ]
    assert tables[1][2] == "| 0.010 | 0.010 | 0.010 | 0.080 | 12.50 |"
    assert "worker" not in text and "recipe" not in text


def test_geolora_cuda_table_is_two_tables_of_at_most_seven_columns():
    text = geolora.table(_geolora_record(cuda=True))
    first = text.splitlines()[0]
    assert "4 sample worker(s), bfloat16 autocast, recipe default, back-projection of the recipe" in first
    assert first.endswith(f"{MACHINE}, 2026-01-02")
    tables = md.tables(text)
    assert len(tables) == 2
    assert all(md.columns(lines[0]) <= 7 for lines in tables)
    assert tables[1][2] == "| 0.010 | 0.010 | 0.010 | 0.080 | 12.50 | 10.00 | 2.00 GiB |"


def test_geolora_profile_gives_date_and_machine(tmp_path):
    record = _geolora_record(cuda=True)
    record["profile"] = {"wall_s": 1.0, "kernel_s": 0.25, "kernel_launches": 100, "host_waits": 6, "host_op_s": 0.5}
    record["profile_tables"] = ["| kernel | calls | device time | share of kernel time |", "|---|---|---|---|"]
    geolora.write_markdown(tmp_path / "run", record)
    lines = (tmp_path / "run_profile.md").read_text().splitlines()
    assert lines[0] == f"Run of 2026-01-02, {MACHINE}."
    assert lines[2].startswith("3 GeoLoRA steps under torch.profiler (GeoLoRA step time: random DINOv3 small")
    assert "6 host waits on the device" in lines[2]
    assert lines[4:] == record["profile_tables"]


def test_point_cloud_large_table_is_seconds_then_memory():
    seconds = {"render": 0.6, "forward": 0.01, "backproject": 0.1, "total": 0.7}
    record = {
        "date": "2026-01-02",
        "machine": MACHINE,
        "views": 49,
        "image_size": 512,
        "repeats": 5,
        "mesh_vs_cloud": [{"shape": "mesh", "mode": "ball", **seconds}],
        "large": [
            {"points": 50000, "what": "features", "seconds": seconds, "rss_before_mib": 889.0, "rss_peak_mib": 900.0},
            {
                "points": 50000,
                "what": "prepare",
                "seconds": {"normals": 0.5, "radii": 0.1, "total": 0.6},
                "rss_before_mib": 889.0,
                "rss_peak_mib": 889.0,
            },
        ],
        "load_average": [0.5, 1.0],
    }
    text = point_clouds.table(record)
    assert text.splitlines()[-1].endswith(f"2026-01-02, {MACHINE}.")
    tables = md.tables(text)
    assert len(tables) == 3
    assert all(md.columns(lines[0]) <= 7 for lines in tables)
    for lines in tables[1:]:
        assert lines[0].startswith("| points | work |")
    assert tables[1][3] == "| 50,000 | normals (0.5 s) and radii (0.1 s) alone |  |  |  | 0.6 |"
    assert tables[2][2] == "| 50,000 | features | 889 | 900 |"


def test_geodesic_memory_table_is_two_narrow_tables_under_machine_and_date(tmp_path):
    done = {
        "run": "default",
        "returncode": 0,
        "n_vertices": 41968,
        "path": "streamed, nothing stored",
        "seconds": 80.0,
        "process_seconds": 81.0,
        "cpu_seconds": 60.0,
        "load_average": 1.0,
        "peak_rss_bytes": 2e9,
        "disk_bytes": 0,
        "geodesic_error": 1.5,
        "chirality_accuracy": 0.99,
    }
    failed = {"run": "streamed", "returncode": 1, "warnings": ["MemoryError"]}
    result = {"machine": MACHINE, "date": "2026-01-02 10:00", "records": [done, failed]}
    text = geodesic_memory.table(result["records"], geodesic_memory.header(result))
    assert text.splitlines()[0].startswith(f"Machine: {MACHINE}; 2026-01-02 10:00.")
    tables = _narrow(text, "| target vertices | run |", 2, 2)
    assert tables[1][2] == "| 41,968 | default bound (half the available memory) | 2.00 GB | 0.00 GB | 1.5000 | 0.9900 |"
    assert "| failed | MemoryError |" in tables[0][3]
    (tmp_path / "run.md").write_text("Machine: x; memory 25 GB; 2026-01-02 10:00.\n")
    assert geodesic_memory.stored_memory_gb(tmp_path / "run") == 25.0
    assert "; memory 25 GB;" in geodesic_memory.header({**result, "memory_gb": 25.0})
