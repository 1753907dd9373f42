import numpy as np
import pytest
import torch

from geofeat import Mesh
from geofeat.errors import MeshError, TrainingError
from geofeat.geometry.partial import PartialShape, cut_partial
from geofeat.geometry.partial_reference import (
    CUT_MAX_TRIES,
    cut_partial_reference,
    draw_cut_normal,
    draw_holes,
    holes_partial_reference,
    largest_component_by_face_count,
    nearest_source_vertices,
)
from geofeat.train.samples import training_partial_reference

# Normals for the lopsided mesh below (plane through its bounding-box centre x = 5, y = 0.5).
KEEPS_TOO_LITTLE = [1.0, 0.0, 0.0]  # the sparse strip's end: under a tenth of the vertices
KEEPS_TOO_MUCH = [-1.0, 0.0, 0.0]  # the dense plate and half the strip: over nine tenths
SPLITS_THE_PLATE = [0.02, 1.0, 0.0]  # the plate above y = 0.6 or so: accepted


def plate(nx: int, ny: int, x: tuple, y: tuple, first: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat grid of nx x ny vertices in z = 0, two triangles a cell, vertex indices from ``first``."""
    gx, gy = np.meshgrid(np.linspace(*x, nx), np.linspace(*y, ny))
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    idx = first + np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return verts, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


@pytest.fixture(scope="module")
def lopsided() -> Mesh:
    """A dense 20 x 20 plate on [0, 1]^2 and a sparse 5 x 2 strip on [1.5, 10] x [0, 1] (410 vertices)."""
    v1, f1 = plate(20, 20, (0.0, 1.0), (0.0, 1.0), 0)
    v2, f2 = plate(5, 2, (1.5, 10.0), (0.0, 1.0), 400)
    verts = np.concatenate([v1, v2]).astype(np.float32)
    return Mesh(verts, np.concatenate([f1, f2]), name="lopsided")


# --- PartialShape.exact ----------------------------------------------------------------------


def test_partial_shape_is_exact_by_default_and_checks_it():
    mesh = Mesh(np.eye(3), [[0, 1, 2]])
    record = PartialShape(mesh, [0, 1, 2], [0], "cuts")
    assert record.exact is True
    with pytest.raises(MeshError, match="exact=False"):
        PartialShape(mesh, [2, 0, 0], [0], "cuts")
    loose = PartialShape(mesh, [2, 0, 0], [0], "cuts", exact=False)  # nearest vertices: repeats, any order
    assert loose.exact is False and loose.vertex_map.tolist() == [2, 0, 0]
    with pytest.raises(MeshError, match="no inverse"):
        loose.source_to_partial(3)
    with pytest.raises(MeshError, match="True or False"):
        PartialShape(mesh, [0, 1, 2], [0], "cuts", exact=1)
    with pytest.raises(MeshError, match=">= 0"):
        PartialShape(mesh, [-1, 0, 0], [0], "cuts", exact=False)


def test_geofeat_generators_stay_exact(faust_mesh):
    assert cut_partial(faust_mesh, 0).exact is True


# --- CUTS ------------------------------------------------------------------------------------


def test_cut_keeps_the_side_of_the_normal_through_the_bounding_box_centre(lopsided):
    shape = cut_partial_reference(lopsided, np.array([SPLITS_THE_PLATE]))
    assert shape.kind == "cuts" and shape.exact is False
    assert shape.info["tries"] == 1 and not shape.info["whole_mesh"]
    np.testing.assert_array_equal(shape.info["plane_point"], [5.0, 0.5, 0.0])
    value = (shape.mesh.verts - shape.info["plane_point"]) @ np.array(SPLITS_THE_PLATE)
    assert value.min() > -1e-6 and np.count_nonzero(np.abs(value) < 1e-6) > 10  # new vertices on the plane
    assert 0.1 < shape.info["keep_fraction"] < 0.9
    assert shape.info["keep_fraction"] == shape.mesh.n_vertices / lopsided.n_vertices
    assert shape.mesh.verts[:, 0].max() <= 1.0  # the largest component: the plate's part, not the strip's
    assert len(shape.face_map) == len(shape.mesh.faces) and shape.face_map.max() < 2 * 19 * 19


def test_cut_ground_truth_is_the_nearest_source_vertex(lopsided):
    shape = cut_partial_reference(lopsided, np.array([SPLITS_THE_PLATE]))
    dist = np.linalg.norm(shape.mesh.verts[:, None, :] - lopsided.verts[None, :, :], axis=2)
    nearest = dist.min(axis=1)
    np.testing.assert_allclose(dist[np.arange(len(dist)), shape.vertex_map], nearest, atol=1e-6)
    second = np.sort(dist, axis=1)[:, 1]
    clear = second - nearest > 1e-5  # away from near ties the index is the same
    assert clear.sum() > 0.9 * len(clear)
    np.testing.assert_array_equal(shape.vertex_map[clear], dist.argmin(axis=1)[clear])


def test_cut_face_map_gives_the_face_each_triangle_was_cut_from(lopsided):
    shape = cut_partial_reference(lopsided, np.array([SPLITS_THE_PLATE]))
    source = lopsided.verts[lopsided.faces[shape.face_map]][:, :, :2]
    centroid = shape.mesh.verts[shape.mesh.faces].mean(axis=1)[:, :2]
    basis = np.stack([source[:, 1] - source[:, 0], source[:, 2] - source[:, 0]], axis=2)
    weights = np.linalg.solve(basis, (centroid - source[:, 0])[:, :, None])[:, :, 0]
    assert np.all(weights >= -1e-6) and np.all(weights.sum(axis=1) <= 1 + 1e-6)


def test_rejected_tries_are_retried_in_order(lopsided):
    normals = np.array([KEEPS_TOO_LITTLE, KEEPS_TOO_MUCH] * 2 + [SPLITS_THE_PLATE])
    shape = cut_partial_reference(lopsided, normals)
    assert shape.info["tries"] == 5 and not shape.info["whole_mesh"]
    np.testing.assert_array_equal(shape.info["normals"], normals)
    np.testing.assert_array_equal(shape.info["plane_normal"], SPLITS_THE_PLATE)
    first = cut_partial_reference(lopsided, normals[4:])
    np.testing.assert_array_equal(shape.mesh.verts, first.mesh.verts)
    np.testing.assert_array_equal(shape.mesh.faces, first.mesh.faces)


def test_the_whole_mesh_after_ten_tries_even_when_the_tenth_would_do(lopsided):
    never = np.array([KEEPS_TOO_LITTLE] * CUT_MAX_TRIES)
    # the official loop's counter is 0 after the tenth try, which selects the whole mesh
    last = np.array([KEEPS_TOO_LITTLE] * (CUT_MAX_TRIES - 1) + [SPLITS_THE_PLATE])
    ninth = np.array([KEEPS_TOO_LITTLE] * (CUT_MAX_TRIES - 2) + [SPLITS_THE_PLATE] * 2)
    for normals in (never, last):
        shape = cut_partial_reference(lopsided, normals)
        assert shape.info["whole_mesh"] and shape.info["tries"] == CUT_MAX_TRIES
        np.testing.assert_array_equal(shape.mesh.verts, lopsided.verts)
        np.testing.assert_array_equal(shape.mesh.faces, lopsided.faces)
        np.testing.assert_array_equal(shape.face_map, np.arange(len(lopsided.faces)))
        np.testing.assert_array_equal(shape.vertex_map, np.arange(lopsided.n_vertices))
    shape = cut_partial_reference(lopsided, ninth)
    assert not shape.info["whole_mesh"] and shape.info["tries"] == CUT_MAX_TRIES - 1


def test_a_random_state_is_drawn_once_a_try(lopsided):
    rng = np.random.RandomState(3)
    shape = cut_partial_reference(lopsided, rng)
    replay = np.random.RandomState(3)
    expected = np.array([replay.randn(3) for _ in range(shape.info["tries"])])
    np.testing.assert_array_equal(shape.info["normals"], expected)
    assert rng.randn() == replay.randn()  # both streams are at the same place
    assert np.array_equal(draw_cut_normal(np.random.RandomState(7)), np.random.RandomState(7).randn(3))
    with pytest.raises(MeshError, match="RandomState"):
        draw_cut_normal(np.random.default_rng(0))


def test_too_few_normals_is_an_error(lopsided):
    with pytest.raises(MeshError, match="only 2 were given"):
        cut_partial_reference(lopsided, np.array([KEEPS_TOO_LITTLE, KEEPS_TOO_MUCH]))
    with pytest.raises(MeshError, match="max_tries"):
        cut_partial_reference(lopsided, np.array([SPLITS_THE_PLATE]), max_tries=0)


# --- HOLES -----------------------------------------------------------------------------------


def euclidean(mesh: Mesh) -> np.ndarray:
    return np.linalg.norm(mesh.verts[:, None, :] - mesh.verts[None, :, :], axis=2).astype(np.float32)


def test_holes_drop_the_balls_and_keep_the_largest_component(lopsided):
    dist = euclidean(lopsided)
    centres = np.array([21 * 5, 21 * 5, 14 * 20 + 12])  # a repeat is allowed
    shape = holes_partial_reference(lopsided, centres, 0.2, dist)
    assert shape.kind == "holes" and shape.exact is False
    kept = np.flatnonzero((dist[centres] >= np.float32(0.2)).all(axis=0))
    faces_in = np.flatnonzero(np.isin(lopsided.faces, kept).all(axis=1))
    plate_faces = faces_in[faces_in < 2 * 19 * 19]  # the plate's faces outnumber the strip's
    np.testing.assert_array_equal(shape.face_map, plate_faces)
    used = np.unique(lopsided.faces[plate_faces])
    np.testing.assert_array_equal(shape.vertex_map, used)  # source vertices, increasing: nearest is itself
    np.testing.assert_array_equal(shape.mesh.verts, lopsided.verts[used])
    assert shape.info["n_holes"] == 3 and shape.info["radius"] == float(np.float32(0.2))


def test_holes_ground_truth_takes_the_first_of_two_vertices_at_one_position():
    # vertex 3 repeats vertex 1's position: the partial vertex 3 maps to 1
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 0], [5, 5, 0]], dtype=np.float32)
    mesh = Mesh(verts, [[0, 1, 2], [3, 4, 2], [4, 5, 2]])
    dist = euclidean(mesh)
    shape = holes_partial_reference(mesh, [5], 1.0, dist)
    assert shape.mesh.n_vertices == 3  # the faces [0, 1, 2] and [3, 4, 2] share only vertex 2: the first wins
    np.testing.assert_array_equal(shape.face_map, [0])
    shape = holes_partial_reference(mesh, [0, 5], 0.5, dist)
    np.testing.assert_array_equal(shape.face_map, [1])
    np.testing.assert_array_equal(shape.vertex_map, [2, 1, 4])  # partial vertices 2, 3, 4 of the source


def test_holes_that_leave_no_face_are_an_error(lopsided):
    with pytest.raises(MeshError, match="no face"):
        holes_partial_reference(lopsided, [0], 100.0, euclidean(lopsided))
    with pytest.raises(MeshError, match="geodesic matrix"):
        holes_partial_reference(lopsided, [0], 0.1, np.zeros((3, 3), dtype=np.float32))
    with pytest.raises(MeshError, match="vertex indices"):
        holes_partial_reference(lopsided, [lopsided.n_vertices], 0.1, euclidean(lopsided))


def test_draw_holes_replays_torch_default_stream():
    torch.manual_seed(3)
    from_default = draw_holes(5000)
    seeded = draw_holes(5000, torch.Generator().manual_seed(3))
    for draw in (from_default, seeded):
        # what the official generate_random_holes drew after torch.manual_seed(3) (torch 2.13, CPU)
        assert draw.n_holes == 8 and draw.centres.tolist() == [1737, 3667, 1360, 2280, 2840, 3525, 2981, 1739]
        assert draw.radius.dtype == np.float32
        assert draw.radius == np.float32((0.16 - 0.1) * torch.tensor([0.10556936], dtype=torch.float32) + 0.1)
    for seed in range(20):
        draw = draw_holes(100, torch.Generator().manual_seed(seed))
        assert 4 <= draw.n_holes <= 12 and draw.centres.shape == (draw.n_holes,) and 0.1 <= draw.radius < 0.16


# --- shared pieces ---------------------------------------------------------------------------


def test_largest_component_counts_faces_not_area_and_ties_go_to_the_first():
    big_area = [[0, 1, 2], [1, 3, 2]]  # 2 faces
    many_faces = [[4, 5, 6], [5, 7, 6], [6, 7, 8], [7, 9, 8]]  # 4 faces
    assert largest_component_by_face_count(np.array(big_area + many_faces)).tolist() == [False] * 2 + [True] * 4
    tie = np.array([[0, 1, 2], [3, 4, 5]])
    assert largest_component_by_face_count(tie).tolist() == [True, False]
    assert largest_component_by_face_count(tie[::-1]).tolist() == [True, False]


def test_nearest_source_vertices_first_index_among_equals():
    source = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 0], [0, 2, 0]], dtype=np.float32)
    partial = np.array([[1, 0, 0], [0.1, 0, 0], [0, 1.9, 0]], dtype=np.float32)
    assert nearest_source_vertices(partial, source).tolist() == [1, 0, 3]


# --- the training loop's draw ------------------------------------------------------------------


class _Answers(np.random.RandomState):
    """A RandomState whose ``randint`` answers from a list (the generator choice of each try)."""

    def __init__(self, choices):
        super().__init__(0)
        self.choices = list(choices)

    def randint(self, low, high=None, size=None, dtype=int):
        assert (low, size) == (0, None)
        return self.choices.pop(0)


def test_training_draw_chooses_in_the_official_order_and_tries_again_below_ten_vertices(lopsided):
    flat = np.zeros((len(lopsided.verts), len(lopsided.verts)), dtype=np.float32) + 5.0
    # kinds given in another order are taken in the official one (ray, cuts, holes): index 1 of (cuts, holes) is holes
    holes_everywhere = np.zeros_like(flat)  # every vertex within any radius of every centre: no face, a failed try
    state = _Answers([1, 1, 0])
    partial = training_partial_reference(lopsided, ("holes", "cuts"), holes_everywhere, state, torch.Generator().manual_seed(0))
    assert partial.kind == "cuts" and partial.info["tries"] == 3 and not partial.exact
    assert partial.mesh.n_vertices >= 10 and state.choices == []
    with pytest.raises(TrainingError, match="non-empty subset"):
        training_partial_reference(lopsided, ("cuts", "spin"), flat, _Answers([0]))


def test_training_draw_gives_up_after_ten_tries():
    verts, faces = plate(3, 3, (0.0, 1.0), (0.0, 1.0), 0)  # 9 vertices: never the 10 the loop wants
    state = _Answers([0] * 10)
    assert training_partial_reference(Mesh(verts, faces, name="small"), ("cuts",), np.zeros((9, 9)), state) is None
    assert state.choices == []  # ten tries, each drew its generator
