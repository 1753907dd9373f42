"""Training samples prepared on the CPU (geofeat.train.samples), in worker processes or inline: the same training to the bit."""

from __future__ import annotations

import csv
import math
import os
import pickle
import signal

import numpy as np
import psutil
import pytest
import torch
from shapes import bumpy
from tiny_models import tiny_dinov3

import geofeat.train.samples as samples_module
from geofeat.backbones import DinoBackbone, lora_state_dict
from geofeat.errors import TrainingError
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.geometry.partial import make_partial
from geofeat.mesh import Mesh
from geofeat.train.config import TrainConfig
from geofeat.train.geodesics import TorchGeodesicStore
from geofeat.train.samples import SampleDataset, SamplePrefetcher, prepare_sample, resolve_workers
from geofeat.train.trainer import GeoLoraTrainer


def _shapes() -> list[Mesh]:
    return [bumpy(seed, 2) for seed in (0, 1, 2)]  # 162 vertices each


def _config(tmp_path, **overrides) -> TrainConfig:
    settings = dict(
        data="unused",
        out=str(tmp_path / "run"),
        image_size=32,
        backproject="face",
        steps=3,
        checkpoint_every=0,
        validate_every=0,
        geodesic_cache=str(tmp_path / "geodesics"),
        progress=False,
        device="cpu",
    )
    settings.update(overrides)
    return TrainConfig(**settings)


def _trainer(tmp_path, **overrides) -> GeoLoraTrainer:
    return GeoLoraTrainer(_config(tmp_path, **overrides), backbone=DinoBackbone(tiny_dinov3(), kind="dinov3"), shapes=_shapes())


def _losses(run) -> list[str]:
    with open(run / "log.csv", newline="") as handle:
        return [row["loss"] for row in csv.DictReader(handle) if row["loss"]]


def _assert_same_lora(a: GeoLoraTrainer, b: GeoLoraTrainer) -> None:
    first, second = lora_state_dict(a.backbone), lora_state_dict(b.backbone)
    assert sorted(first) == sorted(second) and first
    for name in first:
        assert torch.equal(first[name], second[name]), name


def _turned(verts: np.ndarray, degrees: float) -> np.ndarray:
    """The documented rotation: counter-clockwise about +y, points as ``points @ R.T``."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    return verts @ np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]).T


def _children() -> set[int]:
    return {child.pid for child in psutil.Process().children(recursive=True)}


@pytest.mark.parametrize("index", [0, 4])  # epoch 0, and epoch 1 (another permutation)
def test_prepared_sample_follows_the_documented_draws(tmp_path, index):
    config = _config(tmp_path, seed=3, partials_per_shape=3)
    shapes = _shapes()
    store = TorchGeodesicStore(tmp_path / "geodesics")
    sample = prepare_sample(config, shapes, index, store)
    # the rule, written out: the shape from the epoch's permutation, every other draw from default_rng([seed, g])
    n = len(shapes)
    which = int(np.random.default_rng([3, index // n, 1]).permutation(n)[index % n])
    rng = np.random.default_rng([3, index])
    full = _turned(shapes[which].verts, rng.uniform(0.0, 360.0))
    assert sample.index == index and sample.shape_index == which
    assert np.array_equal(sample.full.verts, full) and np.array_equal(sample.full.faces, shapes[which].faces)
    assert len(sample.partials) == 3
    for mesh, gt in sample.partials:
        kind = config.partial_kinds[rng.integers(len(config.partial_kinds))]
        partial = make_partial(Mesh(full, shapes[which].faces), kind, seed=int(rng.integers(2**63 - 1)))
        assert np.array_equal(mesh.verts, _turned(partial.mesh.verts, rng.uniform(0.0, 360.0)))
        assert np.array_equal(mesh.faces, partial.mesh.faces)
        assert gt.dtype == torch.int64 and gt.device.type == "cpu" and np.array_equal(gt.numpy(), partial.vertex_map)
    # the geodesics as stored: the float16 file, widened on the device to what the trainer used before
    stored = np.load(store.path(shapes[which]))
    assert sample.geodesics.dtype == torch.float16 and sample.geodesics.device.type == "cpu"
    assert np.array_equal(sample.geodesics.numpy(), stored)
    assert torch.equal(sample.geodesics.float(), store.load(shapes[which]))
    np.testing.assert_allclose(stored, geodesic_matrix(shapes[which], normalize=True), rtol=2e-3, atol=1e-4)


def test_reference_samples_follow_the_official_loop(tmp_path):
    from geofeat.topology import triangle_areas
    from geofeat.train.samples import training_partial_reference

    config = _config(tmp_path, recipe="reference", seed=2)
    assert config.generators() == "reference"
    shapes = _shapes()
    store = TorchGeodesicStore(tmp_path / "geodesics")
    sample = prepare_sample(config, shapes, 1, store)
    # the rule, written out: one seed from default_rng([seed, g]) for a legacy RandomState and a torch generator
    shape = shapes[sample.shape_index]
    seed = int(np.random.default_rng([2, 1]).integers(2**32))
    state, generator = np.random.RandomState(seed), torch.Generator().manual_seed(seed)
    turned = _turned(shape.verts, -math.degrees(state.uniform(0.0, 2 * math.pi))).astype(np.float32)
    full = turned / np.float32(np.sqrt(triangle_areas(turned, shape.faces).sum()))  # as the official loop sees it
    np.testing.assert_allclose(sample.full.verts, full, rtol=0, atol=1e-6)
    np.testing.assert_allclose(triangle_areas(sample.full.verts, sample.full.faces).sum(), 1.0, rtol=1e-5)
    assert len(sample.partials) == 2
    dist = sample.geodesics.float().numpy()
    for mesh, gt in sample.partials:
        partial = training_partial_reference(sample.full, config.partial_kinds, dist, state, generator)
        np.testing.assert_allclose(
            mesh.verts, _turned(partial.mesh.verts, -math.degrees(state.uniform(0.0, 2 * math.pi))), atol=1e-6
        )
        assert gt.dtype == torch.int64 and np.array_equal(gt.numpy(), partial.vertex_map) and not partial.exact
        distance = np.linalg.norm(partial.mesh.verts[:, None] - sample.full.verts[None], axis=2)
        # the official ground truth: the nearest full vertex (float32 distances: ties within rounding either way)
        assert np.all(distance[np.arange(len(gt)), gt.numpy()] <= distance.min(axis=1) + 1e-5)
    again = prepare_sample(config, shapes, 1, store)
    assert again.full.hash == sample.full.hash
    assert [m.hash for m, _ in again.partials] == [m.hash for m, _ in sample.partials]


def test_partial_generators_setting(tmp_path):
    assert _config(tmp_path).generators() == "geofeat"
    assert _config(tmp_path, recipe="reference", partial_generators="geofeat").generators() == "geofeat"
    assert _config(tmp_path, partial_generators="reference").generators() == "reference"
    with pytest.raises(TrainingError, match="partial_generators must be one of"):
        _config(tmp_path, partial_generators="open3d")


def test_the_dataset_prepares_the_same_sample_in_a_worker_process(tmp_path):
    config = _config(tmp_path)
    dataset = SampleDataset(config, _shapes(), tmp_path / "geodesics")
    here = dataset[5]
    assert pickle.loads(pickle.dumps(dataset))._store is None  # each process opens its own store
    with SamplePrefetcher(dataset, lambda step: range(2 * step, 2 * step + 2), 2, 4, workers=2) as prefetcher:
        assert prefetcher.take(3) is None  # not the next step
        two, three = prefetcher.take(2), prefetcher.take(3)
        assert prefetcher.take(4) is None  # past the last step
    assert [s.index for s in two + three] == [4, 5, 6, 7]
    there = two[1]
    assert there.shape_index == here.shape_index and there.full.hash == here.full.hash
    assert not there.full.verts.flags.writeable  # a mesh from another process is read-only, as any Mesh
    for (mesh_a, gt_a), (mesh_b, gt_b) in zip(here.partials, there.partials, strict=True):
        assert mesh_a.hash == mesh_b.hash and torch.equal(gt_a, gt_b)
    assert torch.equal(here.geodesics, there.geodesics)


def test_the_loader_must_hand_out_the_expected_samples(tmp_path):
    dataset = SampleDataset(_config(tmp_path), _shapes(), tmp_path / "geodesics")
    with SamplePrefetcher(dataset, lambda step: range(step, step + 1), 0, 2, workers=1) as prefetcher:
        prefetcher.step_indices = lambda step: range(step + 7, step + 8)  # the trainer's position moved under it
        with pytest.raises(TrainingError, match="handed out sample 0 where step 0 expected sample 7"):
            prefetcher.take(0)


def test_workers_train_exactly_as_one_process(tmp_path, monkeypatch):
    """workers=2 prepares every sample in worker processes; the weights and losses are those of workers=0, to the bit."""
    (tmp_path / "pids").mkdir()
    prepare = samples_module.prepare_sample

    def recorded(config, shapes, index, geodesics, timer=None):
        (tmp_path / "pids" / f"{index}-{os.getpid()}").touch()
        return prepare(config, shapes, index, geodesics, timer)

    monkeypatch.setattr(samples_module, "prepare_sample", recorded)
    inline = _trainer(tmp_path / "inline", workers=0, shapes_per_rank=2)
    inline.fit()
    for path in (tmp_path / "pids").iterdir():
        path.unlink()
    workers = _trainer(tmp_path / "workers", workers=2, shapes_per_rank=2)
    workers.fit()
    prepared = [name.split("-") for name in os.listdir(tmp_path / "pids")]
    assert sorted(int(index) for index, _ in prepared) == list(range(6))
    assert str(os.getpid()) not in {pid for _, pid in prepared}  # all in worker processes
    _assert_same_lora(inline, workers)
    assert _losses(tmp_path / "inline" / "run") == _losses(tmp_path / "workers" / "run")


def test_resume_with_workers_continues_exactly(tmp_path):
    straight = _trainer(tmp_path / "a", steps=4, workers=0)
    straight.fit()
    _trainer(tmp_path / "b", steps=2, workers=2).fit()
    resumed = _trainer(tmp_path / "b", steps=4, workers=1)  # another worker count: allowed, changes nothing
    resumed.fit()
    _assert_same_lora(straight, resumed)
    assert _losses(tmp_path / "a" / "run") == _losses(tmp_path / "b" / "run")


def test_no_worker_is_left_behind(tmp_path):
    before = _children()
    seen = []

    def watched(trainer, fail_at=None, interrupt_at=None):
        step = trainer.train_step

        def train_step():
            if trainer.step == fail_at:
                raise RuntimeError("failed")
            record = step()
            seen.append(len(_children() - before))
            if trainer.step == interrupt_at:
                os.kill(os.getpid(), signal.SIGINT)  # to this process only; workers ignore Ctrl-C anyway
            return record

        trainer.train_step = train_step
        return trainer

    watched(_trainer(tmp_path / "done", steps=2, workers=2)).fit()
    assert seen and min(seen) == 2 and _children() - before == set()
    with pytest.raises(RuntimeError, match="failed"):
        watched(_trainer(tmp_path / "failed", steps=3, workers=2), fail_at=1).fit()
    assert _children() - before == set()
    with pytest.raises(KeyboardInterrupt):
        watched(_trainer(tmp_path / "stopped", steps=3, workers=2), interrupt_at=1).fit()
    assert _children() - before == set()


def test_train_step_alone_starts_and_restarts_the_workers(tmp_path):
    before = _children()
    trainer = _trainer(tmp_path, steps=3, workers=2)
    trainer._start_or_resume()
    taken = []
    sample_loss = trainer._sample_loss

    def recorded(sample, timer):
        taken.append((sample.index, trainer.sample_stream.prefetcher is not None))
        return sample_loss(sample, timer)

    trainer._sample_loss = recorded
    first = trainer.train_step()
    assert len(_children() - before) == 2 and trainer.sample_stream.prefetcher.next_step == 1
    trainer.train_step()
    trainer.step = 0  # moved back: the workers start again at the new position
    again = trainer.train_step()
    assert trainer.sample_stream.prefetcher.next_step == 1
    assert np.isfinite(again.loss) and again.loss != first.loss  # the weights moved
    trainer.close()
    assert trainer.sample_stream.prefetcher is None and _children() - before == set()
    trainer.step = 3  # past config.steps: prepared here
    trainer.train_step()
    assert taken == [(0, True), (1, True), (0, True), (3, False)]
    assert trainer.sample_stream.prefetcher is None


def test_workers_setting():
    assert resolve_workers(3, torch.device("cpu")) == 3
    assert resolve_workers("auto", torch.device("cpu")) == 0
    assert 0 <= resolve_workers("auto", torch.device("cuda")) <= 4


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_workers_hand_over_pinned_samples(tmp_path):
    pinned = []
    runs = {}
    for workers in (0, 2):
        trainer = _trainer(tmp_path / str(workers), steps=2, workers=workers, device="cuda", amp="off")
        sample_loss = trainer._sample_loss

        def recorded(sample, timer, sample_loss=sample_loss, workers=workers):
            if workers:
                pinned.append(sample.geodesics.is_pinned() and all(gt.is_pinned() for _, gt in sample.partials))
            return sample_loss(sample, timer)

        trainer._sample_loss = recorded
        trainer.fit()
        runs[workers] = [float(loss) for loss in _losses(tmp_path / str(workers) / "run")]
    assert pinned == [True, True]
    np.testing.assert_allclose(runs[2], runs[0], rtol=1e-4)
