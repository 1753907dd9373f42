"""Training settings, the training-shape loader and the train-geolora command."""

import json

import numpy as np
import pytest
import trimesh
from shapes import bumpy, sphere
from tiny_models import tiny_dinov3

import geofeat
from geofeat.apps.cli import main
from geofeat.errors import TrainingError
from geofeat.train.config import RESUMABLE_CHANGES, TrainConfig
from geofeat.train.shapes import load_training_shapes, prepare_full_shape


def test_defaults_are_the_paper_settings():
    config = TrainConfig(data="FAUST_r/off")
    assert (config.rank, config.alpha, config.views_full, config.views_partial) == (16, 32.0, 9, 4)
    assert (config.lr, config.grad_clip, config.temperature, config.offset) == (1e-4, 1.0, 0.1, 0.5)
    assert (config.image_size, config.partials_per_shape, config.steps, config.max_vertices) == (512, 2, 50000, 12000)
    assert config.partial_kinds == ("cuts", "holes", "ray") and config.loss == "geodesic"


@pytest.mark.parametrize(
    "bad, message",
    [
        ({"data": ""}, "data is empty"),
        ({"loss": "l2"}, "loss must be one of"),
        ({"partial_kinds": ("cuts", "slices")}, "partial_kinds"),
        ({"views_full": 0}, "views_full must be a positive integer"),
        ({"lr": -1.0}, "lr must be a number > 0"),
        ({"amp": "maybe"}, "amp must be one of"),
    ],
)
def test_bad_settings_are_refused(bad, message):
    with pytest.raises(TrainingError, match=message):
        TrainConfig(**({"data": "x"} | bad))


def test_workers_setting_is_checked_and_resumable():
    assert TrainConfig(data="x").workers == "auto"
    assert TrainConfig(data="x", workers="2").workers == 2  # the text of a command-line flag
    for bad in (-1, "many", 1.5, True):
        with pytest.raises(TrainingError, match="workers must be an integer >= 0 or 'auto'"):
            TrainConfig(data="x", workers=bad)
    assert TrainConfig(data="x", workers=3).changes_from(TrainConfig(data="x")) == ["workers"]
    assert "workers" in RESUMABLE_CHANGES


def test_files_round_trip_and_flags_win(tmp_path, caplog):
    config = TrainConfig(data="shapes", views_full=16, partial_kinds=("holes",))
    config.save(tmp_path / "a.json")
    again = TrainConfig.from_file(tmp_path / "a.json")
    assert again == config and again.changes_from(config) == []
    (tmp_path / "b.yaml").write_text("data: shapes\nlr: 0.001\nwandb_project: x\npartial_kinds: [cuts, ray]\n")
    loaded = TrainConfig.from_file(tmp_path / "b.yaml", lr=0.01, steps=None)
    assert loaded.lr == 0.01 and loaded.steps == 50000 and loaded.partial_kinds == ("cuts", "ray")
    assert loaded.unknown_keys == ["wandb_project"]
    assert loaded.changes_from(TrainConfig(data="shapes")) == ["partial_kinds", "lr"]
    (tmp_path / "c.json").write_text("[1, 2]")
    with pytest.raises(TrainingError, match="mapping"):
        TrainConfig.from_file(tmp_path / "c.json")
    with pytest.raises(TrainingError, match="does not exist"):
        TrainConfig.from_file(tmp_path / "missing.yaml")


def _write(mesh, path):
    trimesh.Trimesh(mesh.verts, mesh.faces, process=False).export(path)


def test_shapes_from_a_folder_are_decimated_and_connected(tmp_path, caplog):
    _write(sphere(4), tmp_path / "a_big.off")  # 2562 vertices
    two = trimesh.util.concatenate([trimesh.creation.icosphere(2), trimesh.creation.icosphere(1).apply_translation([5, 0, 0])])
    two.export(tmp_path / "b_two_parts.off")
    (tmp_path / "notes.txt").write_text("not a mesh")
    shapes = load_training_shapes(str(tmp_path), max_vertices=1000, progress=False)
    assert [m.name for m in shapes] == ["a_big", "b_two_parts"]
    assert 500 < shapes[0].n_vertices <= 1100
    assert shapes[1].n_vertices == 162  # the larger sphere; the smaller one dropped
    assert "largest connected component" in caplog.text
    assert len(load_training_shapes(str(tmp_path), first=1, max_vertices=5000, progress=False)) == 1
    small = bumpy(0, 2)
    assert prepare_full_shape(small, 12000) is small


def test_shape_loading_errors(tmp_path):
    with pytest.raises(TrainingError, match="holds no mesh"):
        load_training_shapes(str(tmp_path), progress=False)
    with pytest.raises(TrainingError, match="does not exist"):
        load_training_shapes(str(tmp_path / "missing"), progress=False)
    with pytest.raises(TrainingError, match="point cloud"):
        prepare_full_shape(geofeat.Mesh(np.random.default_rng(0).normal(size=(10, 3)), None, "cloud"), 100)


def test_train_geolora_command_trains_and_resumes(tmp_path, capsys):
    tiny_dinov3().save_pretrained(tmp_path / "backbone")
    for seed in (0, 1):
        _write(bumpy(seed, 2), tmp_path / f"shape{seed}.off")
    (tmp_path / "settings.yaml").write_text(f"data: {tmp_path}\nimage_size: 32\nbackproject: face\nsteps: 2\n")
    argv = [
        "train-geolora",
        "--config",
        str(tmp_path / "settings.yaml"),
        "--weights",
        str(tmp_path / "backbone"),
        "--out",
        str(tmp_path / "run"),
        "--geodesic-cache",
        str(tmp_path / "geo"),
        "--no-progress",
        "--device",
        "cpu",
        "--partial-kinds",
        "cuts,holes",
    ]
    assert main(argv) == 0
    assert "step_0000002" in capsys.readouterr().out
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["image_size"] == 32 and saved["partial_kinds"] == ["cuts", "holes"] and saved["steps"] == 2
    assert main([*argv, "--steps", "3"]) == 0  # resumes
    assert "step_0000003" in capsys.readouterr().out
    assert main([*argv, "--steps", "4", "--lr", "0.5"]) == 2  # other settings: refused with a message
    assert "lr=0.0001" in capsys.readouterr().err
