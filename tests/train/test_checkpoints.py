"""`geofeat.train.checkpoints`: checkpoint folders written whole, read back checked, recovered after a crash."""

from __future__ import annotations

import csv
import json
import logging
import os

import pytest
import torch

pytest.importorskip("peft")
pytest.importorskip("safetensors")

from tiny_models import tiny_dinov3  # noqa: E402

from geofeat.backbones import DinoBackbone, LoraSettings, add_lora, load_lora, lora_state_dict  # noqa: E402
from geofeat.errors import DamagedCheckpointError, TrainingError  # noqa: E402
from geofeat.storage.pretrained import CONFIG_FILE, WEIGHTS_FILE  # noqa: E402
from geofeat.train import checkpoints  # noqa: E402


def _backbone() -> DinoBackbone:
    return add_lora(DinoBackbone(tiny_dinov3(seed=0), kind="dinov3"))


def _state(step: int) -> dict:
    return {"step": step, "samples": step, "world_size": 1, "optimizer": {"state": {}, "param_groups": []}}


def _write(run, step, backbone=None):
    return checkpoints.write_checkpoint(run, step, backbone or _backbone(), LoraSettings(training={"lr": 1e-4}), _state(step))


def test_a_checkpoint_is_a_lora_folder_with_the_trainer_state(tmp_path):
    backbone = _backbone()
    folder = _write(tmp_path / "run", 5, backbone)
    assert folder == tmp_path / "run" / "checkpoints" / "step_0000005" == checkpoints.checkpoint_folder(tmp_path / "run", 5)
    assert sorted(p.name for p in folder.iterdir()) == [CONFIG_FILE, checkpoints.STATE_FILE, WEIGHTS_FILE]
    assert sorted(p.name for p in folder.parent.iterdir()) == ["step_0000005"]  # no temporary folder left
    assert json.loads((folder / CONFIG_FILE).read_text())["info"] == {"step": 5}
    assert checkpoints.read_checkpoint(folder)["step"] == 5
    restored = load_lora(DinoBackbone(tiny_dinov3(seed=0), kind="dinov3"), folder)  # what the geolora descriptor does
    for name, value in lora_state_dict(backbone).items():
        assert torch.equal(lora_state_dict(restored)[name], value)
    assert checkpoints.latest_checkpoint(tmp_path / "run") == folder


def test_an_existing_checkpoint_of_the_step_is_kept(tmp_path):
    folder = _write(tmp_path / "run", 2)
    before = (folder / checkpoints.STATE_FILE).read_bytes()
    other = _state(2) | {"samples": 99}
    checkpoints.write_checkpoint(tmp_path / "run", 2, _backbone(), LoraSettings(), other)
    assert (folder / checkpoints.STATE_FILE).read_bytes() == before


def test_a_damaged_newest_checkpoint_falls_back_to_the_previous_one(tmp_path, caplog):
    run = tmp_path / "run"
    _write(run, 2)
    newest = _write(run, 4)
    weights = newest / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:50])
    with pytest.raises(DamagedCheckpointError):
        checkpoints.read_checkpoint(newest)
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        folder, state = checkpoints.readable_checkpoint(run)
    assert folder.name == "step_0000002" and state["step"] == 2
    assert "step_0000004" in caplog.text and (run / "checkpoints" / ".step_0000004.damaged").is_dir()
    (folder / CONFIG_FILE).write_text("{")  # the last one damaged too
    with pytest.raises(TrainingError, match="no checkpoint of .* can be read"):
        checkpoints.readable_checkpoint(run)


def test_a_checkpoint_of_another_step_is_damaged(tmp_path):
    folder = _write(tmp_path / "run", 2)
    torch.save(_state(3), folder / checkpoints.STATE_FILE)
    with pytest.raises(DamagedCheckpointError, match="is for step 3, its folder for step 2"):
        checkpoints.read_checkpoint(folder)


def test_a_checkpoint_of_another_layout_is_refused_not_set_aside_as_damaged(tmp_path):
    old = tmp_path / "run" / "checkpoints" / "step_0000002"
    old.mkdir(parents=True)
    (old / "adapter_config.json").write_text("{}")
    (old / "adapter.safetensors").write_bytes(b"")
    torch.save(_state(2), old / checkpoints.STATE_FILE)
    with pytest.raises(TrainingError, match="a layout this geofeat does not read; expected config.json .*Train again") as info:
        checkpoints.readable_checkpoint(tmp_path / "run")
    assert not isinstance(info.value, DamagedCheckpointError)
    assert old.is_dir()


def test_a_checkpoint_of_kind_lora_adapter_is_refused_not_set_aside_as_damaged(tmp_path):
    folder = _write(tmp_path / "run", 2)
    envelope = json.loads((folder / CONFIG_FILE).read_text())
    (folder / CONFIG_FILE).write_text(json.dumps({**envelope, "kind": "lora_adapter"}))
    with pytest.raises(TrainingError, match="kind 'lora_adapter', a layout this geofeat does not read.*Train again") as info:
        checkpoints.readable_checkpoint(tmp_path / "run")
    assert not isinstance(info.value, DamagedCheckpointError)
    assert folder.is_dir()


def test_stale_temporary_folders_of_dead_saves_are_removed(tmp_path, caplog):
    folder = tmp_path / "run" / "checkpoints"
    _write(tmp_path / "run", 0)
    for name in (".step_0000002.tmp-999999999-0a0b0c0d", ".step_0000003.tmp-999999999", f".step_0000004.tmp-{os.getppid()}-0e"):
        (folder / name).mkdir()
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        removed = checkpoints.remove_stale_temporary_folders(tmp_path / "run")
    assert [p.name for p in removed] == [".step_0000002.tmp-999999999-0a0b0c0d"]
    assert "unfinished checkpoint" in caplog.text
    # no token: not a name atomic_folder writes, so not taken for one of its temporaries
    assert sorted(p.name for p in folder.iterdir()) == [
        ".step_0000003.tmp-999999999",
        f".step_0000004.tmp-{os.getppid()}-0e",
        "step_0000000",
    ]
    assert checkpoints.remove_stale_temporary_folders(tmp_path / "nowhere") == []


def test_truncate_log_keeps_complete_rows_up_to_the_step(tmp_path):
    columns = ("step", "loss")
    (tmp_path / "log.csv").write_text("step,loss\n1,0.5\n2,0.4\n3,0.3\n4")
    checkpoints.truncate_log(tmp_path, 2, columns)
    with open(tmp_path / "log.csv", newline="") as handle:
        assert [row["step"] for row in csv.DictReader(handle)] == ["1", "2"]
    checkpoints.truncate_log(tmp_path, None, columns)
    assert (tmp_path / "log.csv").read_text().splitlines() == ["step,loss"]
    checkpoints.truncate_log(tmp_path / "none", 3, columns)  # no log yet: nothing to do
