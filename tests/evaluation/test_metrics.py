"""Metrics on hand-computed examples: a path graph whose geodesic distance is |i - j|."""

import numpy as np
import pytest

from geofeat.errors import GeofeatError, MetricError
from geofeat.evaluation.metrics import (
    DEFAULT_PCK_THRESHOLDS,
    chirality_accuracy,
    geodesic_errors,
    mean_geodesic_error,
    mean_iou,
    overlap_auc,
    overlap_iou,
    pck_auc,
    pck_curve,
)

N = 5
PATH = np.abs(np.subtract.outer(np.arange(N), np.arange(N))).astype(float)  # path graph 0-1-2-3-4
IDENTITY = np.arange(N)
MIRROR = N - 1 - IDENTITY  # left-right symmetry of the path: i <-> 4 - i


def test_geodesic_errors_hand_computed_and_skip_vertices_without_ground_truth():
    gt = np.array([0, 1, 2, 3, -1])
    pred = np.array([0, 3, 4, 3, 1])
    errors = geodesic_errors(pred, gt, PATH)
    assert errors.dtype == np.float64
    np.testing.assert_array_equal(errors, [0.0, 2.0, 2.0, 0.0])


def test_eval_mask_restricts_the_evaluated_vertices():
    gt = np.array([0, 1, 2, 3, -1])
    pred = np.array([0, 3, 4, 3, 1])
    mask = np.array([False, True, False, True, True])
    np.testing.assert_array_equal(geodesic_errors(pred, gt, PATH, eval_mask=mask), [2.0, 0.0])


def test_perfect_map_has_zero_error_and_unit_auc():
    errors = geodesic_errors(IDENTITY, IDENTITY, PATH)
    assert mean_geodesic_error(errors) == 0.0
    assert pck_auc(errors) == pytest.approx(1.0)


def test_unmatched_prediction_counts_as_the_worst_error_at_that_vertex():
    gt = np.array([0, 1, 2, 3, 4])
    pred = np.array([0, -1, 2, 3, -1])
    # worst possible error at vertex 1 is d(1, 4) = 3, at vertex 4 it is d(4, 0) = 4
    np.testing.assert_array_equal(geodesic_errors(pred, gt, PATH), [0.0, 3.0, 0.0, 0.0, 4.0])
    with pytest.raises(MetricError, match="no predicted match"):
        geodesic_errors(pred, gt, PATH, unmatched="raise")


def test_match_in_another_component_counts_as_the_worst_finite_error():
    dist = PATH.copy()
    dist[:4, 4] = dist[4, :4] = np.inf  # vertex 4 is a separate component
    errors = geodesic_errors(np.array([4, 1]), np.array([0, 1]), dist)
    np.testing.assert_array_equal(errors, [3.0, 0.0])


def test_mean_is_pooled_over_vertices_not_averaged_over_pairs():
    pair_a = geodesic_errors(IDENTITY[:3], IDENTITY[:3], PATH)  # three vertices, error 0
    pair_b = geodesic_errors(np.array([1]), np.array([0]), PATH)  # one vertex, error 1
    assert mean_geodesic_error([pair_a, pair_b]) == pytest.approx(25.0)  # 100 * 1 / 4, not 100 * (0 + 1) / 2
    assert mean_geodesic_error([pair_a, pair_b], scale=1.0) == pytest.approx(0.25)
    assert mean_geodesic_error(pair_b) == pytest.approx(100.0)


def test_pck_curve_and_auc_hand_computed():
    errors = np.array([0.0, 0.1, 0.2, 0.3])
    grid, fractions = pck_curve(errors, thresholds=[0.0, 0.1, 0.2])
    np.testing.assert_allclose(fractions, [0.25, 0.5, 0.75])
    np.testing.assert_allclose(grid, [0.0, 0.1, 0.2])
    # trapezoids: (0.25 + 0.5) / 2 * 0.1 + (0.5 + 0.75) / 2 * 0.1 = 0.1, over the range 0.2
    assert pck_auc(errors, thresholds=[0.0, 0.1, 0.2]) == pytest.approx(0.5)


def test_auc_matches_the_ulrssm_definition_on_even_thresholds():
    errors = np.random.default_rng(0).uniform(0, 0.3, 500)
    _, fractions = pck_curve(errors)
    reference = np.trapezoid(fractions, np.linspace(0.0, 1.0, DEFAULT_PCK_THRESHOLDS.size))
    assert pck_auc(errors) == pytest.approx(reference)
    assert np.all(np.diff(fractions) >= 0) and 0 < pck_auc(errors) < 1


def test_overlap_iou_hand_computed():
    pred = np.array([True, True, False, False])
    gt = np.array([True, False, True, False])
    assert overlap_iou(pred, gt) == pytest.approx(1 / 3)
    assert overlap_iou(gt, gt) == 1.0
    assert overlap_iou(np.zeros(3, bool), np.zeros(3, bool)) == 1.0
    assert overlap_iou(~gt, gt) == 0.0
    assert mean_iou([(gt, gt), (pred, gt)]) == pytest.approx((1 + 1 / 3) / 2)


def test_chirality_perfect_mirrored_ties_and_missing():
    assert chirality_accuracy(IDENTITY, IDENTITY, MIRROR, PATH) == 1.0
    assert chirality_accuracy(MIRROR, IDENTITY, MIRROR, PATH) == 0.0
    # vertex 2 is on the symmetry plane (its own mirror) and is skipped: 4 evaluated vertices.
    # vertex 0 -> 2 is equidistant from 0 and 4 (tie: 1/2), vertex 1 -> -1 scores 0.
    pred = np.array([2, -1, 0, 3, 4])
    assert chirality_accuracy(pred, IDENTITY, MIRROR, PATH) == pytest.approx((0.5 + 0 + 1 + 1) / 4)


def test_chirality_respects_undefined_ground_truth_and_mask():
    sym = MIRROR.copy()
    sym[0] = -1
    mask = np.array([True, True, True, False, True])
    # evaluated: vertices 1 and 4 (0 has no mirror, 2 is on the plane, 3 is masked out)
    assert chirality_accuracy(MIRROR, IDENTITY, sym, PATH, eval_mask=mask) == 0.0
    assert chirality_accuracy(np.array([0, 1, 2, 3, 0]), IDENTITY, sym, PATH, eval_mask=mask) == pytest.approx(0.5)
    with pytest.raises(MetricError, match="chirality is undefined"):
        chirality_accuracy(IDENTITY, IDENTITY, IDENTITY, PATH)


@pytest.mark.parametrize(
    ("pred", "gt", "dist", "match"),
    [
        (IDENTITY, IDENTITY, PATH[:4], "square"),
        (IDENTITY[:4], IDENTITY, PATH, "both have shape"),
        (IDENTITY.astype(float), IDENTITY, PATH, "integer"),
        (IDENTITY[None], IDENTITY, PATH, "1-D"),
        (IDENTITY + 1, IDENTITY, PATH, "1-based"),
        (IDENTITY, IDENTITY - 2, PATH, r"\[0, 4\]"),
    ],
)
def test_invalid_geodesic_inputs_raise_clear_errors(pred, gt, dist, match):
    with pytest.raises(MetricError, match=match):
        geodesic_errors(pred, gt, dist)


def test_invalid_metric_arguments_raise_clear_errors():
    with pytest.raises(MetricError, match="boolean"):
        geodesic_errors(IDENTITY, IDENTITY, PATH, eval_mask=np.ones(N))
    with pytest.raises(MetricError, match="unmatched"):
        geodesic_errors(IDENTITY, IDENTITY, PATH, unmatched="ignore")
    with pytest.raises(MetricError, match="empty"):
        mean_geodesic_error([np.zeros(0)])
    with pytest.raises(MetricError, match="1-D"):
        mean_geodesic_error(np.zeros((2, 2)))
    with pytest.raises(MetricError, match="increasing"):
        pck_curve(np.zeros(3), thresholds=[0.1, 0.0])
    with pytest.raises(MetricError, match="boolean"):
        overlap_iou(np.array([0.9, 0.1]), np.array([True, False]))
    with pytest.raises(MetricError, match=r"shape \(2,\)"):
        overlap_iou(np.array([True]), np.array([True, False]))
    with pytest.raises(MetricError, match="at least one"):
        mean_iou([])
    with pytest.raises(MetricError, match="map_gt_sym_yx"):
        chirality_accuracy(IDENTITY, IDENTITY, MIRROR[:3], PATH)
    assert issubclass(MetricError, GeofeatError)


def test_overlap_auc_is_the_roc_area_with_ties_counting_half():
    from sklearn.metrics import roc_auc_score

    rng = np.random.default_rng(3)
    scores = rng.random(400).round(1)  # many ties
    truth = rng.random(400) < scores
    assert overlap_auc(scores, truth) == pytest.approx(roc_auc_score(truth, scores), abs=1e-12)
    assert overlap_auc(truth.astype(float), truth) == 1.0
    assert overlap_auc(-truth.astype(float), truth) == 0.0
    assert overlap_auc(scores, np.ones(400, dtype=bool)) is None
    with pytest.raises(MetricError, match="shape"):
        overlap_auc(scores[:-1], truth)
