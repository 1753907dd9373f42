"""Partial benchmarks derived from any full collection with correspondences to a template.

A partial shape made from full shape A (with its subset map to A) is matched to full shape B
(partial-to-full, P2F) or to a partial shape made from B (partial-to-partial, P2P). The
ground truth goes through the common template: vertex ``a`` of A is template point ``t``
when ``template_map(A)[t] == a``, and template point ``t`` is vertex
``template_map(B)[t]`` of B. Vertices without a template point have no ground-truth
counterpart (-1). Overlap masks are geometric: every vertex of a partial of A lies on B,
and a vertex of B (or of a partial of B) overlaps when its counterpart in A survived in the
partial of A, where a vertex without a template point takes that of its nearest vertex with
one. Everything is reproducible from one seed.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from geofeat.datasets.base import check_split
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError, MeshError
from geofeat.geometry.partial import make_partial, partial_generator
from geofeat.mesh import Mesh

PARTIAL_KINDS = ("cuts", "holes", "ray")


class TemplateCollection(ABC):
    """Full shapes, each with a map from common template points to its vertices."""

    @property
    @abstractmethod
    def names(self) -> list[str]:
        """Shape names, in index order."""

    @abstractmethod
    def mesh(self, index: int) -> Mesh:
        """Full shape ``index``."""

    @abstractmethod
    def template_map(self, index: int) -> np.ndarray:
        """Shape (T,) int64: the vertex of shape ``index`` at each template point (0-based)."""

    @abstractmethod
    def template_map_sym(self, index: int) -> np.ndarray | None:
        """Shape (T,) int64: the vertex at the mirror image of each template point, or None."""

    def __len__(self) -> int:
        return len(self.names)


def template_inverse(template_map: np.ndarray, n_vertices: int) -> np.ndarray:
    """For each vertex the first template point that lands on it, or -1; shape (V,) int64."""
    inverse = np.full(n_vertices, -1, dtype=np.int64)
    points = np.arange(template_map.size, dtype=np.int64)
    inverse[template_map[::-1]] = points[::-1]  # later writes win: reversed, so the first point wins
    return inverse


def nearest_template_points(mesh: Mesh, template_map: np.ndarray) -> np.ndarray:
    """For each vertex the template point of the nearest vertex that has one; shape (V,) int64.

    Template maps of remeshed collections leave vertices without a template point (about 30%
    on FAUST_r); overlap masks need every vertex, so those take the point of their nearest
    (Euclidean) vertex that has one.
    """
    inverse = template_inverse(template_map, mesh.n_vertices)
    covered = np.flatnonzero(inverse >= 0)
    if covered.size == 0:
        raise DatasetError(f"{mesh.name}: no vertex has a template point; the template map is empty.")
    missing = np.flatnonzero(inverse < 0)
    if missing.size:
        _, nearest = cKDTree(mesh.verts[covered]).query(mesh.verts[missing])
        inverse[missing] = inverse[covered[nearest]]
    return inverse


def ordered_pairs(indices: list[int], seed: int) -> list[tuple[int, int]]:
    """Every ordered pair ``(a, b)`` of distinct ``indices``, in an order drawn from ``seed``.

    The derived partial benchmarks and the depth-scan benchmarks share it, so that pair ``i``
    joins the same two shapes in both.
    """
    pairs = [(a, b) for a in indices for b in indices if a != b]
    order = np.random.default_rng(seed).permutation(len(pairs))
    return [pairs[i] for i in order]


def _compose(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """``second[first]`` where ``first >= 0``, else -1."""
    out = np.full(first.shape, -1, dtype=np.int64)
    valid = first >= 0
    out[valid] = second[first[valid]]
    return out


def _subset_inverse(vertex_map: np.ndarray, n_vertices: int) -> np.ndarray:
    """Inverse of a partial shape's subset map: for each source vertex its partial vertex or -1."""
    inverse = np.full(n_vertices, -1, dtype=np.int64)
    inverse[vertex_map] = np.arange(vertex_map.size)
    return inverse


class CollectionPairs:
    """What the benchmarks made from a `TemplateCollection` share: their pairs and their full shapes.

    A subclass is a dataclass with the fields ``collection``, ``indices`` and ``seed``, and
    calls `_order_pairs` in ``__post_init__``.
    """

    collection: TemplateCollection
    indices: list[int]
    seed: int
    pairs: list[tuple[int, int]]

    def _order_pairs(self) -> None:
        """Set ``pairs`` (`ordered_pairs` of ``indices`` and ``seed``) and an empty cache of full shapes."""
        self.pairs = ordered_pairs(self.indices, self.seed)
        self._meshes: dict[int, Mesh] = {}

    def __len__(self) -> int:
        return len(self.pairs)

    def _full(self, index: int) -> Mesh:
        """Full shape ``index`` of the collection, loaded once."""
        if index not in self._meshes:
            self._meshes[index] = self.collection.mesh(index)
        return self._meshes[index]


@dataclass
class DerivedPartialBenchmark(CollectionPairs):
    """P2F or P2P pairs made from a `TemplateCollection`.

    Parameters
    ----------
    collection : TemplateCollection
    indices : sequence of int
        Shapes of the collection to use (a split).
    kind : {"cuts", "holes", "ray"}
        Partial-shape generator.
    protocol : {"p2f", "p2p"}
    seed : int
        Seeds the pair order and every partial shape.
    name : str
        Benchmark name (for reports).
    partial_options : dict
        Extra keyword arguments of the partial generator.

    Notes
    -----
    The pairs are all ordered pairs (A, B), A != B, of ``indices``, in a seeded random
    order (take the first N for a smaller run). Pair ``i`` makes its partial shapes with
    seeds derived from ``(seed, i)``, so a pair does not change when others are skipped.
    """

    collection: TemplateCollection
    indices: list[int]
    kind: str
    protocol: str = "p2f"
    seed: int = 0
    name: str = ""
    partial_options: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.kind not in PARTIAL_KINDS:
            raise DatasetError(f"kind must be one of {PARTIAL_KINDS}; found {self.kind!r}")
        if self.protocol not in ("p2f", "p2p"):
            raise DatasetError(f"protocol must be 'p2f' or 'p2p'; found {self.protocol!r}")
        try:  # here, not in the first pair a worker makes
            partial_generator(self.kind, self.partial_options)
        except MeshError as err:
            raise DatasetError(f"{self.name or 'derived benchmark'}: {err}") from None
        self._order_pairs()

    @property
    def pair_names(self) -> list[str]:
        """``"<partial of A>-><B>"`` for every pair."""
        names = self.collection.names
        return [f"{names[a]}_{self.kind}->{names[b]}" for a, b in self.pairs]

    def __getitem__(self, i: int) -> ShapePair:
        a, b = self.pairs[i]
        mesh_a, mesh_b = self._full(a), self._full(b)
        seeds = np.random.SeedSequence([self.seed, i]).generate_state(2)
        partial_y = make_partial(mesh_a, self.kind, seed=int(seeds[0]), **self.partial_options)
        names = self.collection.names
        y = partial_y.mesh.renamed(f"{names[a]}_{self.kind}{i}")
        map_a, map_b = self.collection.template_map(a), self.collection.template_map(b)
        template_of_y = template_inverse(map_a, mesh_a.n_vertices)[partial_y.vertex_map]  # (V_y,) point or -1
        in_b = _compose(template_of_y, map_b)
        sym_map = self.collection.template_map_sym(b)
        in_b_sym = None if sym_map is None else _compose(template_of_y, sym_map)
        # Overlap is geometric: a vertex of B overlaps when its counterpart in A survived in Y.
        y_of_a = _subset_inverse(partial_y.vertex_map, mesh_a.n_vertices)
        overlap_b = y_of_a[map_a[nearest_template_points(mesh_b, map_b)]] >= 0
        if self.protocol == "p2f":
            overlap_y = np.ones(y.n_vertices, dtype=bool)  # every vertex of a partial of A lies on B
            return ShapePair(
                x=mesh_b, y=y, map_yx=in_b, overlap_x=overlap_b, overlap_y=overlap_y, map_yx_sym=in_b_sym, protocol="p2f"
            )
        partial_x = make_partial(mesh_b, self.kind, seed=int(seeds[1]), **self.partial_options)
        x = partial_x.mesh.renamed(f"{names[b]}_{self.kind}{i}")
        x_of_b = _subset_inverse(partial_x.vertex_map, mesh_b.n_vertices)
        map_yx = _compose(in_b, x_of_b)
        map_yx_sym = None if in_b_sym is None else _compose(in_b_sym, x_of_b)
        overlap_x = overlap_b[partial_x.vertex_map]
        nearest_in_b = map_b[nearest_template_points(mesh_a, map_a)[partial_y.vertex_map]]
        overlap_y = x_of_b[nearest_in_b] >= 0
        return ShapePair(x=x, y=y, map_yx=map_yx, overlap_x=overlap_x, overlap_y=overlap_y, map_yx_sym=map_yx_sym, protocol="p2p")


class SyntheticCollection(TemplateCollection):
    """`SyntheticHumans` as a template collection (identity correspondences, mirror map)."""

    def __init__(self, humans=None):
        from geofeat.datasets.synthetic import SyntheticHumans

        self.humans = humans if humans is not None else SyntheticHumans()

    @property
    def names(self) -> list[str]:
        return self.humans.names

    def mesh(self, index: int) -> Mesh:
        return self.humans.shape(index)

    def template_map(self, index: int) -> np.ndarray:
        return np.arange(self.humans.mirror.size, dtype=np.int64)

    def template_map_sym(self, index: int) -> np.ndarray:
        return self.humans.mirror


class RemeshedCollection(TemplateCollection):
    """The shapes of a FAUST_r/SCAPE_r split as a template collection."""

    def __init__(self, dataset):
        self.dataset = dataset

    @property
    def names(self) -> list[str]:
        return list(self.dataset.shape_names)

    def mesh(self, index: int) -> Mesh:
        return self.dataset.mesh(self.names[index])

    def template_map(self, index: int) -> np.ndarray:
        return self.dataset.template_map(self.names[index])

    def template_map_sym(self, index: int) -> np.ndarray | None:
        return self.dataset.template_map_sym(self.names[index])


#: Shapes of the built-in synthetic collection: 6 individuals x 5 poses; the last 2 individuals are the test split.
SYNTHETIC_INDIVIDUALS, SYNTHETIC_POSES, SYNTHETIC_TEST_INDIVIDUALS = 6, 5, 2


def synthetic_partial_benchmark(root, split: str, *, kind: str, protocol: str, seed: int = 0, **partial_options):
    """A derived benchmark on the built-in synthetic humans (``root`` is ignored: nothing is read).

    Splits: ``"train"`` the first 4 individuals (20 shapes), ``"test"`` the last 2 (10 shapes,
    90 ordered pairs), ``"all"`` every shape.
    """
    from geofeat.datasets.synthetic import SyntheticHumans

    collection = SyntheticCollection(SyntheticHumans(SYNTHETIC_INDIVIDUALS, SYNTHETIC_POSES, seed=0))
    n_train = (SYNTHETIC_INDIVIDUALS - SYNTHETIC_TEST_INDIVIDUALS) * SYNTHETIC_POSES
    indices = {"train": range(n_train), "test": range(n_train, len(collection)), "all": range(len(collection))}
    check_split(split, list(indices), "synthetic benchmarks")
    name = f"synthetic_{kind if protocol == 'p2f' else 'p2p'}"
    return DerivedPartialBenchmark(collection, list(indices[split]), kind, protocol, seed, name, dict(partial_options))


def remeshed_partial_benchmark(root, split: str, *, loader, kind: str, protocol: str, seed: int = 0, **partial_options):
    """A derived benchmark on a FAUST_r/SCAPE_r split (``loader`` is the dataset class)."""
    collection = RemeshedCollection(loader(root, split))
    return DerivedPartialBenchmark(collection, list(range(len(collection))), kind, protocol, seed, "", dict(partial_options))
