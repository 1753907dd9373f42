"""Evaluation: metrics, the evaluation protocol and reports.

* `geofeat.evaluation.metrics`: geodesic error, PCK, overlap IoU and AUC, chirality;
* `geofeat.evaluation.protocol`: `evaluate_pair`, `summarize`, `evaluate_dataset`, the one
  protocol of every benchmark run;
* `geofeat.evaluation.report`: Markdown tables and plots of results.

The everyday names of the protocol are importable from here:

>>> from geofeat.evaluation import evaluate_pair, summarize
"""

from geofeat.evaluation.protocol import BenchmarkSummary, PairEvaluation, evaluate_dataset, evaluate_pair, summarize

__all__ = ["BenchmarkSummary", "PairEvaluation", "evaluate_dataset", "evaluate_pair", "summarize"]
