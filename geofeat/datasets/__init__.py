"""Benchmark datasets: loaders for every format, converted at the boundary to `ShapePair` records."""

from geofeat.datasets.records import ShapePair

__all__ = ["ShapePair"]
