"""GeoLoRA training on several ranks (torch.distributed, gloo on the CPU) with a tiny random DINOv3 backbone.

One module fixture starts two processes with `torch.multiprocessing.spawn` and the variables
torchrun sets (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT); each runs the
``geofeat train-geolora`` command (`geofeat.apps.cli.main`) twice: a new 2-rank run, then the
resumption on 2 ranks of a run that one process started, both with two sample worker
processes per rank (``--workers 2``). The tests compare those runs with single-process runs
of the same command (without workers).
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
from pathlib import Path

import pytest
import safetensors.torch
import torch
import torch.multiprocessing as mp
import trimesh
from shapes import bumpy, free_port
from tiny_models import tiny_dinov3

import geofeat.train.checkpoints as checkpoints_module
from geofeat.apps.cli import main
from geofeat.runtime import distributed
from geofeat.storage.pretrained import WEIGHTS_FILE
from geofeat.train.run_log import RunLog
from geofeat.train.trainer import GeoLoraTrainer

log = logging.getLogger(__name__)

pytestmark = pytest.mark.skipif(not torch.distributed.is_available(), reason="torch.distributed is not built in")

_VALIDATION = ["--val-dataset", "synthetic_cuts", "--val-pairs", "1"]


def _argv(root: Path, out: str, steps: int, *extra: str) -> list[str]:
    return [
        "train-geolora",
        "--data",
        str(root / "shapes"),
        "--weights",
        str(root / "backbone"),
        "--out",
        str(root / out),
        "--steps",
        str(steps),
        "--image-size",
        "32",
        "--backproject",
        "face",
        "--lr",
        "0.001",
        "--checkpoint-every",
        "1",
        "--validate-every",
        "0",
        "--geodesic-cache",
        str(root / "geodesics"),
        "--device",
        "cpu",
        "--no-progress",
        *extra,
    ]


def _rank_main(rank: int, world: int, port: int, root: Path) -> None:
    """One spawned rank: run the command twice, recording its exit codes, output and which writing routines ran."""
    os.environ.update(RANK=str(rank), WORLD_SIZE=str(world), LOCAL_RANK=str(rank), MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    torch.set_num_threads(1)
    calls: dict[str, int] = {}

    def counted(name, function):
        def wrapper(*args, **kwargs):
            calls[name] = calls.get(name, 0) + 1
            return function(*args, **kwargs)

        return wrapper

    checkpoints_module.save_lora = counted("save_lora", checkpoints_module.save_lora)  # writes a checkpoint's LoRA
    checkpoints_module.truncate_log = counted("_truncate_log", checkpoints_module.truncate_log)
    for owner, method in ((GeoLoraTrainer, "validate"), (RunLog, "step_row"), (RunLog, "validation_row")):
        setattr(owner, method, counted(method, getattr(owner, method)))
    record = {}
    with distributed.process_group("cpu"):  # one group for both commands (each leaves a started group running)
        workers = ("--workers", "2")
        for job, argv in (("new", _argv(root, "ddp", 2, *_VALIDATION, *workers)), ("grow", _argv(root, "grow", 3, *workers))):
            calls.clear()
            output = io.StringIO()
            with contextlib.redirect_stdout(output):
                code = main(argv)
            record[job] = {"code": code, "stdout": output.getvalue(), "calls": dict(calls)}
    (root / f"rank{rank}.json").write_text(json.dumps(record))


def _write(mesh, path):
    trimesh.Trimesh(mesh.verts, mesh.faces, process=False).export(path)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The folder of every run: ``ddp`` (2 ranks), ``grow`` (1 process, then 2 ranks), and the ranks' records."""
    root = tmp_path_factory.mktemp("ddp")
    tiny_dinov3().save_pretrained(root / "backbone")
    (root / "shapes").mkdir()
    for seed in (0, 1):
        _write(bumpy(seed, 2), root / "shapes" / f"shape{seed}.off")  # 162 vertices each
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("GEOFEAT_CACHE_DIR", str(root / "cache"))
        for name in distributed.TORCHRUN_VARIABLES:
            patch.delenv(name, raising=False)
        assert main(_argv(root, "grow", 1)) == 0  # one process takes step 1 (global sample 0)
        mp.spawn(_rank_main, args=(2, free_port(), root), nprocs=2, join=True)
    return root, [json.loads((root / f"rank{r}.json").read_text()) for r in (0, 1)]


def _lora(run: Path, step: int) -> dict[str, torch.Tensor]:
    return safetensors.torch.load_file(str(run / "checkpoints" / f"step_{step:07d}" / WEIGHTS_FILE))


def _max_difference(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> float:
    assert sorted(a) == sorted(b) and a
    return max(float((a[k] - b[k]).abs().max()) for k in a)


def _loss_rows(run: Path) -> list[dict]:
    with open(run / "log.csv", newline="") as handle:
        return [row for row in csv.DictReader(handle) if row["loss"]]


def _state(run: Path, step: int) -> tuple[int, int, int]:
    state = torch.load(run / "checkpoints" / f"step_{step:07d}" / "trainer_state.pt", weights_only=True)
    return state["step"], state["samples"], state["world_size"]


def test_two_ranks_with_one_shape_each_train_as_one_process_with_both(runs, capsys):
    root, ranks = runs
    assert [r["new"]["code"] for r in ranks] == [0, 0]
    assert main(_argv(root, "one", 2, "--shapes-per-rank", "2")) == 0
    ddp, one = _lora(root / "ddp", 2), _lora(root / "one", 2)
    difference = _max_difference(ddp, one)
    log.info("max |LoRA weight difference|, 2 ranks x 1 shape vs 1 process x 2 shapes, after 2 steps: %.3g", difference)
    assert difference < 1e-5, difference
    assert _max_difference(one, _lora(root / "one", 0)) > 1e-3  # the weights moved
    losses = [[float(r["loss"]) for r in _loss_rows(root / run)] for run in ("ddp", "one")]
    assert len(losses[0]) == 2 and losses[0] == pytest.approx(losses[1], rel=1e-5)
    assert [int(r["n_partials"]) for r in _loss_rows(root / "ddp")] == [4, 4]  # 2 ranks x 2 partial shapes
    assert _state(root / "ddp", 2) == (2, 4, 2)
    # the same 4 samples, one a step, train otherwise: the comparison can fail
    assert main(_argv(root, "steps", 4)) == 0
    assert _max_difference(ddp, _lora(root / "steps", 4)) > 1e-4


def test_only_rank_zero_writes(runs):
    root, ranks = runs
    # rank 0: checkpoints of steps 0, 1, 2; validation at the start and the end; 2 log rows; the log check on start
    assert ranks[0]["new"]["calls"] == {"save_lora": 3, "validate": 2, "validation_row": 2, "step_row": 2, "_truncate_log": 1}
    assert ranks[1]["new"]["calls"] == {}
    assert ranks[0]["new"]["stdout"] == f"lora: {root / 'ddp' / 'checkpoints' / 'step_0000002'}\n"
    assert ranks[1]["new"]["stdout"] == ""
    with open(root / "ddp" / "log.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(r["step"], bool(r["loss"]), bool(r["val_geodesic_error"])) for r in rows] == [
        ("0", False, True),
        ("1", True, False),
        ("2", True, False),
        ("2", False, True),
    ]


def test_one_process_resumes_a_two_rank_run(runs):
    root, _ = runs
    assert main(_argv(root, "ddp", 3, *_VALIDATION[:2], "--val-pairs", "0")) == 0  # steps 1-2 on 2 ranks, step 3 here
    assert [int(r["step"]) for r in _loss_rows(root / "ddp")] == [1, 2, 3]
    assert [int(r["n_partials"]) for r in _loss_rows(root / "ddp")][-1] == 2  # 1 shape, global sample 4
    assert _state(root / "ddp", 3) == (3, 5, 1)


def test_two_ranks_resume_a_one_process_run(runs):
    root, ranks = runs
    assert [r["grow"]["code"] for r in ranks] == [0, 0]
    assert ranks[0]["grow"]["calls"]["save_lora"] == 2 and "save_lora" not in ranks[1]["grow"]["calls"]
    assert [int(r["step"]) for r in _loss_rows(root / "grow")] == [1, 2, 3]
    assert [int(r["n_partials"]) for r in _loss_rows(root / "grow")] == [2, 4, 4]  # sample 0 | 1, 2 | 3, 4
    assert [_state(root / "grow", s) for s in (1, 2, 3)] == [(1, 1, 1), (2, 3, 2), (3, 5, 2)]
