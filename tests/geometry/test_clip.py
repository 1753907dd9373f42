import numpy as np
import pytest
from shapes import sphere

from geofeat.errors import MeshError
from geofeat.geometry.clip import clip_plane
from geofeat.topology import triangle_areas

# The unit square as two triangles, both facing +z.
SQUARE_VERTS = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=np.float64)
SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def grid(n: int, dtype=np.float64) -> tuple[np.ndarray, np.ndarray]:
    """The unit square in the z = 0 plane, n x n cells, two triangles a cell, facing +z."""
    xs = np.linspace(0.0, 1.0, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]).astype(dtype)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return verts, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def clipped_square_area(point: np.ndarray, normal: np.ndarray) -> float:
    """Area of the part of the unit square (z = 0) with n . (x - p) > 0, by clipping the polygon."""
    polygon = [np.array(p, dtype=float) for p in ([0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0])]
    kept = []
    for k, current in enumerate(polygon):
        following = polygon[(k + 1) % len(polygon)]
        s0, s1 = normal @ (current - point), normal @ (following - point)
        if s0 > 0:
            kept.append(current)
        if (s0 > 0) != (s1 > 0):
            kept.append(current + (s0 / (s0 - s1)) * (following - current))
    if len(kept) < 3:
        return 0.0
    xy = np.array(kept)[:, :2]
    return 0.5 * abs(np.dot(xy[:, 0], np.roll(xy[:, 1], -1)) - np.dot(xy[:, 1], np.roll(xy[:, 0], -1)))


def test_a_square_cut_through_its_middle():
    verts, faces, parent = clip_plane(SQUARE_VERTS, SQUARE_FACES, [0.5, 0.0, 0.0], [1.0, 0.0, 0.0])
    # the half x > 0.5 is kept: two new vertices on the square's edges, one on its diagonal
    expected_verts = [[0.5, 0, 0], [1, 0, 0], [0.5, 0.5, 0], [1, 1, 0], [0.5, 1, 0]]
    np.testing.assert_array_equal(verts, expected_verts)
    # face 0 keeps two corners (a quad, two triangles), face 1 one corner (a triangle)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [2, 1, 3], [4, 2, 3]])
    np.testing.assert_array_equal(parent, [0, 0, 1])
    assert verts.dtype == np.float64 and faces.dtype == np.int64 and parent.dtype == np.int64
    # only the kept side, new vertices exactly on the plane, half the area, the same orientation
    assert verts[:, 0].min() == 0.5 and np.count_nonzero(verts[:, 0] == 0.5) == 3
    assert triangle_areas(verts, faces).sum() == pytest.approx(0.5)
    e1, e2 = verts[faces[:, 1]] - verts[faces[:, 0]], verts[faces[:, 2]] - verts[faces[:, 0]]
    assert np.all(np.cross(e1, e2)[:, 2] > 0)


def test_the_normal_picks_the_side_and_its_length_does_not_matter():
    left, left_faces, _ = clip_plane(SQUARE_VERTS, SQUARE_FACES, [0.5, 0.0, 0.0], [-3.0, 0.0, 0.0])
    assert left[:, 0].max() == 0.5 and triangle_areas(left, left_faces).sum() == pytest.approx(0.5)
    unit = clip_plane(SQUARE_VERTS, SQUARE_FACES, [0.5, 0.0, 0.0], [1.0, 0.0, 0.0])
    long = clip_plane(SQUARE_VERTS, SQUARE_FACES, [0.5, 0.0, 0.0], [4.0, 0.0, 0.0])
    for a, b in zip(unit, long, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_vertex_on_the_plane_is_not_kept_but_reached_by_the_cut():
    # plane x = 0: the corners at x = 0 have value 0, which is not kept; the edges from them
    # are cut at t = 0, so the new vertices fall on them and merge: the whole square comes back
    verts, faces, parent = clip_plane(SQUARE_VERTS, SQUARE_FACES, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(verts, SQUARE_VERTS)
    np.testing.assert_array_equal(faces, [[0, 1, 2], [3, 0, 2]])  # face 1 restarts at its cut edge (1, 2)
    # plane x = 1 with the normal pointing away: no vertex has a positive value, nothing is left
    verts, faces, parent = clip_plane(SQUARE_VERTS, SQUARE_FACES, [1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert verts.shape == (0, 3) and faces.shape == (0, 3) and parent.shape == (0,)


def test_every_vertex_is_kept_or_on_the_plane_and_the_area_is_the_clipped_polygon():
    verts, faces = grid(9)
    rng = np.random.default_rng(0)
    for _ in range(20):
        point = np.append(rng.uniform(0.2, 0.8, 2), 0.0)
        normal = rng.standard_normal(3)
        out, out_faces, parent = clip_plane(verts, faces, point, normal)
        value = (out - point) @ normal
        # on the plane up to the float32 rounding of the vertex values (what VTK interpolates from)
        on_plane = np.abs(value) <= 1e-7 * np.linalg.norm(normal)
        from_source = (out[:, None, :] == verts[None, :, :]).all(axis=2).any(axis=1)
        assert np.all(on_plane | (from_source & (value > 0)))  # no vertex off the plane on the dropped side
        assert np.all(np.bincount(out_faces.ravel(), minlength=len(out)) > 0)  # every vertex used
        assert triangle_areas(out, out_faces).sum() == pytest.approx(clipped_square_area(point, normal), abs=1e-7)
        assert np.all(np.diff(parent) >= 0)
        # each output triangle lies in its source face: its centroid's barycentric weights are >= 0
        a, b, c = (verts[faces[parent, k]][:, :2] for k in range(3))
        centroid = out[out_faces].mean(axis=1)[:, :2]
        basis = np.stack([b - a, c - a], axis=2)
        weights = np.linalg.solve(basis, (centroid - a)[:, :, None])[:, :, 0]
        assert np.all(weights >= -1e-9) and np.all(weights.sum(axis=1) <= 1 + 1e-9)


def test_vertices_are_numbered_in_order_of_first_use():
    verts, faces = grid(6)
    out, out_faces, _ = clip_plane(verts, faces, [0.5, 0.5, 0.0], [0.3, 1.0, 0.2])
    flat = out_faces.ravel()
    _, first_use = np.unique(flat, return_index=True)
    assert np.array_equal(flat[np.sort(first_use)], np.arange(len(out)))


def test_vertices_at_one_position_merge_and_collapsed_triangles_go():
    # two triangles sharing an edge only by position (vertices 2, 3 repeat 1, 2's coordinates)
    verts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [3, 5, 4]])
    out, out_faces, parent = clip_plane(verts, faces, [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert len(out) == 4 and np.array_equal(out_faces, [[0, 1, 2], [1, 3, 2]]) and np.array_equal(parent, [0, 1])
    # a triangle with two corners at one position names a vertex twice: dropped
    out, out_faces, parent = clip_plane(verts, [[0, 1, 3], [0, 1, 2]], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert np.array_equal(parent, [1]) and len(out) == 3


def test_float32_vertices_give_float32_vertices_rounded_once():
    verts, faces = grid(5, dtype=np.float32)
    out32, faces32, _ = clip_plane(verts, faces, [0.41, 0.5, 0.0], [1.0, 0.2, 0.0])
    out64, faces64, _ = clip_plane(verts.astype(np.float64), faces, [0.41, 0.5, 0.0], [1.0, 0.2, 0.0])
    assert out32.dtype == np.float32 and out64.dtype == np.float64
    np.testing.assert_array_equal(faces32, faces64)
    np.testing.assert_array_equal(out32, out64.astype(np.float32))


def test_a_closed_surface_cut_through_its_centre():
    mesh = sphere(3)
    verts, faces, parent = clip_plane(mesh.verts, mesh.faces, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    assert verts[:, 2].min() == 0.0 and np.all(verts[:, 2] >= 0.0)
    # the cut leaves one boundary loop on the plane: every boundary edge has both ends at z = 0
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = unique[counts == 1]
    assert boundary.size and np.all(verts[boundary, 2] == 0.0)


@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((SQUARE_VERTS, SQUARE_FACES, [0, 0, 0], [0, 0, 0]), "zero vector"),
        ((SQUARE_VERTS, SQUARE_FACES, [0, 0], [1, 0, 0]), "shape \\(3,\\)"),
        ((SQUARE_VERTS, SQUARE_FACES, [0, 0, np.nan], [1, 0, 0]), "finite"),
        ((SQUARE_VERTS[:, :2], SQUARE_FACES, [0, 0, 0], [1, 0, 0]), "shape \\(V, 3\\)"),
        ((SQUARE_VERTS.astype(int), SQUARE_FACES, [0, 0, 0], [1, 0, 0]), "float32 or float64"),
        ((SQUARE_VERTS, SQUARE_FACES + 2, [0, 0, 0], [1, 0, 0]), "must lie in"),
        ((SQUARE_VERTS, SQUARE_FACES.astype(float), [0, 0, 0], [1, 0, 0]), "integer array"),
    ],
)
def test_bad_input_is_a_mesh_error(args, match):
    with pytest.raises(MeshError, match=match):
        clip_plane(*args)
