"""Evaluating predicted matches against ground truth, pair by pair and over a benchmark.

One protocol for every caller (``benchmarks/run.py``, ``benchmarks/tables/summarize.py``, the GeoLoRA
trainer's validation):

* `evaluate_pair` scores a `Match` of a `ShapePair` into a `PairEvaluation` record: geodesic
  errors, chirality accuracy, overlap IoU and overlap ROC AUC;
* `summarize` pools records into a `BenchmarkSummary`, the metrics that ``results.json``
  holds;
* `evaluate_dataset` runs a matcher, or several side by side, over the first pairs of a
  dataset and evaluates them, target shape by target shape (each target's geodesic matrix is
  computed or read once), in one process or in a pool of forked worker processes
  (`map_forked`), with the same records either way.

Protocols (``protocol=``): ``"vertices"`` evaluates every vertex of ``y`` that has a
counterpart (the default); ``"template"`` evaluates the template points of datasets with a
common template (FAUST_r, SCAPE_r), as the ULRSSM and DPFM references do
(`geofeat.evaluation.metrics.template_geodesic_errors`). Distances are edge-Dijkstra geodesics on the
target ``x`` divided by ``sqrt(area(x))``, or by the pair's ``error_scale`` where the
benchmark fixes another length (BeCoS: the full shape's ``sqrt(area)``, also for a partial ``x``).

Point clouds: a cloud ``y`` needs nothing special (distances are on ``x``). A cloud ``x``
made from a mesh (``pair.x_surface``, a depth scan) is measured on that mesh: each point of
``x`` stands for the corner of its face with the largest barycentric weight, and distances
are the mesh's, over the square root of its area (`evaluation_target`). A cloud ``x`` without
one is measured with the heat method on its own points, over the square root of its
point-cloud area (`geofeat.geometry.geodesic`).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import DatasetError, MetricError
from geofeat.evaluation import metrics
from geofeat.evaluation.targets import check_surface, evaluation_target, points_on_target
from geofeat.geometry.geodesic import area_normalisation
from geofeat.geometry.geodesic_memory import GeodesicEntries, evaluation_distances, memory_limit
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.runtime.processes import end_with_parent
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)

__all__ = [
    "PROTOCOLS",
    "SUMMARY_COLUMNS",
    "BenchmarkSummary",
    "PairEvaluation",
    "default_workers",
    "evaluate_dataset",
    "evaluation_target",
    "evaluate_pair",
    "map_forked",
    "pair_targets",
    "summarize",
]

#: Which points of ``y`` are evaluated: every vertex with a counterpart, or the template points.
PROTOCOLS = ("vertices", "template")

#: Markdown table columns ``(key, header, format)`` of the summary metrics, as run reports show them.
SUMMARY_COLUMNS = [
    ("n_pairs", "pairs", "d"),
    ("geodesic_error", "geodesic error x100", ".2f"),
    ("pck_auc", "PCK AUC", ".3f"),
    ("miou", "mIoU", ".3f"),
    ("overlap_auc", "overlap AUC", ".3f"),
    ("chirality_accuracy", "chirality acc.", ".3f"),
]


@dataclass(frozen=True, eq=False)
class PairEvaluation:
    """The metrics of one matched pair.

    Attributes
    ----------
    pair : str
        ``"<y name>-><x name>"``.
    errors : numpy.ndarray, shape (n_evaluated,), float64
        Geodesic error of every evaluated point (fractions of ``sqrt(area(x))``).
    chirality_accuracy : float or None
        Fraction of evaluated points matched on the correct side, where the dataset has a
        mirrored ground truth.
    iou : float or None
        Overlap IoU, the mean over the shapes whose ground-truth overlap the dataset gives
        (a head that predicts no overlap for a shape counts as predicting all of it).
    overlap_auc : float or None
        ROC AUC of the predicted overlap probabilities, the mean over the shapes with
        probabilities and a ground truth holding both classes.
    """

    pair: str
    errors: np.ndarray
    chirality_accuracy: float | None = None
    iou: float | None = None
    overlap_auc: float | None = None

    @property
    def n_evaluated(self) -> int:
        """Number of evaluated points."""
        return int(self.errors.size)

    @property
    def geodesic_error(self) -> float:
        """Mean geodesic error of the pair, x100."""
        return 100 * float(self.errors.mean())

    def to_dict(self) -> dict[str, Any]:
        """The pair's row of ``results.json``: name, counts and metrics, without the error array (None left out)."""
        row: dict[str, Any] = {"pair": self.pair, "n_evaluated": self.n_evaluated}
        for key in ("chirality_accuracy", "iou", "overlap_auc"):
            value = getattr(self, key)
            if value is not None:
                row[key] = value
        row["geodesic_error"] = self.geodesic_error
        return row


@dataclass(frozen=True)
class BenchmarkSummary:
    """Metrics pooled over the pairs of a benchmark, the way published tables report them.

    Attributes
    ----------
    n_pairs : int
    n_evaluated_vertices : int
        Evaluated points of all pairs together.
    geodesic_error : float
        Mean geodesic error x100 over all evaluated points of all pairs pooled.
    pck_auc : float
        Area under the PCK curve, in [0, 1].
    pck_thresholds, pck : list of float
        The PCK curve: fraction of points within each error threshold.
    chirality_accuracy : float or None
        Mean over pairs weighted by their evaluated points (pairs with a mirrored ground truth).
    miou : float or None
        Mean overlap IoU over the pairs that have one.
    overlap_auc : float or None
        Mean overlap ROC AUC over the pairs that have one.
    """

    n_pairs: int
    n_evaluated_vertices: int
    geodesic_error: float
    pck_auc: float
    pck_thresholds: list[float] = field(repr=False)
    pck: list[float] = field(repr=False)
    chirality_accuracy: float | None = None
    miou: float | None = None
    overlap_auc: float | None = None

    def to_dict(self) -> dict[str, Any]:
        """The summary keys of ``results.json`` (None left out), in a fixed order."""
        return {key: value for key, value in self.__dict__.items() if value is not None}

    @property
    def pck_curve(self) -> tuple[np.ndarray, np.ndarray]:
        """``(thresholds, fractions)``, two float64 arrays of the same length."""
        return np.asarray(self.pck_thresholds, dtype=np.float64), np.asarray(self.pck, dtype=np.float64)


def _check_protocol(protocol: str) -> None:
    if protocol not in PROTOCOLS:
        raise MetricError(f"protocol must be one of {PROTOCOLS}; found {protocol!r}.")


def evaluate_pair(
    pair: ShapePair, match: Match, protocol: str = "vertices", distances: np.ndarray | None = None
) -> PairEvaluation:
    """Score a predicted match of a pair.

    Parameters
    ----------
    pair : ShapePair
        Ground truth; V_x and V_y vertices.
    match : Match
        Prediction: ``map_yx`` (V_y,) and optional overlap masks and probabilities.
    protocol : {"vertices", "template"}
        Evaluated points (see the module notes).
    distances : numpy.ndarray, shape (V_t, V_t), or GeodesicEntries, optional
        Geodesic distances on the pair's `evaluation_target` (``pair.x``, or the mesh of
        ``pair.x_surface``) over ``sqrt(area)``
        (`geofeat.geometry.geodesic_memory.evaluation_distances`); computed
        when not given. A `GeodesicEntries` not computed yet is asked for the entries this
        pair reads and computed.

    Returns
    -------
    PairEvaluation

    Raises
    ------
    MetricError
        For an unknown protocol or a distance matrix of the wrong shape.
    DatasetError
        For ``protocol="template"`` on a pair without template points.
    """
    _check_pair(pair, protocol)
    dist_x = evaluation_distances(evaluation_target(pair)) if distances is None else distances
    if isinstance(dist_x, GeodesicEntries) and not dist_x.computed:
        _score(pair, match, protocol, dist_x)  # asks for the entries it reads
        dist_x.compute()
    return _score(pair, match, protocol, dist_x)


def _check_pair(pair: ShapePair, protocol: str) -> None:
    _check_protocol(protocol)
    check_surface(pair)
    scale = pair.error_scale
    if scale is not None and not (isinstance(scale, (int, float, np.floating)) and np.isfinite(scale) and scale > 0):
        raise MetricError(f"pair {pair.name}: error_scale must be a positive finite length or None; found {scale!r}.")
    if protocol == "template" and (pair.corr_x is None or pair.corr_y is None):
        raise DatasetError(f"pair {pair.name}: --protocol template needs a dataset with template points (faust_r, scape_r)")


def _score(pair: ShapePair, match: Match, protocol: str, dist_x: np.ndarray | GeodesicEntries) -> PairEvaluation:
    """`evaluate_pair` on given distances (a `GeodesicEntries` not computed yet: asks for its entries)."""
    _check_pair(pair, protocol)
    target = evaluation_target(pair)
    n_t = target.n_vertices
    if dist_x.shape != (n_t, n_t):
        size, what, where = (
            ("V_x", "x", "pair.x") if pair.x_surface is None else ("V", "the mesh of x_surface", "pair.x_surface.mesh")
        )
        raise MetricError(
            f"pair {pair.name}: distances must be the ({size}, {size}) = ({n_t}, {n_t}) matrix of {what}; "
            f"found shape {dist_x.shape}. Pass geofeat.geometry.geodesic_memory.evaluation_distances({where})."
        )
    predicted = points_on_target(pair, match.map_yx, "the predicted map_yx")
    corr_x, corr_x_sym = points_on_target(pair, pair.corr_x, "corr_x"), points_on_target(pair, pair.corr_x_sym, "corr_x_sym")
    if protocol == "template":
        errors = metrics.template_geodesic_errors(predicted, corr_x, pair.corr_y, dist_x)
        sym = None
        if corr_x_sym is not None:
            sym = (metrics.at_template_points(predicted, pair.corr_y), corr_x, corr_x_sym)
    else:
        truth = points_on_target(pair, pair.map_yx, "map_yx")
        errors = metrics.geodesic_errors(predicted, truth, dist_x)
        mirrored = points_on_target(pair, pair.map_yx_sym, "map_yx_sym")
        sym = None if mirrored is None else (predicted, truth, mirrored)
    chirality = None if sym is None else metrics.chirality_accuracy(*sym, dist_x)
    if pair.error_scale is not None:  # the distances are over sqrt(area) of the target; the benchmark fixes another length
        errors = errors / (area_normalisation(target) * pair.error_scale)
    ious = [
        metrics.overlap_iou(np.ones(truth.shape, dtype=bool) if guess is None else guess, truth)
        for guess, truth in ((match.overlap_y, pair.overlap_y), (match.overlap_x, pair.overlap_x))
        if truth is not None
    ]
    aucs = [
        metrics.overlap_auc(scores, truth)
        for scores, truth in ((match.overlap_prob_y, pair.overlap_y), (match.overlap_prob_x, pair.overlap_x))
        if scores is not None and truth is not None
    ]
    aucs = [auc for auc in aucs if auc is not None]
    return PairEvaluation(
        pair=f"{pair.y.name}->{pair.x.name}",
        errors=errors,
        chirality_accuracy=chirality,
        iou=float(np.mean(ious)) if ious else None,
        overlap_auc=float(np.mean(aucs)) if aucs else None,
    )


def summarize(records: Sequence[PairEvaluation]) -> BenchmarkSummary:
    """Pool per-pair records into the benchmark metrics.

    Parameters
    ----------
    records : sequence of PairEvaluation
        At least one, with at least one evaluated point in all.

    Returns
    -------
    BenchmarkSummary
        Geodesic error and PCK pooled over all points; chirality weighted by the evaluated
        points of each pair; mIoU and overlap AUC as means over the pairs that have them.
    """
    if not records:
        raise MetricError("summarize needs at least one evaluated pair; found none.")
    errors = [r.errors for r in records]
    pooled = np.concatenate(errors)
    thresholds, fractions = metrics.pck_curve(pooled)
    with_chirality = [r for r in records if r.chirality_accuracy is not None]
    chirality = None
    if with_chirality:
        weights = np.array([r.n_evaluated for r in with_chirality], dtype=float)
        values = np.array([r.chirality_accuracy for r in with_chirality])
        chirality = float((weights * values).sum() / weights.sum())
    ious = [r.iou for r in records if r.iou is not None]
    aucs = [r.overlap_auc for r in records if r.overlap_auc is not None]
    return BenchmarkSummary(
        n_pairs=len(records),
        n_evaluated_vertices=int(sum(r.n_evaluated for r in records)),
        geodesic_error=metrics.mean_geodesic_error(errors),
        pck_auc=metrics.pck_auc(pooled),
        pck_thresholds=thresholds.tolist(),
        pck=fractions.tolist(),
        chirality_accuracy=chirality,
        miou=float(np.mean(ious)) if ious else None,
        overlap_auc=float(np.mean(aucs)) if aucs else None,
    )


# ----------------------------------------------------------------------------- a dataset


def pair_targets(dataset: Sequence[ShapePair], n_pairs: int) -> list[str | int]:
    """A key of the target shape ``x`` of each of the first ``n_pairs`` pairs, without loading any mesh.

    Datasets with ``pair_names`` (``"<y>-><x>"``, every loader here) give the target's name;
    a list or tuple of `ShapePair` (loaded already) gives each target's hash; for other
    sequences every pair is its own group (its index).
    """
    names = getattr(dataset, "pair_names", None)
    if names is not None:
        return [name.rsplit("->", 1)[1] for name in list(names)[:n_pairs]]
    if isinstance(dataset, (list, tuple)):
        return [pair.x.hash if isinstance(pair, ShapePair) else i for i, pair in enumerate(dataset[:n_pairs])]
    return list(range(n_pairs))


def _group_by_target(targets: Sequence[str | int]) -> list[list[int]]:
    """Pair indices grouped by target, groups in order of their first pair, indices ascending."""
    groups: dict[str | int, list[int]] = {}
    for i, key in enumerate(targets):
        groups.setdefault(key, []).append(i)
    return list(groups.values())


MatchFunction = Callable[[int, ShapePair], Match]

#: The name `evaluate_dataset` gives a single matcher inside (never shown).
_ONE = ""


@dataclass
class _Job:
    dataset: Sequence[ShapePair]
    matchers: dict[str, MatchFunction]
    protocol: str
    store: GeodesicStore | None
    keep: frozenset[int]
    memory: tuple[int | None, str]


#: The job of the forked workers of `evaluate_dataset` (inherited through fork, never pickled).
_JOB: _Job | None = None

#: ``(pair index, {matcher name: record}, (pair, {matcher name: match}) when the pair is kept)``.
_Evaluated = tuple[int, dict[str, PairEvaluation], tuple[ShapePair, dict[str, Match]] | None]


def _evaluate_group(indices: list[int]) -> list[_Evaluated]:
    """Match and evaluate the pairs of one target shape, every matcher on a pair in a row."""
    job = _JOB
    if job is None:
        raise RuntimeError("no evaluation job: _evaluate_group runs inside evaluate_dataset only")
    out: list[_Evaluated] = []
    target, distances = None, None
    waiting: list[tuple[int, ShapePair, dict[str, Match]]] = []  # pairs of a target evaluated from streamed entries

    def score(i: int, pair: ShapePair, matches: dict[str, Match]) -> None:
        records = {name: _score(pair, match, job.protocol, distances) for name, match in matches.items()}
        out.append((i, records, (pair, matches) if i in job.keep else None))

    def evaluate_waiting() -> None:
        if waiting:
            distances.compute()  # every entry the target's pairs read, in one pass
            for item in waiting:
                score(*item)
            waiting.clear()

    for i in indices:
        pair = job.dataset[i]
        matches = {name: match(i, pair) for name, match in job.matchers.items()}
        shape = evaluation_target(pair)
        if shape.hash != target:
            evaluate_waiting()
            bound, source = job.memory
            target, distances = shape.hash, evaluation_distances(shape, job.store, bound, limit_source=source)
        if isinstance(distances, GeodesicEntries):
            for match in matches.values():
                _score(pair, match, job.protocol, distances)  # asks for the entries it reads
            waiting.append((i, pair, matches))
        else:
            score(i, pair, matches)
    evaluate_waiting()
    return out


def _worker_start(parent_pid: int) -> None:
    """In a forked worker: ends with the parent (`end_with_parent`); one BLAS/torch thread, the cores go to the workers.

    The BLAS of numpy/scipy was started in the parent with its own thread count, so the
    environment variables come too late: `threadpoolctl` lowers it in place. Workers that
    each keep several BLAS threads on the same cores wait on each other (a cold main job
    took 117 s instead of about 40 s on 2 cores). torch is lowered too where the parent had
    loaded it; where not (the training-free pipelines never load it), ``OMP_NUM_THREADS``
    makes a later import in the worker start with one thread.
    """
    from threadpoolctl import threadpool_limits

    end_with_parent(parent_pid)
    threadpool_limits(1)
    torch = sys.modules.get("torch")
    if torch is None:
        os.environ["OMP_NUM_THREADS"] = "1"
    else:
        torch.set_num_threads(1)


def default_workers() -> int:
    """Worker processes of `evaluate_dataset` when not given: the usable CPU cores (``os.sched_getaffinity``)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def _usable_workers(workers: int, n_tasks: int) -> int:
    """``workers`` capped by the number of tasks; 1 where there is no ``fork`` start method."""
    workers = max(1, min(int(workers), n_tasks))
    if workers > 1 and "fork" not in multiprocessing.get_all_start_methods():
        log.info("no fork start method here: working in one process")
        return 1
    return workers


Task = TypeVar("Task")
Result = TypeVar("Result")


def map_forked(function: Callable[[Task], Result], tasks: Sequence[Task], workers: int) -> Iterator[Result]:
    """``function(task)`` for every task, in a pool of forked worker processes: the pool of `evaluate_dataset`.

    Parameters
    ----------
    function : callable
        ``function(task) -> result``, a module-level function. The workers are forked, so they
        inherit what this process holds (module globals set before the call included): only
        the tasks and the results are pickled.
    tasks : sequence
        Submitted in this order (put the longest first, so that the workers finish together).
    workers : int
        Processes, at most one per task. Each runs one BLAS and one torch thread. With one,
        or where ``fork`` does not exist, the tasks run here, one after the other.

    Yields
    ------
    result
        ``function(task)``, in the order the tasks finish (in task order in one process). A
        task that raises raises here, and the tasks not started yet are dropped.
    """
    workers = _usable_workers(workers, len(tasks))
    if workers == 1:
        for task in tasks:
            yield function(task)
        return
    from concurrent.futures import ProcessPoolExecutor, as_completed

    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_worker_start, initargs=(os.getpid(),)) as pool:
        futures = [pool.submit(function, task) for task in tasks]
        try:
            for future in as_completed(futures):
                yield future.result()
        finally:  # a failure, or a caller that stops early, starts no further task
            for future in futures:
                future.cancel()


def evaluate_dataset(
    dataset: Sequence[ShapePair],
    match: MatchFunction | Mapping[str, MatchFunction],
    n_pairs: int | None = None,
    *,
    protocol: str = "vertices",
    store: GeodesicStore | None = None,
    workers: int = 1,
    keep: Sequence[int] = (),
    on_kept: Callable[[dict[int, tuple[ShapePair, Any]]], None] | None = None,
    progress: bool = True,
    desc: str = "evaluating",
    memory: int | str | None = None,
) -> tuple[list[PairEvaluation] | dict[str, list[PairEvaluation]], dict[int, tuple[ShapePair, Any]]]:
    """Match and evaluate the first ``n_pairs`` pairs of a dataset, target shape by target shape.

    Parameters
    ----------
    dataset : sequence of ShapePair
        Indexable (a dataset of `geofeat.datasets`, or a list of pairs).
    match : callable or mapping
        ``match(index, pair) -> Match``; or several, ``{name: match}``, evaluated on the same
        pairs: each pair is loaded once and matched by all of them in a row (they share what
        the process holds: input features, spectral bases), and each target's geodesic
        matrix is computed or read once for all.
    n_pairs : int, optional
        Default all pairs.
    protocol : {"vertices", "template"}
    store : GeodesicStore, optional
        Where the targets' geodesic matrices are kept on disk (None: computed in memory).
    workers : int
        Processes. With more than one (and where ``fork`` exists) the target groups are
        shared out among forked workers (`map_forked`), which inherit ``dataset`` and
        ``match`` (nothing is pickled but the records); each worker computes with one
        thread. The records do not depend on the number of workers, nor on the other
        matchers: every pair is matched and evaluated alone.
    keep : sequence of int
        Pair indices whose ``(pair, match)`` are returned too (for pictures).
    on_kept : callable, optional
        ``on_kept(kept)``, called once in this process as soon as every kept pair is
        evaluated, with the ``kept`` dict returned at the end: with workers, pictures are
        drawn while the other pairs are still evaluated. Not called when no pair is kept.
    progress : bool
        Show a tqdm progress bar (pairs).
    desc : str
        The progress bar's label.
    memory : int or str, optional
        Bound on the memory of a target's geodesic matrix (bytes or ``"4G"``; default
        ``$GEOFEAT_GEODESIC_MEMORY``, else half the memory available at the start). The
        workers share it: each gets the bound divided by their number. Above it, only the
        distances the evaluation reads are computed, a few rows at a time, and not stored
        (`geofeat.geometry.geodesic_memory.GeodesicEntries`, the same values).

    Returns
    -------
    records : list of PairEvaluation, or dict
        In pair order; for a mapping of matchers, ``{name: list of PairEvaluation}`` in the
        mapping's order.
    kept : dict
        ``index -> (ShapePair, Match)`` for the indices of ``keep``; for a mapping of
        matchers, ``index -> (ShapePair, {name: Match})``.

    Raises
    ------
    MetricError
        For an unknown protocol or an empty mapping of matchers.
    """
    global _JOB
    _check_protocol(protocol)
    several = isinstance(match, Mapping)
    matchers = dict(match) if several else {_ONE: match}
    if not matchers:
        raise MetricError("evaluate_dataset needs at least one matcher; found an empty mapping. Pass {name: match(index, pair)}.")
    n_pairs = len(dataset) if n_pairs is None else min(int(n_pairs), len(dataset))
    groups = _group_by_target(pair_targets(dataset, n_pairs))
    workers = _usable_workers(workers, len(groups))
    bound, source = memory_limit(memory)
    if bound is not None and workers > 1:
        bound, source = bound // workers, f"{source}, shared by {workers} worker processes"
    results: dict[int, tuple[dict[str, PairEvaluation], tuple[ShapePair, dict[str, Match]] | None]] = {}
    wanted = sorted(i for i in set(keep) if 0 <= i < n_pairs)
    waiting = set(wanted)

    def kept(i: int) -> tuple[ShapePair, Any]:
        pair, matches = results[i][1]
        return (pair, matches) if several else (pair, matches[_ONE])

    def collect(i: int, records: dict[str, PairEvaluation], pair_matches: tuple[ShapePair, dict[str, Match]] | None) -> None:
        results[i] = (records, pair_matches)
        bar.update(1)
        if i in waiting:
            waiting.discard(i)
            if not waiting and on_kept is not None:
                on_kept({j: kept(j) for j in wanted})

    order = groups if workers == 1 else sorted(groups, key=len, reverse=True)  # largest first: the workers finish together
    _JOB = _Job(dataset, matchers, protocol, store, frozenset(wanted), (bound, source))
    try:
        with progress_bar(total=n_pairs, desc=desc, unit="pair", show=progress) as bar:
            for evaluated in map_forked(_evaluate_group, order, workers):
                for item in evaluated:
                    collect(*item)
    finally:
        _JOB = None
    records = {name: [results[i][0][name] for i in range(n_pairs)] for name in matchers}
    return (records if several else records[_ONE]), {i: kept(i) for i in wanted}
