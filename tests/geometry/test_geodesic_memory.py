"""The memory bound of all-pairs geodesics: estimates, the streamed entries above it, and the bound's settings."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from shapes import bumpy

from geofeat import Mesh
from geofeat.errors import GeodesicMemoryError, GeofeatError
from geofeat.evaluation import metrics
from geofeat.geometry import geodesic, geodesic_memory
from geofeat.geometry.geodesic import all_pairs_memory, geodesic_matrix
from geofeat.geometry.geodesic_memory import GeodesicEntries, evaluation_distances, memory_limit
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.storage.sizes import parse_size


def two_pieces() -> Mesh:
    """Two bumpy spheres side by side: distances between them are infinite."""
    a, b = bumpy(0, 3), bumpy(1, 2)
    verts = np.concatenate([a.verts, b.verts + 5.0])
    return Mesh(verts, np.concatenate([a.faces, b.faces + a.n_vertices]), name="two pieces")


def metrics_of(dist, pred, gt, sym):
    return (
        metrics.geodesic_errors(pred, gt, dist),
        metrics.chirality_accuracy(pred, gt, sym, dist),
        metrics.geodesic_errors(pred, gt, dist, eval_mask=np.arange(gt.size) % 3 == 0),
    )


def same(a, b) -> None:
    np.testing.assert_array_equal(a[0], b[0])
    assert a[1] == b[1]
    np.testing.assert_array_equal(a[2], b[2])


@pytest.mark.parametrize("limit", [None, 1], ids=["one pass", "a pass per worst case"])
def test_streamed_entries_equal_the_matrix_exactly(limit):
    mesh = two_pieces()  # 642 + 162 vertices: separator and patches, two components
    n = mesh.n_vertices
    rng = np.random.default_rng(0)
    gt = rng.integers(-1, n, 400)
    pred = rng.integers(0, n, 400)
    pred[::37] = -1  # unmatched: the worst case of its row
    sym = rng.integers(-1, n, 400)
    full = geodesic_matrix(mesh, "dijkstra", normalize=True, cache=False)
    entries = GeodesicEntries(mesh, limit=limit)
    metrics_of(entries, pred, gt, sym)  # asks
    entries.compute()
    same(metrics_of(entries, pred, gt, sym), metrics_of(full, pred, gt, sym))
    assert np.isinf(full[0, n - 1]) and entries.computed


def test_streamed_entries_compute_only_the_rows_read():
    mesh = bumpy(0, 3)
    full = geodesic_matrix(mesh, "dijkstra", normalize=True, cache=False)
    entries = GeodesicEntries(mesh)
    rows, cols = np.array([0, 5, 5]), np.array([7, 9, 0])
    entries[rows, cols]
    entries.compute()
    np.testing.assert_array_equal(entries[rows, cols], full[rows, cols])
    assert entries.n_rows_computed < mesh.n_vertices  # no worst case asked: not every row
    with pytest.raises(GeofeatError, match="not asked for"):
        entries[np.array([1]), np.array([2])]
    with pytest.raises(GeofeatError, match="not asked for"):
        entries.worst_case(np.array([3]))


def test_estimates_and_sizes():
    assert all_pairs_memory(40_000) > 4 * 40_000**2 > all_pairs_memory(10_000)
    assert all_pairs_memory(1000, "float16") - all_pairs_memory(1000) == 2 * 1000**2
    assert parse_size("4G", "x") == 4 << 30 and parse_size("512 MiB", "x") == 512 << 20 and parse_size(1000, "x") == 1000
    assert parse_size("1.5kb", "x") == 1536
    for bad in ("lots", "-1G", "4X"):
        with pytest.raises(GeofeatError, match="size in bytes|zero bytes or more"):
            parse_size(bad, "GEOFEAT_GEODESIC_MEMORY")


def test_the_bound_comes_from_the_argument_the_environment_or_the_available_memory(monkeypatch):
    real = geodesic_memory.available_memory()
    assert real is None or real > 0
    monkeypatch.delenv(geodesic_memory.MEMORY_ENV, raising=False)
    monkeypatch.setattr(geodesic_memory, "available_memory", lambda: 8_000_000_000)
    assert memory_limit() == (4_000_000_000, "50% of the 8.0 GB available")
    monkeypatch.setenv(geodesic_memory.MEMORY_ENV, "2G")
    assert memory_limit() == (2 << 30, geodesic_memory.MEMORY_ENV)
    assert memory_limit("1M") == (1 << 20, "memory_limit")
    monkeypatch.setenv(geodesic_memory.MEMORY_ENV, "much")
    with pytest.raises(GeofeatError, match="GEOFEAT_GEODESIC_MEMORY must be a size"):
        memory_limit()
    monkeypatch.delenv(geodesic_memory.MEMORY_ENV)
    monkeypatch.setattr(geodesic_memory, "available_memory", lambda: None)
    assert memory_limit()[0] is None


def test_evaluation_distances_streams_above_the_bound_and_says_so(tmp_path, caplog):
    mesh = bumpy(0, 3)
    store = GeodesicStore(tmp_path / "g")
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        streamed = evaluation_distances(mesh, store, limit="1M")
    assert isinstance(streamed, GeodesicEntries) and store.entries() == []  # nothing computed, nothing stored
    assert "642 vertices" in caplog.text and "above the bound of 1.0 MB" in caplog.text
    assert "without forming the matrix or keeping it in the geodesic store" in caplog.text
    full = evaluation_distances(mesh, store)  # within the default bound: the matrix, stored
    assert isinstance(full, np.ndarray) and len(store.entries()) == 1
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        again = evaluation_distances(mesh, store, limit="1M")  # a stored matrix is read back, whatever the bound
    assert isinstance(again, np.ndarray) and caplog.text == ""
    np.testing.assert_array_equal(again, full)


def test_a_matrix_that_does_not_fit_raises_a_clear_error(monkeypatch):
    def no_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 23.8 GiB for an array with shape (80000, 80000)")

    monkeypatch.setattr(geodesic, "_all_pairs_dijkstra", no_memory)
    with pytest.raises(GeodesicMemoryError, match="642 vertices: its all-pairs geodesic matrix needs about") as info:
        geodesic_matrix(bumpy(0, 3), cache=False)
    assert isinstance(info.value, MemoryError)
