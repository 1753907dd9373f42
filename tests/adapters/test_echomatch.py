"""EchoMatch head: correspondence reflection, losses, training, prediction and checkpoints on small partial-to-partial pairs."""

import dataclasses

import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.adapters.echomatch.config import EchoMatchConfig
from geofeat.adapters.echomatch.head import EchoMatchHead
from geofeat.adapters.echomatch.networks import EchoMatchNet
from geofeat.adapters.echomatch.reflection import (
    correspondence_reflection,
    pointmap_matrix,
    reflection_features,
    round_trip_error,
    sampled_reflection,
    spatial_neighbours,
)
from geofeat.adapters.heads import load_head, make_head
from geofeat.adapters.inputs import ground_truth_overlaps
from geofeat.datasets.records import ShapePair
from geofeat.errors import HeadError
from geofeat.evaluation.metrics import overlap_iou
from geofeat.geometry import make_partial

#: CPU-sized settings (the paper's sizes are the defaults).
SMALL = dict(
    descriptor="wks",
    descriptor_params={"n_eig": 24, "n_descr": 16},
    n_eig=24,
    n_fmap=16,
    feature_channels=16,
    width=16,
    n_blocks=2,
    overlap_width=8,
    overlap_blocks=1,
    n_neighbours=16,
    dropout=0.0,
    epochs=20,
    lr=5e-3,
    progress=False,
)


def _index_map(from_vertices: np.ndarray, to_vertices: np.ndarray) -> np.ndarray:
    """For each source index in ``from_vertices`` its position in the sorted ``to_vertices``, or -1."""
    pos = np.clip(np.searchsorted(to_vertices, from_vertices), 0, len(to_vertices) - 1)
    return np.where(to_vertices[pos] == from_vertices, pos, -1).astype(np.int64)


class P2PPair:
    """Two cuts of one bumpy mesh: ``x`` and ``y`` with the exact maps both ways and the overlaps."""

    def __init__(self, mesh_seed=0, seed_x=3, seed_y=4):
        mesh = bumpy(mesh_seed, 3)
        part_x = make_partial(mesh, "cuts", seed=seed_x, keep_range=(0.4, 0.65))
        part_y = make_partial(mesh, "cuts", seed=seed_y, keep_range=(0.4, 0.65))
        self.x, self.y = part_x.mesh, part_y.mesh
        self.map_yx = _index_map(part_y.vertex_map, part_x.vertex_map)
        self.map_xy = _index_map(part_x.vertex_map, part_y.vertex_map)
        self.overlap_x, self.overlap_y = self.map_xy >= 0, self.map_yx >= 0
        self.pair = ShapePair(self.x, self.y, self.map_yx, self.overlap_x, self.overlap_y, protocol="p2p")


@pytest.fixture(scope="module")
def p2p():
    return P2PPair()


@pytest.fixture(scope="module")
def trained(p2p):
    """A small head overfitted on the pair, with the IoU of its overlaps before and after.

    The overlap loss starts to fall only after 50 to 70 epochs (once the soft maps are sharp):
    200 epochs end well past that on every seed and thread count tried, where 100
    stopped inside it and the IoU depended on the trajectory.
    """
    settings = {**SMALL, "epochs": 200, "lr": 1e-2, "overlap_width": 16, "overlap_blocks": 2, "w_nce_cross": 1.0}
    head = make_head("echomatch", **settings)
    before = head.match(p2p.pair)
    losses = head.fit([p2p.pair])
    return head, before, losses


def _iou(match, p2p):
    return 0.5 * (overlap_iou(match.overlap_x, p2p.overlap_x) + overlap_iou(match.overlap_y, p2p.overlap_y))


def test_pair_is_a_real_partial_to_partial_pair(p2p):
    assert 0 < p2p.overlap_x.sum() < p2p.x.n_vertices and 0 < p2p.overlap_y.sum() < p2p.y.n_vertices
    ok = p2p.overlap_y
    assert np.array_equal(p2p.map_xy[p2p.map_yx[ok]], np.flatnonzero(ok))


def test_reflection_of_exact_map_is_identity_and_of_random_map_is_not(p2p):
    n_x, n_y = p2p.x.n_vertices, p2p.y.n_vertices
    reflection = correspondence_reflection(pointmap_matrix(p2p.map_xy, n_y), pointmap_matrix(p2p.map_yx, n_x))
    eye = torch.eye(n_x)
    ov = torch.as_tensor(p2p.overlap_x)
    assert torch.equal(reflection[ov], eye[ov])
    assert float(round_trip_error(reflection, p2p.x.verts, p2p.overlap_x)) == 0.0
    nbrs = torch.as_tensor(spatial_neighbours(p2p.x.verts, 8))
    scores = reflection_features(torch.gather(reflection, 1, nbrs), width=10)
    assert scores.shape == (n_x, 10)
    assert torch.equal(scores[ov, 0], torch.ones(int(ov.sum())))
    assert float(scores[ov, 1:].abs().sum()) == 0.0

    rng = np.random.default_rng(0)
    random = correspondence_reflection(
        pointmap_matrix(rng.integers(0, n_y, n_x), n_y), pointmap_matrix(rng.integers(0, n_x, n_y), n_x)
    )
    assert not torch.equal(random[ov], eye[ov])
    scale = float(np.linalg.norm(p2p.x.verts - p2p.x.verts.mean(0), axis=1).mean())
    assert float(round_trip_error(random, p2p.x.verts, p2p.overlap_x)) > 0.3 * scale


def test_sampled_reflection_matches_the_dense_product_and_its_gradient():
    g = torch.Generator().manual_seed(0)
    p_xy = torch.softmax(torch.randn(7, 5, generator=g, dtype=torch.float64), dim=1).requires_grad_()
    p_yx = torch.softmax(torch.randn(5, 7, generator=g, dtype=torch.float64), dim=1).requires_grad_()
    nbrs = torch.stack([torch.randperm(7, generator=g)[:3] for _ in range(7)])
    dense = torch.gather(correspondence_reflection(p_xy, p_yx), 1, nbrs)
    assert torch.allclose(sampled_reflection(p_xy, p_yx, nbrs), dense)
    assert torch.autograd.gradcheck(lambda a, b: sampled_reflection(a, b, nbrs), (p_xy, p_yx))


def test_neighbours_start_with_the_vertex_itself(p2p):
    nbrs = spatial_neighbours(p2p.x.verts, 5)
    assert nbrs.shape == (p2p.x.n_vertices, 5) and nbrs.dtype == np.int64
    assert np.array_equal(nbrs[:, 0], np.arange(p2p.x.n_vertices))
    assert spatial_neighbours(p2p.x.verts[:3], 5).shape == (3, 3)
    doubled = spatial_neighbours(np.concatenate([p2p.x.verts, p2p.x.verts]), 4)  # every vertex twice
    assert np.array_equal(doubled[:, 0], np.arange(2 * p2p.x.n_vertices))
    assert all(len(set(row)) == 4 for row in doubled)


def test_overlaps_are_derived_from_the_map_when_missing(p2p):
    bare = ShapePair(p2p.x, p2p.y, p2p.map_yx, protocol="p2p")
    overlap_x, overlap_y = ground_truth_overlaps(bare)
    assert np.array_equal(overlap_x, p2p.overlap_x) and np.array_equal(overlap_y, p2p.overlap_y)
    head = EchoMatchHead(EchoMatchConfig(**SMALL))
    terms = head.loss_terms(bare)
    assert set(terms) == {"fmap", "overlap", "nce_cross", "nce_self"}
    assert all(torch.isfinite(t) and t.ndim == 0 for t in terms.values())


def test_loss_is_finite_and_decreases(p2p):
    head = make_head("echomatch", **SMALL)
    losses = head.fit([p2p.pair])
    assert len(losses) == SMALL["epochs"] and np.all(np.isfinite(losses))
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:5])


@pytest.mark.numerically_sensitive
def test_overlap_iou_improves_when_overfitting(p2p, trained):
    head, before, losses = trained
    after = head.match(p2p.pair)
    assert _iou(after, p2p) > _iou(before, p2p) + 0.1
    assert _iou(after, p2p) > 0.75
    assert np.mean(losses[-10:]) < np.mean(losses[:10])


def test_learned_temperature_is_positive_and_moves_by_ratios():
    """Any parameter value gives a positive temperature, strictly increasing in it (no clamp plateau)."""
    log_net = EchoMatchNet(3, EchoMatchConfig(**SMALL))
    raw_net = EchoMatchNet(3, EchoMatchConfig(**SMALL, learn_log_temperature=False))
    assert float(log_net.temperature_value().detach()) == pytest.approx(0.1) == float(raw_net.temperature_value().detach())
    values = []
    with torch.no_grad():
        for p in (-30.0, -3.0, -0.5, 0.0, 2.0):
            log_net.log_temperature.fill_(p)
            values.append(float(log_net.temperature_value()))
    assert all(v > 0 for v in values) and bool(np.all(np.diff(values) > 0))
    # an Adam step changes the temperature by a ratio of about exp(lr), whatever its size
    optimizer = torch.optim.Adam(log_net.parameters(), lr=0.1)
    with torch.no_grad():
        log_net.log_temperature.fill_(np.log(1e-3))
    log_net.temperature_value().sum().backward()
    optimizer.step()
    assert float(log_net.temperature_value().detach()) == pytest.approx(1e-3 * np.exp(-0.1), rel=1e-4)


def test_match_shapes_and_dtypes(p2p, trained):
    head = trained[0]
    match = head.match(p2p.pair)
    assert match.map_yx.shape == (p2p.y.n_vertices,) and match.map_yx.dtype == np.int64
    assert match.map_yx.min() >= 0 and match.map_yx.max() < p2p.x.n_vertices
    assert match.overlap_y.shape == (p2p.y.n_vertices,) and match.overlap_y.dtype == bool
    assert match.overlap_x.shape == (p2p.x.n_vertices,) and match.overlap_x.dtype == bool
    prob_x, prob_y = head.overlap_probabilities(p2p.pair)
    assert np.array_equal(prob_x > 0.5, match.overlap_x) and np.array_equal(prob_y > 0.5, match.overlap_y)
    restricted = EchoMatchHead(dataclasses.replace(head.config, restrict_to_overlap=True))
    restricted.model, restricted.in_channels = head.model, head.in_channels
    mapped = restricted.match(p2p.pair).map_yx
    if match.overlap_x.any():
        assert match.overlap_x[mapped].all()


def test_save_load_round_trip(p2p, trained, tmp_path):
    head = trained[0]
    head.save(tmp_path / "echo")
    loaded = load_head(tmp_path / "echo")
    assert isinstance(loaded, EchoMatchHead) and loaded.config == head.config
    a, b = head.match(p2p.pair), loaded.match(p2p.pair)
    assert np.array_equal(a.map_yx, b.map_yx)
    assert np.array_equal(a.overlap_x, b.overlap_x) and np.array_equal(a.overlap_y, b.overlap_y)


@pytest.mark.parametrize(
    "settings",
    [
        {"n_fmap": 60, "n_eig": 50},
        {"prune_strategy": "x"},
        {"dropout": 1.0},
        {"temperature_init": 0.0},
        {"learn_log_temperature": "false"},
        {"w_nce_self": -1.0},
        {"n_neighbours": 0},
        {"overlap_threshold": 1.5},
        {"no_such_setting": 1},
    ],
)
def test_bad_settings_raise(settings):
    with pytest.raises(HeadError):
        make_head("echomatch", **settings)


def test_bad_pairs_raise(p2p):
    head = make_head("echomatch", **SMALL)
    no_match = ShapePair(p2p.x, p2p.y, np.full(p2p.y.n_vertices, -1), protocol="p2p")
    with pytest.raises(HeadError, match="no correspondence"):
        head.training_loss(no_match)
    short = ShapePair(p2p.x, p2p.y, p2p.map_yx[:-1], protocol="p2p")
    with pytest.raises(HeadError, match="map_yx"):
        head.training_loss(short)
    with pytest.raises(HeadError, match="overlap_x"):
        ground_truth_overlaps(ShapePair(p2p.x, p2p.y, p2p.map_yx, p2p.overlap_x[:-1], p2p.overlap_y))
