"""The common head interface: training-free heads, the shared training loop and checkpoints."""

from dataclasses import dataclass

import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.adapters.base import HeadConfig
from geofeat.adapters.heads import load_head, make_head
from geofeat.adapters.inputs import input_features
from geofeat.adapters.learned import LearnedHead
from geofeat.adapters.matchers import FunctionalMapHead
from geofeat.datasets.records import Match, ShapePair
from geofeat.descriptors import compute, make_descriptor
from geofeat.errors import HeadError, UnusablePair
from geofeat.geometry import make_partial


def _pair(seed: int = 0) -> ShapePair:
    mesh = bumpy(seed, 3)
    partial = make_partial(mesh, "cuts", seed=seed)
    return ShapePair(x=mesh, y=partial.mesh, map_yx=np.asarray(partial.vertex_map, dtype=np.int64), protocol="p2f")


def test_nn_head_matches_a_permuted_copy_exactly_with_xyz():
    mesh = bumpy(0, 3)
    order = np.random.default_rng(0).permutation(mesh.n_vertices)
    inverse = np.argsort(order)
    copy = type(mesh)(mesh.verts[order], inverse[mesh.faces], "permuted")
    pair = ShapePair(x=mesh, y=copy, map_yx=order.astype(np.int64), protocol="f2f")
    match = make_head("nn", descriptor="xyz").match(pair)
    assert isinstance(match, Match) and match.map_yx.dtype == np.int64 and match.overlap_y.all()
    np.testing.assert_array_equal(match.map_yx, pair.map_yx)


def test_head_keeps_recent_features_read_only_and_keyed_by_descriptor_settings():
    mesh = bumpy(0, 3)
    head = make_head("nn", descriptor="xyz", descriptor_params={"normalize": True})
    first = head.features(mesh)
    assert head.features(mesh) is first  # the target of several pairs in a row is read once
    assert not first.flags.writeable
    np.testing.assert_array_equal(first, input_features(mesh, "xyz", {"normalize": True}))
    head.config.descriptor_params = {"normalize": False}
    raw = head.features(mesh)  # other settings: not the kept array
    np.testing.assert_array_equal(raw, mesh.verts.astype(np.float32))
    assert not np.array_equal(raw, first)


def test_head_builds_its_descriptor_once_for_every_mesh(monkeypatch):
    """A model-backed descriptor loads its weights when built: a head builds it once, not once per mesh."""
    import geofeat.adapters.base as heads_module

    built = []

    def counting_make_descriptor(name, **params):
        built.append((name, params))
        return make_descriptor(name, **params)

    monkeypatch.setattr(heads_module, "make_descriptor", counting_make_descriptor)
    head = make_head("nn", descriptor="wks", descriptor_params={"n_eig": 30, "n_descr": 8})
    meshes = [bumpy(seed, 2) for seed in range(3)]
    for mesh in meshes:
        np.testing.assert_array_equal(head.features(mesh), compute(mesh, "wks", n_eig=30, n_descr=8, cache=False))
    assert built == [("wks", {"n_eig": 30, "n_descr": 8})]
    head.config.descriptor_params = {"n_eig": 30, "n_descr": 4}  # other settings: a new descriptor, once
    assert head.features(meshes[0]).shape == (meshes[0].n_vertices, 4)
    head.features(meshes[1])
    assert built == [("wks", {"n_eig": 30, "n_descr": 8}), ("wks", {"n_eig": 30, "n_descr": 4})]


def test_fmap_head_settings_and_errors():
    head = make_head("fmap", descriptor="wks", k=20, n_eig=40)
    assert isinstance(head, FunctionalMapHead) and head.config.k == 20
    match = head.match(_pair())
    assert match.map_yx.shape == (_pair().y.n_vertices,)
    with pytest.raises(HeadError, match="unknown setting"):
        make_head("fmap", colour="red")
    with pytest.raises(HeadError, match="unknown head"):
        make_head("magic")
    with pytest.raises(HeadError, match="takes only normalize"):
        input_features(bumpy(0, 2), "xyz", {"scale": 2})
    with pytest.raises(HeadError, match="takes only normalize"):
        input_features(bumpy(0, 2), "xyz", {"normalize": "false"})
    mesh = bumpy(0, 2)
    np.testing.assert_array_equal(input_features(mesh, "xyz", {"normalize": False}), mesh.verts.astype(np.float32))
    centred = input_features(mesh, "xyz")
    np.testing.assert_allclose(centred.mean(axis=0), 0.0, atol=1e-6)


@dataclass
class _AffineConfig(HeadConfig):
    width: int = 8


class _AffineHead(LearnedHead):
    """A per-vertex linear map trained so that y's features reach their ground-truth x features."""

    name = "test_affine"
    config_class = _AffineConfig

    def build_model(self, in_channels):
        return torch.nn.Linear(in_channels, self.config.width)

    def training_loss(self, pair):
        fx = self.model(self.shape_inputs(pair.x)[0])
        fy = self.model(self.shape_inputs(pair.y)[0])
        keep = torch.as_tensor(pair.map_yx >= 0)
        logits = fy[keep] @ fx.T
        return torch.nn.functional.cross_entropy(logits, torch.as_tensor(pair.map_yx[keep]))

    def predict(self, pair):
        fx = self.model(self.shape_inputs(pair.x)[0])
        fy = self.model(self.shape_inputs(pair.y)[0])
        return Match((fy @ fx.T).argmax(1).numpy(), np.ones(pair.y.n_vertices, dtype=bool))


def test_learned_head_trains_saves_and_loads(tmp_path, monkeypatch):
    from geofeat.adapters import head_registry

    monkeypatch.setattr(head_registry, "HEADS", head_registry.HEADS.copy())
    head_registry.register_head("test_affine", f"{__name__}:_AffineHead")
    head = _AffineHead(descriptor="wks", n_eig=40, epochs=3, lr=1e-2, cosine_annealing=True, progress=False)
    pairs = [_pair(0), _pair(1)]
    with pytest.raises(HeadError, match="no model yet"):
        head.save(tmp_path / "early")
    losses = head.fit(pairs)
    assert len(losses) == 6 and losses[-1] < losses[0]
    head.save(tmp_path / "head")
    again = load_head(tmp_path / "head")
    assert isinstance(again, _AffineHead) and again.config == head.config
    np.testing.assert_array_equal(again.match(pairs[0]).map_yx, head.match(pairs[0]).map_yx)
    with pytest.raises(HeadError, match="no training pairs"):
        head.fit([])


class _PickyHead(_AffineHead):
    """Refuses the pairs of bumpy1, as a head refuses pairs without any correspondence."""

    name = "test_picky"

    def training_loss(self, pair):
        if pair.x.name == "bumpy1":
            raise UnusablePair(f"pair {pair.name}: nothing to learn from")
        return super().training_loss(pair)


def test_fit_skips_unusable_pairs(caplog):
    import logging

    caplog.set_level(logging.INFO, logger="geofeat.adapters.learned")
    head = _PickyHead(descriptor="wks", n_eig=40, epochs=2, progress=False)
    losses = head.fit([_pair(0), _pair(1)])
    assert len(losses) == 2  # the bumpy1 pair skipped in both epochs
    assert "skipped a training pair" in caplog.text


class _DivergingHead(_AffineHead):
    """Its loss turns to NaN from the third step on, as a diverging training run's does."""

    name = "test_diverging"

    def __init__(self, **settings):
        super().__init__(**settings)
        self.steps = 0

    def training_loss(self, pair):
        self.steps += 1
        loss = super().training_loss(pair)
        return loss * float("nan") if self.steps >= 3 else loss


def test_fit_refuses_a_loss_that_is_not_finite():
    head = _DivergingHead(descriptor="wks", n_eig=40, epochs=3, progress=False)
    with pytest.raises(HeadError, match="not finite .* at step 3"):
        head.fit([_pair(0), _pair(1)])


def test_setting_checks_name_the_setting_and_keep_their_bounds():
    from geofeat.adapters.base import check_integers, check_numbers

    config = HeadConfig(n_eig=0, lr=float("inf"))
    with pytest.raises(HeadError, match="test: n_eig must be an integer >= 1; found 0"):
        check_integers("test", config, ("epochs", "n_eig"), 1)
    check_integers("test", config, ("n_eig",), 0)
    with pytest.raises(HeadError, match="lr must be a finite number >= 0"):
        check_numbers("test", config, ("lr",), 0.0)
    config = HeadConfig(lr=1.0)
    check_numbers("test", config, ("lr",), 0.0, 1.0)
    with pytest.raises(HeadError, match=r"lr must be a finite number in \(0.0, 1.0\)"):
        check_numbers("test", config, ("lr",), 0.0, 1.0, low_open=True, high_open=True)


def test_head_names_follow_the_registry_rules(monkeypatch):
    from geofeat.adapters import head_registry
    from geofeat.adapters.matchers import NearestNeighbourHead

    assert head_registry.head_class("NN") is NearestNeighbourHead
    assert isinstance(make_head(" FMap ", k=10), FunctionalMapHead)
    assert {"nn", "fmap", "ulrssm", "dpfm", "echomatch"} <= set(head_registry.HEADS.names())
    monkeypatch.setattr(head_registry, "HEADS", head_registry.HEADS.copy())
    with pytest.raises(HeadError, match="already registered; pass overwrite=True"):
        head_registry.register_head("nn", FunctionalMapHead)
    head_registry.register_head("Test-Affine", _AffineHead, summary="a test head")
    assert head_registry.head_class("test_affine") is _AffineHead
    head_registry.register_head("test_affine", f"{__name__}:_PickyHead", overwrite=True)
    assert head_registry.head_class("TEST_AFFINE") is _PickyHead
    with pytest.raises(HeadError, match="unknown head 'test_afine'.*test_affine"):
        make_head("test_afine")


def test_saved_folder_layout_and_a_folder_of_another_layout(tmp_path, monkeypatch):
    import json

    from safetensors.torch import save_file

    from geofeat.adapters import head_registry

    monkeypatch.setattr(head_registry, "HEADS", head_registry.HEADS.copy())
    head_registry.register_head("test_affine", f"{__name__}:_AffineHead")
    head = _AffineHead(descriptor="xyz", n_eig=40, progress=False)
    head._ensure_model(_pair().x)
    head.save(tmp_path / "new")
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == ["config.json", "weights.safetensors"]
    saved = json.loads((tmp_path / "new" / "config.json").read_text())
    assert saved["kind"] == "head" and saved["info"] == {"head": "test_affine", "in_channels": 3}
    assert saved["config"] == head.config.to_dict()
    make_head("fmap", k=12).save(tmp_path / "fmap")
    assert [p.name for p in (tmp_path / "fmap").iterdir()] == ["config.json"]
    assert load_head(tmp_path / "fmap").config.k == 12
    with pytest.raises(HeadError, match="preset 'reference' only applies with a release checkpoint"):
        load_head(tmp_path / "fmap", preset="reference")
    with pytest.raises(HeadError, match=r"settings \['k'\] only apply with a release checkpoint"):
        load_head(tmp_path / "fmap", k=3)

    old = tmp_path / "old"  # head_config.json + weights.safetensors: not read, refused with a message
    old.mkdir()
    (old / "head_config.json").write_text(
        json.dumps({"head": "test_affine", "geofeat_version": "0.9", "config": head.config.to_dict()})
    )
    state = {k: v.contiguous() for k, v in head.model.state_dict().items()}
    save_file(state, str(old / "weights.safetensors"), metadata={"in_channels": "3"})
    with pytest.raises(
        HeadError,
        match=r"holds a head as head_config.json \+ weights.safetensors, a layout this geofeat does not read; expected a "
        r"'head' as config.json \+ weights.safetensors .* Save it again",
    ):
        load_head(old)
    with pytest.raises(HeadError, match="holds a 'lora', not a 'head'"):
        saved["kind"] = "lora"
        (tmp_path / "new" / "config.json").write_text(json.dumps(saved))
        load_head(tmp_path / "new")
