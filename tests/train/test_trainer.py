"""The GeoLoRA trainer on tiny random DINOv3 backbones and small seeded meshes."""

from __future__ import annotations

import contextlib
import csv
import os
import re
import signal
import time

import numpy as np
import pytest
import torch
from shapes import bumpy
from tiny_models import tiny_dinov3

import geofeat
from geofeat.backbones import DinoBackbone, lora_state_dict
from geofeat.errors import TrainingError
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.train.checkpoints import latest_checkpoint
from geofeat.train.config import TrainConfig
from geofeat.train.geodesics import TorchGeodesicStore
from geofeat.train.trainer import GeoLoraTrainer, rotate_about_up


def _backbone() -> DinoBackbone:
    return DinoBackbone(tiny_dinov3(), kind="dinov3")


def _shapes():
    return [bumpy(seed, 2) for seed in (0, 1)]  # 162 vertices each


def _config(tmp_path, **overrides) -> TrainConfig:
    settings = dict(
        data="unused",
        out=str(tmp_path / "run"),
        image_size=32,
        backproject="face",
        steps=4,
        checkpoint_every=2,
        validate_every=0,
        geodesic_cache=str(tmp_path / "geodesics"),
        progress=False,
        device="cpu",
    )
    settings.update(overrides)
    return TrainConfig(**settings)


def _trainer(tmp_path, **overrides) -> GeoLoraTrainer:
    return GeoLoraTrainer(_config(tmp_path, **overrides), backbone=_backbone(), shapes=_shapes())


def _log_rows(run) -> list[dict]:
    with open(run / "log.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def test_rotate_about_up_keeps_height_and_distances():
    mesh = bumpy(0, 2)
    turned = rotate_about_up(mesh, 90.0)
    np.testing.assert_allclose(turned.verts[:, 1], mesh.verts[:, 1])
    np.testing.assert_allclose(turned.verts[:, 0], mesh.verts[:, 2], atol=1e-12)
    np.testing.assert_allclose(geodesic_matrix(turned), geodesic_matrix(mesh), atol=1e-9)


def test_fit_writes_log_checkpoints_and_moves_only_lora(tmp_path):
    trainer = _trainer(tmp_path)
    base = {k: v.clone() for k, v in trainer.backbone.model.state_dict().items()}
    final = trainer.fit()
    run = tmp_path / "run"
    assert final == run / "checkpoints" / "step_0000004" == latest_checkpoint(run)
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step_0000000", "step_0000002", "step_0000004"]
    rows = [r for r in _log_rows(run) if r["loss"]]
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert all(np.isfinite(float(r["loss"])) and int(r["n_partials"]) == 2 for r in rows)
    assert all(float(r["t_backward"]) > 0 and float(r["t_render"]) > 0 for r in rows)
    # The base weights did not move; LoRA B left zero.
    after = trainer.backbone.model.base_model.model.state_dict()
    for name, value in after.items():
        if "lora_" not in name:
            assert torch.equal(value, base[name.replace(".base_layer", "")]), name
    assert any(bool(t.abs().sum() > 0) for k, t in lora_state_dict(trainer.backbone).items() if "lora_B" in k)
    assert (run / "config.json").is_file()


def test_training_lowers_the_loss_of_a_fixed_draw(tmp_path):
    """End to end (render, backbone, upsampling, back-projection, loss): repeated steps on one draw lower its loss."""
    trainer = _trainer(tmp_path, lr=5e-2, steps=1000, image_size=64)
    trainer._start_or_resume()
    losses = []
    for _ in range(25):
        trainer.step = 0  # the same shape, rotation and partial shapes every time
        losses.append(trainer.train_step().loss)
    assert losses[-1] < 0.9 * losses[0], losses


def test_resume_continues_exactly(tmp_path):
    straight = _trainer(tmp_path / "a")
    straight.fit()
    first = _trainer(tmp_path / "b", steps=2)
    first.fit()
    resumed = _trainer(tmp_path / "b", steps=4)
    resumed.fit()
    a, b = lora_state_dict(straight.backbone), lora_state_dict(resumed.backbone)
    for name in a:
        torch.testing.assert_close(a[name], b[name], rtol=0, atol=1e-6)
    losses_a = [float(r["loss"]) for r in _log_rows(tmp_path / "a" / "run") if r["loss"]]
    losses_b = [float(r["loss"]) for r in _log_rows(tmp_path / "b" / "run") if r["loss"]]
    np.testing.assert_allclose(losses_a, losses_b, rtol=1e-5)


def test_resume_refuses_other_settings(tmp_path):
    _trainer(tmp_path, steps=2).fit()
    with pytest.raises(TrainingError, match="lr=0.0001"):
        _trainer(tmp_path, steps=4, lr=1e-3).fit()


def test_resume_refuses_changed_training_shapes_and_says_what_changed(tmp_path):
    _trainer(tmp_path, steps=2).fit()
    config = _config(tmp_path, steps=4)
    moved = bumpy(1, 2)
    edited = geofeat.Mesh(moved.verts * 1.01, moved.faces, moved.name)  # the same name, other content
    cases = {
        "1 changed in content (bumpy1)": [bumpy(0, 2), edited],
        "1 added (bumpy2)": [*_shapes(), bumpy(2, 2)],
        "1 removed (bumpy1)": _shapes()[:1],
        "the same shapes in another order": _shapes()[::-1],
    }
    for message, shapes in cases.items():
        with pytest.raises(TrainingError, match=re.escape(message)):
            GeoLoraTrainer(config, backbone=_backbone(), shapes=shapes).fit()
    assert GeoLoraTrainer(config, backbone=_backbone(), shapes=_shapes()).fit().name == "step_0000004"


def test_time_budget_stops_with_a_checkpoint(tmp_path):
    trainer = _trainer(tmp_path, steps=100, max_minutes=1e-6, checkpoint_every=0)
    final = trainer.fit()
    assert final.name == "step_0000001"


def test_ctrl_c_finishes_the_step_and_saves(tmp_path):
    trainer = _trainer(tmp_path, steps=10, checkpoint_every=0)
    step = trainer.train_step

    def interrupted_step():
        record = step()
        if trainer.step == 2:
            os.kill(os.getpid(), signal.SIGINT)
        return record

    trainer.train_step = interrupted_step
    with pytest.raises(KeyboardInterrupt):
        trainer.fit()
    assert latest_checkpoint(tmp_path / "run").name == "step_0000002"
    resumed = _trainer(tmp_path, steps=3, checkpoint_every=0)
    assert resumed.fit().name == "step_0000003"


def test_validation_is_logged(tmp_path):
    trainer = _trainer(tmp_path, steps=2, validate_every=1, val_dataset="synthetic_cuts", val_pairs=1)
    trainer.fit()
    errors = [float(r["val_geodesic_error"]) for r in _log_rows(tmp_path / "run") if r["val_geodesic_error"]]
    assert len(errors) == 3  # start, after step 1, end
    assert all(0 < e < 200 for e in errors)


def test_bfloat16_autocast_step_on_cpu(tmp_path):
    trainer = _trainer(tmp_path, amp="on")
    trainer._start_or_resume()
    assert np.isfinite(trainer.train_step().loss)


def test_plain_loss_and_single_kind(tmp_path):
    trainer = _trainer(tmp_path, loss="plain", partial_kinds=("holes",), partials_per_shape=1)
    trainer._start_or_resume()
    record = trainer.train_step()
    assert record.n_partials == 1 and np.isfinite(record.loss)


def test_reference_steps_rescale_rope_with_draws_seeded_by_the_sample(tmp_path):
    trainer = _trainer(tmp_path, recipe="reference", backproject="ball", image_size=64)
    assert trainer._rope_augmentation()
    sample = trainer.sample_stream.dataset.prepare(0)
    features = []
    for _ in range(2):
        with torch.no_grad(), trainer._training_mode(sample.index):
            assert trainer.backbone.rope_augmentation
            features.append(
                trainer.sample_features(sample.full, [m for m, _ in sample.partials], lambda phase: contextlib.nullcontext())
            )
    assert not trainer.backbone.rope_augmentation  # validation and inference see eval() mode
    for (a, _), (b, _) in zip(features[0], features[1], strict=True):
        assert torch.equal(a, b)  # the same sample draws the same rescaling
    with torch.no_grad():
        plain = trainer.sample_features(sample.full, [m for m, _ in sample.partials], lambda phase: contextlib.nullcontext())
    assert plain[0].seen.any() and not torch.equal(plain[0][0], features[0][0][0])  # eval() mode: no rescaling
    assert not _trainer(tmp_path / "off", recipe="reference", backproject=None, rope_augmentation=False)._rope_augmentation()
    assert not _trainer(tmp_path / "default")._rope_augmentation()


def test_image_size_must_fit_the_patch(tmp_path):
    with pytest.raises(TrainingError, match="multiple of the backbone patch size 16"):
        _trainer(tmp_path, image_size=40)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_step_with_autocast(tmp_path):
    trainer = _trainer(tmp_path, device="cuda")
    trainer._start_or_resume()
    start = time.perf_counter()
    record = trainer.train_step()
    wall = time.perf_counter() - start
    assert np.isfinite(record.loss)
    # phases timed by CUDA events: each one there, none negative, together within the step's wall time
    assert {"render", "forward", "backproject", "loss", "backward", "optimizer"} <= set(record.seconds)
    assert all(seconds >= 0 for seconds in record.seconds.values())
    assert sum(record.seconds.values()) <= wall


def test_geodesic_store_round_trip_and_repair(tmp_path, caplog):
    store = TorchGeodesicStore(tmp_path / "g")
    mesh = bumpy(0, 2)
    dist = store.load(mesh).numpy()
    exact = geodesic_matrix(mesh, normalize=True)
    np.testing.assert_allclose(dist, exact, rtol=2e-3, atol=1e-4)
    path = store.path(mesh)
    assert np.load(path).dtype == np.float16
    path.write_bytes(b"not a numpy file")
    np.testing.assert_allclose(store.load(mesh).numpy(), dist)
    assert "recomputing" in caplog.text


def test_reference_recipe_trains_one_shared_a_per_block_and_resumes_exactly(tmp_path):
    """``recipe="reference"``: the official recipe, whose fused-qkv LoRA has one A per block; resume stays exact."""
    overrides = {"recipe": "reference", "backproject": None, "image_size": 32, "steps": 2, "checkpoint_every": 1}
    straight = _trainer(tmp_path / "a", **overrides)
    straight.fit()
    named = dict(straight.backbone.model.named_parameters(remove_duplicate=False))
    for block in range(straight.backbone.num_layers):
        a = {id(p) for n, p in named.items() if f"layer.{block}." in n and "lora_A" in n}
        assert len(a) == 1
    state = lora_state_dict(straight.backbone)
    assert torch.count_nonzero(state["layer.0.q_proj.lora_B.weight"]) > 0  # it trained
    torch.testing.assert_close(state["layer.0.q_proj.lora_A.weight"], state["layer.0.v_proj.lora_A.weight"], rtol=0, atol=0)
    # every checkpoint also holds the LoRA as a release checkpoint, which loads back to the same tensors
    from geofeat.backbones import load_official_lora
    from geofeat.train.checkpoints import RELEASE_FILE

    release = latest_checkpoint(tmp_path / "a" / "run") / RELEASE_FILE
    loaded = load_official_lora(_backbone(), release)
    for name, value in lora_state_dict(loaded).items():
        torch.testing.assert_close(value, state[name], rtol=0, atol=0)
    _trainer(tmp_path / "b", **(overrides | {"steps": 1})).fit()
    resumed = _trainer(tmp_path / "b", **overrides)
    resumed.fit()
    for name, value in lora_state_dict(resumed.backbone).items():
        torch.testing.assert_close(value, state[name], rtol=0, atol=1e-6)


@pytest.mark.parametrize(("recipe", "used"), [("default", 1), ("reference", 0)])
def test_a_partial_shape_without_a_loss_is_left_out_or_skips_the_sample(tmp_path, monkeypatch, recipe, used):
    """geofeat leaves out the partial shape; the reference recipe, like the official loop, the whole sample."""
    trainer = _trainer(tmp_path, recipe=recipe, partials_per_shape=2, image_size=32)
    real_loss, calls = trainer._loss, []

    def second_fails(*args):
        calls.append(1)
        if len(calls) == 2:
            raise TrainingError("no partial vertex was seen")
        return real_loss(*args)

    monkeypatch.setattr(trainer, "_loss", second_fails)
    sample = trainer.sample_stream.dataset.prepare(0)
    loss, count = trainer._sample_loss(sample, lambda phase: contextlib.nullcontext())
    assert count == used and (loss is None) == (used == 0)
