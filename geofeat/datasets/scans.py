"""Depth-scan benchmarks: a virtual depth scan of one shape matched to the full shape of another.

Each pair of a `ScanBenchmark` takes two different shapes A and B of a collection with a
common template (FAUST_r, SCAPE_r, the built-in humans), scans A with the virtual depth
camera of `geofeat.datasets.depth_camera` from a random viewpoint, and matches the scan (a
point cloud, ``y``) to the full mesh B (``x``): partial to full, as the derived CUTS, HOLES
and RAY benchmarks pair their shapes (every ordered pair, in a seeded order; pair ``i``
draws its scan from the seed ``(seed, i)``).

Ground truth. Each scan point keeps the surface point of A its ray hit (a face and
barycentric coordinates, ``pair.y_surface``). It stands for the corner of that face with the
largest barycentric weight, a vertex ``a`` of A; its counterpart in B is the vertex of B at
the first template point that lands on ``a`` (as for the vertices of a CUTS partial shape),
and ``-1`` where no template point does (about 30% of FAUST_r's vertices have none).
``map_yx_sym`` does the same through the mirrored template.

Overlap. Every scan point lies on A, which B covers whole: ``overlap_y`` is all True. A
vertex of B overlaps when its counterpart on A (through the template point of its nearest
vertex that has one) is a corner of a face the camera sees
(`geofeat.datasets.depth_camera.Scan.seen_faces`, an exact visibility test, independent of
the image resolution and the dropout).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from geofeat.datasets.base import check_split
from geofeat.datasets.depth_camera import DepthCamera, Scan, scan_mesh
from geofeat.datasets.derived import (
    SYNTHETIC_INDIVIDUALS,
    SYNTHETIC_POSES,
    SYNTHETIC_TEST_INDIVIDUALS,
    CollectionPairs,
    RemeshedCollection,
    SyntheticCollection,
    TemplateCollection,
    nearest_template_points,
    template_inverse,
)
from geofeat.datasets.records import ShapePair
from geofeat.errors import DatasetError, RenderError
from geofeat.mesh import require_faces

__all__ = ["ScanBenchmark", "depth_camera_from_options", "remeshed_scan_benchmark", "synthetic_scan_benchmark"]


def depth_camera_from_options(title: str, options: dict) -> DepthCamera:
    """A `DepthCamera` from loader options; `DatasetError` naming the settings for an unknown or bad one."""
    known = DepthCamera.field_names()
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise DatasetError(f"{title}: unknown option(s) {', '.join(unknown)}; the depth camera takes: {', '.join(known)}.")
    try:
        return DepthCamera(**options)
    except RenderError as err:
        raise DatasetError(f"{title}: {err}") from None


def _through(points: np.ndarray, template_map: np.ndarray) -> np.ndarray:
    """``template_map[points]`` where ``points >= 0``, else -1; shape of ``points``, int64."""
    return np.where(points >= 0, template_map[np.maximum(points, 0)], -1).astype(np.int64)


@dataclass
class ScanBenchmark(CollectionPairs):
    """P2F pairs: a depth scan of shape A (a point cloud) matched to the full mesh of shape B.

    Parameters
    ----------
    collection : TemplateCollection
    indices : sequence of int
        Shapes of the collection to use (a split).
    seed : int
        Seeds the pair order and every scan.
    name : str
        Benchmark name (for reports).
    camera : DepthCamera
        The depth camera's settings.

    Notes
    -----
    The pairs are all ordered pairs (A, B), A != B, of ``indices``, in a seeded random order
    (take the first N for a smaller run). Pair ``i`` scans A with the seed ``(seed, i)``, so a
    pair does not change when others are skipped.
    """

    collection: TemplateCollection
    indices: list[int]
    seed: int = 0
    name: str = ""
    camera: DepthCamera = field(default_factory=DepthCamera)

    def __post_init__(self) -> None:
        self._order_pairs()

    @property
    def pair_names(self) -> list[str]:
        """``"<scan of A>-><B>"`` for every pair (equals ``self[i].name``)."""
        names = self.collection.names
        return [f"{names[a]}_scan{i}->{names[b]}" for i, (a, b) in enumerate(self.pairs)]

    def scan(self, i: int) -> Scan:
        """The depth scan of pair ``i``: its points, their surface points and the camera position."""
        a, _ = self.pairs[i]
        seed = int(np.random.SeedSequence([self.seed, i]).generate_state(1)[0])
        return scan_mesh(self._full(a), self.camera, seed=seed, name=f"{self.collection.names[a]}_scan{i}")

    def __getitem__(self, i: int) -> ShapePair:
        a, b = self.pairs[i]
        mesh_a, mesh_b = self._full(a), self._full(b)
        scan = self.scan(i)
        map_a, map_b = self.collection.template_map(a), self.collection.template_map(b)
        template_of_y = template_inverse(map_a, mesh_a.n_vertices)[scan.surface.nearest_corner]  # (V_y,) point or -1
        sym_map = self.collection.template_map_sym(b)
        seen_a = np.zeros(mesh_a.n_vertices, dtype=bool)
        seen_a[require_faces(mesh_a, "a depth scan")[scan.seen_faces()].ravel()] = True
        overlap_b = seen_a[map_a[nearest_template_points(mesh_b, map_b)]]
        return ShapePair(
            x=mesh_b,
            y=scan.cloud,
            map_yx=_through(template_of_y, map_b),
            overlap_x=overlap_b,
            overlap_y=np.ones(scan.cloud.n_vertices, dtype=bool),
            map_yx_sym=None if sym_map is None else _through(template_of_y, sym_map),
            protocol="p2f",
            y_surface=scan.surface,
        )


def synthetic_scan_benchmark(root, split: str, *, seed: int = 0, **camera_options) -> ScanBenchmark:
    """Depth scans of the built-in synthetic humans matched to full shapes (``root`` is ignored: nothing is read).

    Splits as the other synthetic benchmarks: ``"train"`` the first 4 individuals, ``"test"`` the
    last 2 (10 shapes, 90 ordered pairs), ``"all"``. ``camera_options`` are `DepthCamera` settings.
    """
    from geofeat.datasets.synthetic import SyntheticHumans

    camera = depth_camera_from_options("synthetic_scans", camera_options)
    collection = SyntheticCollection(SyntheticHumans(SYNTHETIC_INDIVIDUALS, SYNTHETIC_POSES, seed=0))
    n_train = (SYNTHETIC_INDIVIDUALS - SYNTHETIC_TEST_INDIVIDUALS) * SYNTHETIC_POSES
    indices = {"train": range(n_train), "test": range(n_train, len(collection)), "all": range(len(collection))}
    check_split(split, list(indices), "synthetic benchmarks")
    return ScanBenchmark(collection, list(indices[split]), seed, "synthetic_scans", camera)


def remeshed_scan_benchmark(root, split: str, *, loader, seed: int = 0, **camera_options) -> ScanBenchmark:
    """Depth scans of a FAUST_r/SCAPE_r split matched to its full shapes (``loader`` is the dataset class).

    ``camera_options`` are `DepthCamera` settings (``image_size``, ``depth_noise``, ...).
    """
    name = f"{loader.title.lower()}_scans"
    camera = depth_camera_from_options(name, camera_options)
    collection = RemeshedCollection(loader(root, split))
    return ScanBenchmark(collection, list(range(len(collection))), seed, name, camera)
