"""geofeat.evaluation.protocol: per-pair records, both protocols, the benchmark summary and the dataset loop."""

from __future__ import annotations

import dataclasses
import math
import multiprocessing
import os

import numpy as np
import pytest
import torch

import geofeat
from geofeat.datasets import Match, ShapePair, load_dataset
from geofeat.errors import DatasetError, MetricError
from geofeat.evaluation import metrics
from geofeat.evaluation.protocol import (
    BenchmarkSummary,
    PairEvaluation,
    evaluate_dataset,
    evaluate_pair,
    map_forked,
    pair_targets,
    summarize,
)
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.geometry.geodesic_store import GeodesicStore


def unit_square() -> geofeat.Mesh:
    """Two triangles of a unit square (area 1): edge-Dijkstra d(0,2) = sqrt(2), d(1,3) = 2, sides 1."""
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    return geofeat.Mesh(verts, np.array([[0, 1, 2], [0, 2, 3]]), name="square")


def square_pair(**fields) -> ShapePair:
    square = unit_square()
    settings = dict(
        x=square,
        y=square.renamed("square_y"),
        map_yx=np.arange(4),
        map_yx_sym=np.array([1, 0, 3, 2]),  # the mirror x -> 1 - x
        overlap_x=np.array([True, True, False, False]),
        protocol="f2f",
    )
    return ShapePair(**(settings | fields))


SWAPPED = np.array([0, 3, 2, 1])  # vertices 1 and 3 swapped: errors 0, 2, 0, 2


def test_hand_computed_square_vertices_protocol():
    dist = geodesic_matrix(unit_square())
    assert dist[0, 2] == pytest.approx(math.sqrt(2)) and dist[1, 3] == pytest.approx(2.0)
    match = Match(SWAPPED, np.ones(4, dtype=bool), np.array([True, False, False, False]), None, np.array([0.9, 0.2, 0.1, 0.3]))
    record = evaluate_pair(square_pair(), match)
    assert isinstance(record, PairEvaluation) and record.pair == "square_y->square"
    np.testing.assert_allclose(record.errors, [0.0, 2.0, 0.0, 2.0], rtol=1e-6)
    assert record.errors.dtype == np.float64 and record.n_evaluated == 4
    assert record.geodesic_error == pytest.approx(100.0)
    # v0, v2 land on their counterpart; v1 -> 3 and v3 -> 1 lie nearer the mirror images (0 and 2)
    assert record.chirality_accuracy == 0.5
    assert record.iou == 0.5  # only x has a ground-truth overlap: {0} against {0, 1}
    # overlap AUC of x: positives 0.9, 0.2 against negatives 0.1, 0.3: three of four pairs ranked right
    assert record.overlap_auc == 0.75
    assert list(record.to_dict()) == ["pair", "n_evaluated", "chirality_accuracy", "iou", "overlap_auc", "geodesic_error"]


def test_a_pair_error_scale_replaces_the_target_area():
    """BeCoS divides errors on a partial x by its full shape's sqrt(area): a pair's error_scale says so."""
    match = Match(SWAPPED, np.ones(4, dtype=bool), None, None, None)
    plain = evaluate_pair(square_pair(), match)  # over sqrt(area(x)) = 2 for the unit square of side 2
    area_side = math.sqrt(square_pair().x.area())
    scaled = evaluate_pair(dataclasses.replace(square_pair(), error_scale=2 * area_side), match)
    np.testing.assert_allclose(scaled.errors, plain.errors / 2, rtol=1e-12)
    assert scaled.chirality_accuracy == plain.chirality_accuracy
    for bad in (0.0, -1.0, float("nan"), "2"):
        with pytest.raises(MetricError, match="error_scale must be a positive finite length"):
            evaluate_pair(dataclasses.replace(square_pair(), error_scale=bad), match)


def test_hand_computed_square_template_protocol():
    pair = square_pair(corr_x=np.array([0, 1, 2]), corr_y=np.array([0, 1, 2]), corr_x_sym=np.array([1, 0, 3]))
    record = evaluate_pair(pair, Match(SWAPPED, np.ones(4, dtype=bool)), protocol="template")
    np.testing.assert_allclose(record.errors, [0.0, 2.0, 0.0], rtol=1e-6)  # the map read at the 3 template points
    assert record.n_evaluated == 3 and record.geodesic_error == pytest.approx(200 / 3)
    assert record.chirality_accuracy == pytest.approx(2 / 3)
    assert record.overlap_auc is None and record.iou == 0.5  # no predicted overlap counts as all of x, against {0, 1}
    row = record.to_dict()
    assert "overlap_auc" not in row and row["n_evaluated"] == 3


def test_protocol_errors_name_the_fix():
    with pytest.raises(DatasetError, match="template points"):
        evaluate_pair(square_pair(), Match(SWAPPED, np.ones(4, dtype=bool)), protocol="template")
    with pytest.raises(MetricError, match="protocol must be one of"):
        evaluate_pair(square_pair(), Match(SWAPPED, np.ones(4, dtype=bool)), protocol="points")
    with pytest.raises(MetricError, match=r"\(V_x, V_x\) = \(4, 4\)"):
        evaluate_pair(square_pair(), Match(SWAPPED, np.ones(4, dtype=bool)), distances=np.zeros((3, 3)))
    with pytest.raises(MetricError, match="at least one"):
        summarize([])


def test_given_distances_are_used_as_they_are():
    scaled = 10 * np.asarray(geodesic_matrix(unit_square()))
    record = evaluate_pair(square_pair(), Match(SWAPPED, np.ones(4, dtype=bool)), distances=scaled)
    assert record.geodesic_error == pytest.approx(1000.0)


def _old_summary(records: list[dict]) -> dict:
    """The summary of benchmarks/run.py before the evaluation module, on its dict records."""
    errors = [r["errors"] for r in records]
    thresholds, fractions = metrics.pck_curve(np.concatenate(errors))
    summary = {
        "n_pairs": len(records),
        "n_evaluated_vertices": int(sum(r["n_evaluated"] for r in records)),
        "geodesic_error": metrics.mean_geodesic_error(errors),
        "pck_auc": metrics.pck_auc(np.concatenate(errors)),
        "pck_thresholds": thresholds.tolist(),
        "pck": fractions.tolist(),
    }
    with_chirality = [r for r in records if "chirality_accuracy" in r]
    if with_chirality:
        weights = np.array([r["n_evaluated"] for r in with_chirality], dtype=float)
        values = np.array([r["chirality_accuracy"] for r in with_chirality])
        summary["chirality_accuracy"] = float((weights * values).sum() / weights.sum())
    for key, name in (("iou", "miou"), ("overlap_auc", "overlap_auc")):
        values = [r[key] for r in records if key in r]
        if values:
            summary[name] = float(np.mean(values))
    return summary


def test_summary_equals_the_former_run_py_summary_to_the_bit():
    rng = np.random.default_rng(0)
    records = [
        PairEvaluation("a->x", rng.uniform(0, 0.4, 50), chirality_accuracy=0.7, iou=0.8),
        PairEvaluation("b->x", rng.uniform(0, 0.4, 7), chirality_accuracy=0.2, overlap_auc=0.9),
        PairEvaluation("c->z", rng.uniform(0, 0.4, 31), iou=0.5),
    ]
    as_dicts = [{"errors": r.errors, **r.to_dict()} for r in records]
    summary = summarize(records)
    assert isinstance(summary, BenchmarkSummary)
    assert summary.to_dict() == _old_summary(as_dicts)
    assert list(summary.to_dict()) == list(_old_summary(as_dicts))  # the key order of results.json too
    assert summary.n_pairs == 3 and summary.n_evaluated_vertices == 88
    assert summary.chirality_accuracy == pytest.approx((50 * 0.7 + 7 * 0.2) / 57)
    assert summary.miou == pytest.approx(0.65) and summary.overlap_auc == 0.9
    thresholds, fractions = summary.pck_curve
    assert thresholds.dtype == fractions.dtype == np.float64 and thresholds.shape == fractions.shape
    no_extras = summarize([dataclasses.replace(records[0], chirality_accuracy=None, iou=None)])
    assert {"chirality_accuracy", "miou", "overlap_auc"}.isdisjoint(no_extras.to_dict())


def test_overlap_metrics_average_every_shape_with_ground_truth():
    pair = load_dataset("synthetic_cuts")[0]  # P2F: the ground truth overlap of the full shape x
    assert pair.overlap_y.all() and 0 < pair.overlap_x.mean() < 1
    all_y = np.ones(pair.y.n_vertices, dtype=bool)
    no_prediction = evaluate_pair(pair, Match(pair.map_yx, all_y))
    assert no_prediction.iou == pytest.approx((1.0 + pair.overlap_x.mean()) / 2)
    assert no_prediction.overlap_auc is None  # no probabilities, no ranking
    scores = pair.overlap_x + np.random.default_rng(0).uniform(0, 0.5, pair.x.n_vertices)  # ranks the truth perfectly
    exact = evaluate_pair(pair, Match(pair.map_yx, all_y, pair.overlap_x.copy(), None, scores))
    assert exact.iou == 1.0 and exact.overlap_auc == 1.0  # only x has both classes
    summary = summarize([no_prediction, exact])
    assert summary.overlap_auc == 1.0 and summary.miou == pytest.approx((no_prediction.iou + 1.0) / 2)


def test_pair_targets_group_pairs_without_loading_meshes():
    dataset = load_dataset("synthetic_cuts")
    targets = pair_targets(dataset, 12)
    assert targets == [name.rsplit("->", 1)[1] for name in dataset.pair_names[:12]]
    assert pair_targets([object(), object()], 2) == [0, 1]
    loaded = [dataset[i] for i in range(4)]  # pairs in memory: their targets' hashes
    assert pair_targets(loaded, 3) == [pair.x.hash for pair in loaded[:3]]
    assert pair_targets(loaded, 4)[0] == pair_targets(loaded, 4)[3] != pair_targets(loaded, 4)[1]  # as the names say


def test_dataset_evaluation_is_the_same_in_one_process_and_in_workers(tmp_path):
    dataset = load_dataset("synthetic_cuts")
    n = 4

    def shifted_truth(index: int, pair: ShapePair) -> Match:  # a deterministic, imperfect matcher
        predicted = np.where(pair.map_yx >= 0, pair.map_yx, 0)
        return Match(np.roll(predicted, index + 1), np.ones(pair.y.n_vertices, dtype=bool))

    store = GeodesicStore(tmp_path / "geodesics")
    calls = []  # on_kept: once per run, with the kept pairs, before the run returns
    settings = dict(store=store, keep=[0, 2, 99], on_kept=calls.append, progress=False)  # 99: past n, ignored
    one, kept = evaluate_dataset(dataset, shifted_truth, n, workers=1, **settings)
    two, kept_two = evaluate_dataset(dataset, shifted_truth, n, workers=2, **settings)
    assert len(calls) == 2 and calls[0] is not kept and sorted(calls[0]) == sorted(calls[1]) == [0, 2]
    np.testing.assert_array_equal(calls[1][2][1].map_yx, kept_two[2][1].map_yx)
    assert [r.pair for r in one] == [dataset[i].name for i in range(n)]  # in pair order, whatever the grouping
    for a, b in zip(one, two, strict=True):
        assert a.to_dict() == b.to_dict()
        np.testing.assert_array_equal(a.errors, b.errors)
    assert sorted(kept) == sorted(kept_two) == [0, 2]
    pair, match = kept[2]
    assert pair.name == dataset[2].name
    np.testing.assert_array_equal(match.map_yx, shifted_truth(2, dataset[2]).map_yx)
    # the same records as pair-by-pair evaluation with in-memory distances
    direct = evaluate_pair(dataset[1], shifted_truth(1, dataset[1]))
    np.testing.assert_array_equal(direct.errors, one[1].errors)
    assert direct.to_dict() == one[1].to_dict()


def _shifted_truth(shift: int):
    """A deterministic, imperfect matcher: the true map (holes at 0) rolled by ``index + shift``."""

    def match(index: int, pair: ShapePair) -> Match:
        predicted = np.where(pair.map_yx >= 0, pair.map_yx, 0)
        return Match(np.roll(predicted, index + shift), np.ones(pair.y.n_vertices, dtype=bool))

    return match


def _same_records(a: list[PairEvaluation], b: list[PairEvaluation]) -> None:
    assert [r.to_dict() for r in a] == [r.to_dict() for r in b]
    for one, two in zip(a, b, strict=True):
        np.testing.assert_array_equal(one.errors, two.errors)


def test_several_matchers_give_the_records_of_each_matcher_alone(tmp_path):
    dataset = load_dataset("synthetic_cuts")
    n = 4  # three targets, one of them twice
    matchers = {"one": _shifted_truth(1), "five": _shifted_truth(5), "truth": _shifted_truth(0)}
    store = GeodesicStore(tmp_path / "geodesics")
    alone = {name: evaluate_dataset(dataset, match, n, store=store, progress=False)[0] for name, match in matchers.items()}
    assert alone["one"][1].to_dict() != alone["five"][1].to_dict()  # the matchers differ
    for workers in (1, 2):
        calls = []
        records, kept = evaluate_dataset(
            dataset, matchers, n, store=store, workers=workers, keep=[3], on_kept=calls.append, progress=False
        )
        assert list(records) == list(matchers)  # in the mapping's order
        for name in matchers:
            _same_records(records[name], alone[name])
        pair, matches = kept[3]
        assert sorted(kept) == [3] and pair.name == dataset[3].name and list(matches) == list(matchers)
        for name, match in matchers.items():
            np.testing.assert_array_equal(matches[name].map_yx, match(3, dataset[3]).map_yx)
        assert len(calls) == 1 and sorted(calls[0]) == [3]
    # a list of loaded pairs is grouped by target too, with the same records
    loaded = [dataset[i] for i in range(n)]
    records, _ = evaluate_dataset(loaded, matchers, workers=2, progress=False)
    for name in matchers:
        _same_records(records[name], alone[name])
    with pytest.raises(MetricError, match="at least one matcher"):
        evaluate_dataset(dataset, {}, n, progress=False)


#: What the workers of `map_forked` read: set before the call, inherited through fork.
_OFFSET = 0


def _add_offset(task: int) -> int:
    if task < 0:
        raise ValueError(f"negative task {task}")
    return task + _OFFSET


def test_map_forked_runs_every_task_here_or_in_forked_workers():
    global _OFFSET
    _OFFSET = 100
    try:
        assert list(map_forked(_add_offset, [3, 1, 2], workers=1)) == [103, 101, 102]  # here: task order
        assert list(map_forked(_add_offset, [], workers=2)) == []
        if "fork" in multiprocessing.get_all_start_methods():
            assert sorted(map_forked(_add_offset, list(range(6)), workers=2)) == list(range(100, 106))
        for workers in (1, 2):
            with pytest.raises(ValueError, match="negative task -1"):
                list(map_forked(_add_offset, [0, -1, 2], workers=workers))
    finally:
        _OFFSET = 0


def _thread_counts() -> tuple[list[int], int]:
    from threadpoolctl import threadpool_info

    return [pool["num_threads"] for pool in threadpool_info()], torch.get_num_threads()


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="workers are forked only where fork exists")
def test_forked_workers_run_one_blas_and_one_torch_thread():
    from concurrent.futures import ProcessPoolExecutor

    from geofeat.evaluation.protocol import _worker_start

    with ProcessPoolExecutor(
        1, mp_context=multiprocessing.get_context("fork"), initializer=_worker_start, initargs=(os.getpid(),)
    ) as pool:
        blas, torch_threads = pool.submit(_thread_counts).result()
    assert blas and all(n == 1 for n in blas), blas  # numpy/scipy's BLAS pools, lowered after the fork
    assert torch_threads == 1


# A fresh interpreter: match and evaluate two pairs with the nn head in 2 forked workers, then
# report whether torch was loaded, and the threads a worker's later torch import starts with.
_TORCH_FREE_RUN = """
import multiprocessing, os, sys
from concurrent.futures import ProcessPoolExecutor
from geofeat.adapters.heads import make_head
from geofeat.datasets import load_dataset
from geofeat.evaluation.protocol import _worker_start, evaluate_dataset

head = make_head("nn", descriptor="xyz", progress=False)
records, _ = evaluate_dataset(load_dataset("synthetic_cuts"), lambda i, pair: head.match(pair), 2, workers=2, progress=False)
loaded = "torch" in sys.modules

def later_torch_threads():
    import torch
    return torch.get_num_threads()

with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"), initializer=_worker_start, initargs=(os.getpid(),)) as pool:
    threads = pool.submit(later_torch_threads).result()
print(len(records), loaded, threads)
"""


@pytest.mark.skipif("fork" not in multiprocessing.get_all_start_methods(), reason="workers are forked only where fork exists")
def test_training_free_pipeline_never_loads_torch_and_workers_import_it_with_one_thread():
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    result = subprocess.run([sys.executable, "-c", _TORCH_FREE_RUN], capture_output=True, text=True, env=env, timeout=300)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["2", "False", "1"]
