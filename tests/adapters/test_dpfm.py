"""The DPFM head: sampling, supervision, training, matching, checkpoints and settings."""

import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.adapters.blocks import fmap_layers as fl
from geofeat.adapters.blocks.operators import surface_operators
from geofeat.adapters.dpfm import DPFMConfig, DPFMHead
from geofeat.adapters.dpfm.losses import ground_truth_fmap, weighted_overlap_bce
from geofeat.adapters.dpfm.sampling import sample_interpolation
from geofeat.adapters.heads import load_head, make_head
from geofeat.adapters.inputs import ground_truth_overlaps
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError, UnusablePair
from geofeat.geometry import make_partial

#: CPU-sized settings: a small network on 642-vertex shapes.
SMALL = dict(
    descriptor="wks",
    descriptor_params={"n_descr": 16},
    n_eig=30,
    n_fmap=20,
    width=16,
    n_blocks=2,
    dropout=False,
    attention_dim=16,
    n_heads=2,
    sampling_ratio=0.25,
    lr=5e-3,
    nce_pairs=128,
    progress=False,
)
STEPS = 40


def _pair(seed: int = 0) -> ShapePair:
    mesh = bumpy(seed, 3)
    partial = make_partial(mesh, "cuts", seed=seed)
    return ShapePair(x=mesh, y=partial.mesh, map_yx=np.asarray(partial.vertex_map, dtype=np.int64), protocol="p2f")


@pytest.fixture(scope="module")
def pair() -> ShapePair:
    return _pair(0)


@pytest.fixture(scope="module")
def trained(pair):
    """A small head overfitted on one pair, and its losses."""
    head = DPFMHead(**SMALL, epochs=STEPS)
    losses = head.fit([pair])
    return head, losses


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max(1, (a | b).sum()))


# ----------------------------------------------------------------------------- sampling


def test_sample_interpolation_refuses_no_samples():
    points = bumpy(0, 3).verts
    with pytest.raises(HeadError, match="n_samples"):
        sample_interpolation(points, 0)


def test_sample_interpolation_reproduces_sampled_values():
    points = bumpy(1, 3).verts
    interp = sample_interpolation(points, 50, n_neighbours=3, seed=0)
    assert interp.neighbours.shape == (len(points), 3) and interp.weights.dtype == torch.float32
    torch.testing.assert_close(interp.weights.sum(1), torch.ones(len(points)))
    values = torch.randn(50, 4)
    out = interp.interpolate(values)
    assert out.shape == (len(points), 4)
    torch.testing.assert_close(out[interp.samples], values, atol=1e-5, rtol=1e-5)


# ----------------------------------------------------------------------------- supervision


def test_ground_truth_overlaps_and_fmap(pair):
    overlap_x, overlap_y = ground_truth_overlaps(pair)
    assert overlap_y.all() and overlap_x.sum() == pair.y.n_vertices
    assert overlap_x[pair.map_yx].all()
    ops_x, ops_y = surface_operators(pair.x, 20), surface_operators(pair.y, 20)
    full = ground_truth_fmap(pair.map_yx, ops_x.evecs, ops_y.evecs, ops_y.mass)
    torch.testing.assert_close(full, fl.pointmap_to_fmap(pair.map_yx, ops_x.evecs, ops_y.evecs, ops_y.mass))
    # vertices without a counterpart contribute nothing, and are not overlap
    cut = pair.map_yx.copy()
    cut[:100] = -1
    partial = ShapePair(x=pair.x, y=pair.y, map_yx=cut, protocol="p2p")
    px, py = ground_truth_overlaps(partial)
    assert not py[:100].any() and py[100:].all() and px.sum() == pair.y.n_vertices - 100
    c_cut = ground_truth_fmap(cut, ops_x.evecs, ops_y.evecs, ops_y.mass)
    pulled = ops_x.evecs[torch.as_tensor(np.array(pair.map_yx))]
    pulled[:100] = 0
    torch.testing.assert_close(c_cut, ops_y.evecs.T @ (ops_y.mass[:, None] * pulled))


def test_weighted_overlap_bce_balances_classes():
    logits = torch.tensor([2.0, -1.0, 0.5, 0.0])
    target = torch.tensor([True, False, False, False])
    bce = torch.nn.functional.binary_cross_entropy_with_logits(logits, target.float(), reduction="none")
    expected = (torch.tensor([0.75, 0.25, 0.25, 0.25]) * bce).mean()
    torch.testing.assert_close(weighted_overlap_bce(logits, target), expected)
    ones = torch.ones(4, dtype=torch.bool)
    assert float(weighted_overlap_bce(logits, ones, single_class_weight=0.0)) == 0.0  # the reference's weights
    assert float(weighted_overlap_bce(logits, ones, single_class_weight=0.5)) > 0.0


# ----------------------------------------------------------------------------- training and matching


def test_loss_is_finite_and_decreases(trained):
    _, losses = trained
    assert len(losses) == STEPS and np.isfinite(losses).all()
    assert np.mean(losses[-5:]) < 0.5 * losses[0]


def test_match_gives_right_shapes_and_dtypes(trained, pair):
    head, _ = trained
    match = head.match(pair)
    assert isinstance(match, Match)
    assert match.map_yx.shape == (pair.y.n_vertices,) and match.map_yx.dtype == np.int64
    assert match.map_yx.min() >= 0 and match.map_yx.max() < pair.x.n_vertices
    assert match.overlap_y.shape == (pair.y.n_vertices,) and match.overlap_y.dtype == bool
    assert match.overlap_x.shape == (pair.x.n_vertices,) and match.overlap_x.dtype == bool


@pytest.mark.numerically_sensitive
def test_overlap_prediction_learns_on_one_pair(pair):
    # the overlap terms alone (on a tiny network the functional-map term dominates the first hundreds of steps)
    head = DPFMHead(**dict(SMALL, descriptor_params={}, w_fmap=0.0, w_nce=0.0), epochs=150)
    overlap_x, overlap_y = ground_truth_overlaps(pair)
    everything = _iou(np.ones_like(overlap_x), overlap_x)  # what "all overlap" scores
    head.fit([pair])
    match = head.match(pair)
    # 0.85-0.98 depending on the BLAS thread count (float summation order); all-overlap scores far less
    assert _iou(match.overlap_x, overlap_x) > max(0.75, everything + 0.2)
    assert match.overlap_y.mean() > 0.9
    # the masks are the probabilities the match carries, thresholded at overlap_threshold
    assert match.overlap_prob_x.shape == (pair.x.n_vertices,) and match.overlap_prob_y.shape == (pair.y.n_vertices,)
    np.testing.assert_array_equal(match.overlap_prob_x > head.config.overlap_threshold, match.overlap_x)


def test_save_and_load_give_identical_predictions(trained, pair, tmp_path):
    head, _ = trained
    head.save(tmp_path / "dpfm")
    loaded = load_head(tmp_path / "dpfm")
    assert isinstance(loaded, DPFMHead) and loaded.config == head.config
    a, b = head.match(pair), loaded.match(pair)
    np.testing.assert_array_equal(a.map_yx, b.map_yx)
    np.testing.assert_array_equal(a.overlap_y, b.overlap_y)
    np.testing.assert_array_equal(a.overlap_x, b.overlap_x)


def test_registered_variants_and_partial_ground_truth(pair):
    cut = pair.map_yx.copy()
    cut[::7] = -1  # some vertices of y without counterpart (P2P-like ground truth)
    partial = ShapePair(x=pair.x, y=pair.y, map_yx=cut, protocol="p2p")
    settings = dict(SMALL, sampling_ratio=1.0, n_attention_layers=2, w_nce=1.0, pointmap="features", overlap_weighted_fmap=True)
    head = make_head("dpfm", **settings)
    assert isinstance(head, DPFMHead) and isinstance(head.config, DPFMConfig)
    losses = head.fit([partial])
    assert len(losses) == 1 and np.isfinite(losses).all()
    match = head.match(partial)
    assert match.map_yx.shape == (pair.y.n_vertices,) and match.overlap_x.shape == (pair.x.n_vertices,)


@pytest.mark.parametrize(
    "settings, message",
    [
        (dict(sampling_ratio=0.0), "sampling_ratio"),
        (dict(attention_dim=10, n_heads=4), "divide"),
        (dict(n_fmap=60, n_eig=30), "n_fmap"),
        (dict(fmap_features="magic"), "fmap_features"),
        (dict(pointmap="magic"), "pointmap"),
        (dict(width=0), "width"),
        (dict(lambda_=-1.0), "lambda_"),
        (dict(overlap_threshold=1.0), "overlap_threshold"),
        (dict(max_samples=0), "max_samples"),
        (dict(colour="red"), "unknown setting"),
    ],
)
def test_bad_settings_raise(settings, message):
    with pytest.raises(HeadError, match=message):
        DPFMHead(**settings)


def test_bad_pairs_raise(pair):
    head = DPFMHead(**SMALL)
    with pytest.raises(HeadError, match="map_yx"):
        head.training_loss(ShapePair(x=pair.x, y=pair.y, map_yx=pair.map_yx[:-1]))
    with pytest.raises(UnusablePair, match="no correspondence"):
        head.training_loss(ShapePair(x=pair.x, y=pair.y, map_yx=np.full(pair.y.n_vertices, -1)))
