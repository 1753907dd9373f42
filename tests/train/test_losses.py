"""Geodesic-weighted and plain PointInfoNCE against hand computations on a tiny example."""

from __future__ import annotations

import math

import pytest
import torch

from geofeat.errors import GeofeatError, TrainingError
from geofeat.train import geodesic_point_info_nce, observed_rows, point_info_nce

S = 1 / math.sqrt(2)


def lse(*values: float) -> float:
    return math.log(sum(math.exp(v) for v in values))


@pytest.fixture()
def tiny() -> dict[str, torch.Tensor]:
    """3 partial and 4 full vertices, C = 2; full 3 is (0, 2), i.e. (0, 1) once normalised."""
    return {
        "feat_partial": torch.tensor([[2.0, 0.0], [0.0, -3.0], [1.0, 1.0]]),
        "feat_full": torch.tensor([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, 2.0]]),
        "gt_full_index": torch.tensor([0, 1, 3]),
        "geodesic_full": 0.25 * torch.tensor([[0.0, 1, 2, 1], [1, 0, 1, 2], [2, 1, 0, 1], [1, 2, 1, 0]]),
    }


# Hand computation, T = 0.1, weights 0.5 + d(gt, j); logits = [positive, weighted negatives] / T.
# p0 = (1, 0), gt 0: cos with full = [1, 0, -1, 0], weights [.5, .75, 1, .75] -> [10 | 5, 0, -10, 0]
# p1 = (0, -1), gt 1: cos = [0, -1, 0, -1], weights [.75, .5, .75, 1]       -> [-10 | 0, -5, 0, -10]
# p2 = (s, s), gt 3: cos = [s, s, -s, s], weights [.75, 1, .75, .5]        -> [10s | 7.5s, 10s, -7.5s, 5s]
WEIGHTED = [
    lse(10, 5, 0, -10, 0) - 10,
    lse(-10, 0, -5, 0, -10) + 10,
    lse(10 * S, 7.5 * S, 10 * S, -7.5 * S, 5 * S) - 10 * S,
]
# Plain: every weight 1.
PLAIN = [
    lse(10, 10, 0, -10, 0) - 10,
    lse(-10, 0, -10, 0, -10) + 10,
    lse(10 * S, 10 * S, 10 * S, -10 * S, 10 * S) - 10 * S,
]


def mean(values: list[float]) -> float:
    return sum(values) / len(values)


def test_weighted_matches_hand_computation(tiny):
    loss = geodesic_point_info_nce(**tiny)
    assert loss.shape == ()
    assert loss.item() == pytest.approx(mean(WEIGHTED), rel=1e-6)


def test_plain_matches_hand_computation(tiny):
    del tiny["geodesic_full"]
    assert point_info_nce(**tiny).item() == pytest.approx(mean(PLAIN), rel=1e-6)


def test_temperature_and_offset_are_used(tiny):
    # T = 1, offset = 1, p0 only: logits [1 | 1, 1.25 * 0, -1.5, 1.25 * 0]
    tiny["gt_full_index"] = torch.tensor([0, -1, -1])
    loss = geodesic_point_info_nce(**tiny, temperature=1.0, offset=1.0)
    assert loss.item() == pytest.approx(lse(1, 1, 0, -1.5, 0) - 1, rel=1e-6)


def test_unseen_partial_vertices_are_ignored_exactly(tiny):
    tiny["feat_partial"][1] = float("nan")  # never read
    loss = geodesic_point_info_nce(**tiny, seen_partial=torch.tensor([True, False, True]))
    assert loss.item() == pytest.approx(mean([WEIGHTED[0], WEIGHTED[2]]), rel=1e-6)


def test_minus_one_counterparts_are_ignored(tiny):
    tiny["feat_partial"][2] = float("nan")
    tiny["gt_full_index"] = torch.tensor([0, 1, -1])
    assert geodesic_point_info_nce(**tiny).item() == pytest.approx(mean(WEIGHTED[:2]), rel=1e-6)


def test_unseen_full_zero_mode_gives_logit_zero(tiny):
    # full 2 unseen: its feature counts as zero (the authors' convention), logit 0 for every query
    tiny["feat_full"][2] = float("nan")
    loss = geodesic_point_info_nce(**tiny, seen_full=torch.tensor([True, True, False, True]))
    expected = [
        lse(10, 5, 0, 0, 0) - 10,
        lse(-10, 0, -5, 0, -10) + 10,
        lse(10 * S, 7.5 * S, 10 * S, 0, 5 * S) - 10 * S,
    ]
    assert loss.item() == pytest.approx(mean(expected), rel=1e-6)


def test_unseen_full_drop_mode_removes_negatives_and_queries(tiny):
    tiny["feat_full"][2] = float("nan")
    tiny["feat_full"][3] = float("nan")  # gt of p2: p2 is no query
    seen_full = torch.tensor([True, True, False, False])
    loss = geodesic_point_info_nce(**tiny, seen_full=seen_full, unseen_full="drop")
    expected = [lse(10, 5, 0) - 10, lse(-10, 0, -5) + 10]
    assert loss.item() == pytest.approx(mean(expected), rel=1e-6)


def test_observed_rows():
    feats = torch.tensor([[0.0, 0.0], [1.0, -1.0], [0.0, 2.0]])
    assert observed_rows(feats).tolist() == [False, True, True]


def random_pair(n_full: int = 60, n_partial: int = 40, channels: int = 8):
    gen = torch.Generator().manual_seed(0)
    feat_full = torch.randn(n_full, channels, generator=gen)
    gt = torch.randperm(n_full, generator=gen)[:n_partial]
    feat_partial = feat_full[gt] + 0.05 * torch.randn(n_partial, channels, generator=gen)
    points = torch.randn(n_full, 3, generator=gen)
    geodesic = torch.cdist(points, points) / 4
    return feat_partial, feat_full, gt, geodesic


def test_perfect_features_beat_shuffled_ones():
    feat_partial, feat_full, gt, geodesic = random_pair()
    shuffled = feat_partial[torch.randperm(len(gt), generator=torch.Generator().manual_seed(1))]
    good = geodesic_point_info_nce(feat_partial, feat_full, gt, geodesic)
    bad = geodesic_point_info_nce(shuffled, feat_full, gt, geodesic)
    assert good < bad - 1.0
    assert point_info_nce(feat_partial, feat_full, gt) < point_info_nce(shuffled, feat_full, gt) - 1.0


@pytest.mark.parametrize("weighted", [True, False])
def test_gradient_flows_to_both_feature_matrices(weighted):
    feat_partial, feat_full, gt, geodesic = random_pair()
    feat_partial.requires_grad_(True)
    feat_full.requires_grad_(True)
    seen_full = torch.ones(len(feat_full), dtype=torch.bool)
    seen_full[:5] = False
    if weighted:
        loss = geodesic_point_info_nce(feat_partial, feat_full, gt, geodesic, seen_full=seen_full)
    else:
        loss = point_info_nce(feat_partial, feat_full, gt, seen_full=seen_full)
    loss.backward()
    for grad in (feat_partial.grad, feat_full.grad):
        assert torch.isfinite(grad).all() and grad.abs().sum() > 0
    assert feat_full.grad[:5].abs().sum() == 0  # unseen full vertices get no gradient


def test_weighting_acts_on_negatives_only():
    feat_partial, feat_full, gt, geodesic = random_pair()
    plain = point_info_nce(feat_partial, feat_full, gt)
    # weight 1 on every negative (offset 1, distance 0) is exactly the plain loss: the positive is never weighted
    unit = geodesic_point_info_nce(feat_partial, feat_full, gt, torch.zeros_like(geodesic), offset=1.0)
    assert unit.item() == pytest.approx(plain.item(), rel=1e-6)
    assert geodesic_point_info_nce(feat_partial, feat_full, gt, geodesic).item() != pytest.approx(plain.item(), rel=1e-3)
    # only the rows of ground-truth vertices are read
    unused = torch.ones(len(feat_full), dtype=torch.bool)
    unused[gt] = False
    changed = geodesic.clone()
    changed[unused] = 123.0
    same = geodesic_point_info_nce(feat_partial, feat_full, gt, changed)
    assert same.item() == geodesic_point_info_nce(feat_partial, feat_full, gt, geodesic).item()


def test_float64_features_stay_float64(tiny):
    tiny = {k: (v.double() if v.is_floating_point() else v) for k, v in tiny.items()}
    loss = geodesic_point_info_nce(**tiny)
    assert loss.dtype == torch.float64
    assert loss.item() == pytest.approx(mean(WEIGHTED), rel=1e-12)


def bad_inputs(tiny):
    yield {"feat_partial": tiny["feat_partial"][0]}
    yield {"feat_full": tiny["feat_full"][:, :1]}
    yield {"feat_full": tiny["feat_full"][:0]}
    yield {"feat_partial": tiny["feat_partial"].long()}
    yield {"gt_full_index": tiny["gt_full_index"][:2]}
    yield {"gt_full_index": tiny["gt_full_index"].float()}
    yield {"gt_full_index": torch.tensor([0, 4, 1])}
    yield {"gt_full_index": torch.tensor([0, -2, 1])}
    yield {"gt_full_index": torch.tensor([-1, -1, -1])}
    yield {"geodesic_full": tiny["geodesic_full"][:3]}
    yield {"geodesic_full": tiny["geodesic_full"].numpy()}
    yield {"geodesic_full": torch.full((4, 4), float("inf"))}
    yield {"geodesic_full": -tiny["geodesic_full"]}
    yield {"seen_partial": torch.tensor([1, 0, 1])}
    yield {"seen_partial": torch.tensor([True, False])}
    yield {"seen_partial": torch.zeros(3, dtype=torch.bool)}
    yield {"seen_full": torch.ones(3, dtype=torch.bool)}
    yield {"temperature": 0.0}
    yield {"offset": float("nan")}
    yield {"unseen_full": "ignore"}


def test_bad_inputs_raise_training_error(tiny):
    for change in bad_inputs(tiny):
        with pytest.raises(TrainingError) as info:
            geodesic_point_info_nce(**{**tiny, **change})
        assert isinstance(info.value, GeofeatError) and isinstance(info.value, ValueError)


def test_plain_checks_its_inputs(tiny):
    with pytest.raises(TrainingError, match="channels"):
        point_info_nce(tiny["feat_partial"], tiny["feat_full"][:, :1], tiny["gt_full_index"])
