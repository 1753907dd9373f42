"""The ULRSSM head: unsupervised loss, training, prediction, test-time adaptation, checkpoints, settings."""

import dataclasses

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from shapes import bumpy

import geofeat
from geofeat.adapters.base import HeadConfig
from geofeat.adapters.blocks.functional_maps import nearest_neighbors
from geofeat.adapters.heads import load_head, make_head
from geofeat.adapters.ulrssm import LOSS_TERMS, ULRSSMConfig, ULRSSMHead
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError
from geofeat.geometry import make_partial

#: CPU-sized settings (the defaults are the paper's: width 128, 256 outputs, 200 eigenfunctions).
SMALL = {
    "descriptor": "wks",
    "descriptor_params": {"n_eig": 40, "n_descr": 16},
    "width": 32,
    "width_out": 32,
    "n_blocks": 2,
    "n_eig": 40,
    "diffusion_eig": 40,
    "n_fmap": 30,
    "dropout": False,
    "tta_steps": 0,
    "progress": False,
}


@pytest.fixture(scope="module")
def full_pair() -> ShapePair:
    """A blob (642 vertices) and an anisotropically stretched, slightly noisy copy of it (identity map)."""
    x = bumpy(0, 3)
    rng = np.random.default_rng(0)
    verts = x.verts * np.array([1.1, 0.95, 1.0]) + rng.normal(scale=2e-3, size=x.verts.shape)
    y = geofeat.Mesh(verts, x.faces, name="bumpy0-stretched")
    return ShapePair(x=x, y=y, map_yx=np.arange(y.n_vertices), protocol="f2f")


@pytest.fixture(scope="module")
def partial_pair() -> ShapePair:
    """A planar cut of a blob matched to the whole blob."""
    x = bumpy(1, 3)
    part = make_partial(x, "cuts", seed=0, keep_range=(0.4, 0.8))
    return ShapePair(x=x, y=part.mesh, map_yx=part.vertex_map.copy(), protocol="p2f")


def state_copy(head: ULRSSMHead) -> dict[str, torch.Tensor]:
    return {name: value.detach().clone() for name, value in head.model.state_dict().items()}


def same_state(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[name], b[name]) for name in a)


def test_registered_and_defaults_are_the_paper_sizes():
    head = make_head("ulrssm", progress=False)
    assert isinstance(head, ULRSSMHead)
    c = head.config
    assert (c.width, c.width_out, c.n_blocks, c.dropout) == (128, 256, 4, True)
    assert (c.n_fmap, c.n_eig, c.diffusion_eig, c.temperature, c.fmap_lambda) == (200, 200, 128, 0.07, 100.0)
    assert (c.w_bij, c.w_orth, c.w_couple, c.w_lap, c.lr, c.cosine_annealing) == (1.0, 1.0, 1.0, 0.0, 1e-3, True)
    assert (c.tta_steps, c.tta_lr, c.grad_clip, c.refine_fmap) == (15, 1e-3, 1.0, True)


def test_loss_is_finite_and_decreases(full_pair):
    head = ULRSSMHead(**SMALL, epochs=20, cosine_annealing=False)
    losses = head.fit([full_pair])
    assert len(losses) == 20
    assert np.all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.9 * losses[0]


def test_loss_terms(full_pair, partial_pair):
    head = ULRSSMHead(**SMALL, w_lap=1e-3)
    head._ensure_model(full_pair.x).eval()
    for pair in (full_pair, partial_pair):
        terms = head.loss_terms(pair)
        assert set(terms) == set(LOSS_TERMS)
        assert all(t.ndim == 0 and torch.isfinite(t) for t in terms.values())
        assert all(float(terms[name].detach()) >= 0 for name in LOSS_TERMS)
        assert terms["total"].requires_grad
    assert float(head.loss_terms(full_pair)["lap"].detach()) > 0
    assert float(head.loss_terms(partial_pair)["lap"].detach()) == 0  # no Laplacian term in the partial loss


def test_partial_variant_is_used_for_partial_protocols(partial_pair):
    head = ULRSSMHead(**SMALL)
    head._ensure_model(partial_pair.x).eval()
    with torch.no_grad():
        loss_p2f = head.training_loss(partial_pair)
        loss_p2p = head.training_loss(dataclasses.replace(partial_pair, protocol="p2p"))
        loss_f2f = head.training_loss(dataclasses.replace(partial_pair, protocol="f2f"))
        partial = head.loss_terms(partial_pair, partial=True)
        full = head.loss_terms(partial_pair, partial=False)
    assert torch.equal(loss_p2f, partial["total"]) and torch.equal(loss_p2p, partial["total"])
    assert torch.equal(loss_f2f, full["total"])
    assert not torch.allclose(partial["total"], full["total"])
    assert not torch.allclose(partial["orth"], full["orth"])


def test_fit_then_match(full_pair, partial_pair):
    head = ULRSSMHead(**SMALL, epochs=2)
    losses = head.fit([full_pair, partial_pair])
    assert len(losses) == 4 and np.all(np.isfinite(losses))
    for pair in (full_pair, partial_pair):
        match = head.match(pair)
        assert isinstance(match, Match)
        assert match.map_yx.shape == (pair.y.n_vertices,) and match.map_yx.dtype == np.int64
        assert match.map_yx.min() >= 0 and match.map_yx.max() < pair.x.n_vertices
        assert match.overlap_y.shape == (pair.y.n_vertices,) and match.overlap_y.dtype == bool
        assert match.overlap_y.all() and match.overlap_x is None


def test_plain_prediction_is_nearest_neighbour_of_normalised_features(partial_pair):
    head = ULRSSMHead(**SMALL, refine_fmap=False)
    model = head._ensure_model(partial_pair.x).eval()
    with torch.no_grad():
        fx = F.normalize(model(*head.shape_inputs(partial_pair.x)), dim=-1).numpy()
        fy = F.normalize(model(*head.shape_inputs(partial_pair.y)), dim=-1).numpy()
    expected = nearest_neighbors(fx, fy)
    np.testing.assert_array_equal(head.match(partial_pair).map_yx, expected)
    refined = ULRSSMHead(dataclasses.replace(head.config, refine_fmap=True))
    refined.in_channels, refined.model = head.in_channels, head.model
    assert refined.match(partial_pair).map_yx.shape == expected.shape


def test_fit_clips_gradients(full_pair, monkeypatch):
    calls = []
    clip = torch.nn.utils.clip_grad_norm_

    def spy(params, max_norm, *args, **kwargs):
        calls.append(max_norm)
        return clip(params, max_norm, *args, **kwargs)

    monkeypatch.setattr(torch.nn.utils, "clip_grad_norm_", spy)
    ULRSSMHead(**SMALL, epochs=2, grad_clip=0.5).fit([full_pair])
    assert calls == [0.5, 0.5]
    ULRSSMHead(**SMALL, epochs=1, grad_clip=None).fit([full_pair])
    assert calls == [0.5, 0.5]


def test_tta_restores_weights_bit_for_bit(partial_pair, monkeypatch):
    head = ULRSSMHead(**{**SMALL, "tta_steps": 3, "tta_lr": 1e-2})
    head.fit([partial_pair])
    before = state_copy(head)
    adapted = []
    adapt, adapt_prepared = head.adapt, head._adapt

    def spy(pair, steps):
        losses = adapt_prepared(pair, steps)
        adapted.append(not same_state(before, state_copy(head)))  # the weights did move
        return losses

    monkeypatch.setattr(head, "_adapt", spy)
    match = head.match(partial_pair)
    assert adapted == [True]
    assert same_state(before, state_copy(head))
    assert all(p.grad is None for p in head.model.parameters())
    # the adapted prediction is that of the adapted weights
    twin = ULRSSMHead(dataclasses.replace(head.config, tta_steps=0))
    twin.in_channels, twin.model = head.in_channels, head.model
    try:
        adapt(partial_pair, 3)
        np.testing.assert_array_equal(twin.match(partial_pair).map_yx, match.map_yx)
    finally:
        head.model.load_state_dict(before)


def test_no_tta_when_steps_is_zero(full_pair, monkeypatch):
    head = ULRSSMHead(**SMALL)
    head.fit([full_pair])
    before = state_copy(head)

    def forbidden(*args, **kwargs):
        raise AssertionError("adapt must not run with tta_steps=0")

    monkeypatch.setattr(head, "adapt", forbidden)
    match = head.match(full_pair)
    with torch.no_grad():
        np.testing.assert_array_equal(head.predict(full_pair).map_yx, match.map_yx)
    assert same_state(before, state_copy(head))


def test_save_load_round_trip(tmp_path, partial_pair):
    head = ULRSSMHead(**{**SMALL, "tta_steps": 2})
    head.fit([partial_pair])
    head.save(tmp_path / "ulrssm")
    loaded = load_head(tmp_path / "ulrssm")
    assert isinstance(loaded, ULRSSMHead) and loaded.config == head.config
    assert same_state(state_copy(head), state_copy(loaded))
    np.testing.assert_array_equal(loaded.match(partial_pair).map_yx, head.match(partial_pair).map_yx)


@pytest.mark.parametrize(
    "settings",
    [
        {"n_fmap": 50, "n_eig": 40},
        {"diffusion_eig": 64, "n_eig": 40},
        {"width": 0},
        {"width_out": 2.5},
        {"temperature": 0.0},
        {"tta_steps": -1},
        {"tta_steps": True},
        {"tta_lr": float("nan")},
        {"w_bij": -1.0},
        {"resolvent_gamma": 1.5},
        {"grad_clip": 0.0},
        {"dropout": 1.5},
        {"refine_fmap": "yes"},
        {"no_such_setting": 1},
    ],
)
def test_bad_settings_raise(settings):
    with pytest.raises(HeadError):
        ULRSSMHead(**{**SMALL, **settings})


def test_bad_config_type_and_adapt_steps(full_pair):
    with pytest.raises(HeadError):
        ULRSSMHead(HeadConfig())
    assert isinstance(ULRSSMHead(ULRSSMConfig(**SMALL)).config, ULRSSMConfig)
    with pytest.raises(HeadError):
        ULRSSMHead(**SMALL).adapt(full_pair, steps=-2)
