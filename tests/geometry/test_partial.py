import time

import numpy as np
import pytest
import trimesh
from shapes import sphere

import geofeat
from geofeat import Mesh
from geofeat.errors import MeshError
from geofeat.geometry.geodesic import distances_from
from geofeat.geometry.partial import (
    PartialShape,
    cut_partial,
    holes_partial,
    largest_component,
    largest_component_submesh,
    make_partial,
    ray_partial,
    shape_centre,
    submesh,
    visible_faces,
)

KINDS = ("cuts", "holes", "ray")
FAUST_IDS = ("000", "013", "027", "051", "099")  # several subjects and poses
SEEDS = (0, 1)
DEFAULT_KEEP = {"cuts": (0.1, 0.9), "holes": (0.05, 1.0), "ray": (0.05, 1.0)}


@pytest.fixture(scope="module")
def faust_shapes(faust_dir) -> list[Mesh]:
    return [geofeat.load_mesh(faust_dir / "off" / f"tr_reg_{i}.off") for i in FAUST_IDS]


@pytest.fixture(scope="module")
def partials(faust_shapes) -> dict:
    """Every (kind, shape, seed) partial shape, made once for the module."""
    return {
        (kind, index, seed): make_partial(mesh, kind, seed)
        for kind in KINDS
        for index, mesh in enumerate(faust_shapes)
        for seed in SEEDS
    }


def grid_plate(n: int, half: float, z: float) -> tuple[np.ndarray, np.ndarray]:
    """A flat square [-half, half]^2 at height z, n x n cells, two triangles a cell."""
    xs = np.linspace(-half, half, n + 1)
    gx, gy = np.meshgrid(xs, xs, indexing="ij")
    verts = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return verts, faces


def two_plates(big: tuple, small: tuple) -> Mesh:
    v1, f1 = grid_plate(*big)
    v2, f2 = grid_plate(*small)
    return Mesh(np.vstack([v1, v2]), np.vstack([f1, f2 + len(v1)]), name="plates")


# --- invariants on real shapes ------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_partial_is_an_exact_subset_of_the_source(kind, faust_shapes, partials):
    for index, source in enumerate(faust_shapes):
        for seed in SEEDS:
            p = partials[kind, index, seed]
            assert isinstance(p, PartialShape) and p.kind == kind
            vmap, fmap = p.vertex_map, p.face_map
            assert vmap.dtype == np.int64 and fmap.dtype == np.int64
            assert vmap.shape == (p.mesh.n_vertices,) and fmap.shape == (len(p.mesh.faces),)
            assert np.all(np.diff(vmap) > 0) and vmap[0] >= 0 and vmap[-1] < source.n_vertices  # injective, sorted
            assert np.array_equal(p.mesh.verts, source.verts[vmap])  # bit-exact coordinates
            assert np.array_equal(vmap[p.mesh.faces], source.faces[fmap])  # each face is its source face
            assert np.unique(fmap).size == fmap.size
            assert np.array_equal(np.unique(p.mesh.faces), np.arange(p.mesh.n_vertices))  # no unreferenced vertex
            assert p.mesh.n_components() == 1
            assert largest_component(p.mesh, np.arange(len(p.mesh.faces))).size == len(p.mesh.faces)  # edge-connected
            fraction = p.mesh.n_vertices / source.n_vertices
            lo, hi = DEFAULT_KEEP[kind]
            assert lo <= fraction <= hi and p.info["keep_fraction"] == fraction
            assert p.mesh.n_vertices < source.n_vertices


@pytest.mark.parametrize("kind", KINDS)
def test_same_seed_same_shape_other_seed_other_shape(kind, faust_shapes, partials):
    source = faust_shapes[0]
    first = partials[kind, 0, 0]
    again = make_partial(source, kind, 0)
    assert again.mesh.hash == first.mesh.hash and np.array_equal(again.vertex_map, first.vertex_map)
    for key, value in first.info.items():
        np.testing.assert_array_equal(again.info[key], value)
    from_generator = make_partial(source, kind, np.random.default_rng(0))
    assert from_generator.mesh.hash == first.mesh.hash
    assert partials[kind, 0, 1].mesh.hash != first.mesh.hash


def test_dispatcher_calls_the_generators(faust_shapes, partials):
    source = faust_shapes[1]
    for kind, generator in (("cuts", cut_partial), ("holes", holes_partial), ("ray", ray_partial)):
        assert generator(source, 1).mesh.hash == partials[kind, 1, 1].mesh.hash


def test_partial_record_is_read_only_and_inverts(partials, faust_shapes):
    p = partials["holes", 0, 0]
    with pytest.raises(ValueError):
        p.vertex_map[0] = 1
    with pytest.raises(TypeError):
        p.info["radius"] = 1.0
    inverse = p.source_to_partial(faust_shapes[0].n_vertices)
    assert np.array_equal(inverse[p.vertex_map], np.arange(p.mesh.n_vertices))
    assert np.count_nonzero(inverse >= 0) == p.mesh.n_vertices and set(np.unique(inverse[inverse < 0])) == {-1}
    with pytest.raises(MeshError, match="n_source_vertices"):
        p.source_to_partial(10)


# --- per kind -------------------------------------------------------------------------------


def test_cut_keeps_one_side_of_a_plane_through_the_centroid(faust_shapes, partials):
    for index, source in enumerate(faust_shapes):
        for seed in SEEDS:
            p = partials["cuts", index, seed]
            normal, point = p.info["plane_normal"], p.info["plane_point"]
            assert abs(np.linalg.norm(normal) - 1) < 1e-12
            np.testing.assert_allclose(point, shape_centre(source), rtol=0, atol=1e-15)
            assert np.all((p.mesh.verts - point) @ normal >= 0)


def test_cut_bbox_centre_option(faust_shapes):
    source = faust_shapes[2]
    p = cut_partial(source, 3, center="bbox")
    np.testing.assert_array_equal(p.info["plane_point"], 0.5 * (source.verts.min(0) + source.verts.max(0)))
    assert np.all((p.mesh.verts - p.info["plane_point"]) @ p.info["plane_normal"] >= 0)


def test_holes_remove_geodesic_balls_of_the_drawn_radius(faust_shapes, partials):
    for index, source in enumerate(faust_shapes):
        sqrt_area = np.sqrt(source.area())
        for seed in SEEDS:
            p = partials["holes", index, seed]
            centres, radius = p.info["centres"], p.info["radius"]
            assert 4 <= centres.size <= 12 and 0.10 <= radius < 0.16
            assert p.info["radius_abs"] == pytest.approx(radius * sqrt_area, rel=1e-15)
            nearest = distances_from(source, centres).min(axis=0)
            assert nearest[p.vertex_map].min() >= p.info["radius_abs"]  # no kept vertex inside a ball
            inside = np.flatnonzero(nearest < p.info["radius_abs"])
            assert inside.size > centres.size and not np.isin(inside, p.vertex_map).any()


def test_holes_options_are_honoured(faust_shapes):
    p = holes_partial(faust_shapes[0], 5, n_holes=(2, 2), radius_range=(0.05, 0.05))
    assert p.info["centres"].size == 2 and p.info["radius"] == 0.05
    heat = holes_partial(faust_shapes[0], 5, n_holes=(2, 2), radius_range=(0.05, 0.05), geodesic="heat")
    assert np.array_equal(heat.info["centres"], p.info["centres"])
    assert abs(heat.mesh.n_vertices - p.mesh.n_vertices) < 0.05 * p.mesh.n_vertices


def test_ray_part_faces_the_camera(faust_shapes, partials):
    for index, source in enumerate(faust_shapes):
        oriented = trimesh.Trimesh(source.verts, source.faces, process=False)
        assert oriented.volume > 0  # outward normals, so "facing the camera" is meaningful
        for seed in SEEDS:
            p = partials["ray", index, seed]
            eye, target = p.info["eye"], p.info["target"]
            tri = p.mesh.verts[p.mesh.faces]
            normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
            facing = np.einsum("ij,ij->i", normals, eye - tri.mean(axis=1)) > 0
            assert facing.all()
            mean_normal = normals.sum(axis=0)
            assert mean_normal @ (eye - target) > 0.5 * np.linalg.norm(mean_normal) * np.linalg.norm(eye - target)
            seen = visible_faces(source, eye, target)
            assert np.array_equal(p.face_map, largest_component(source, np.flatnonzero(seen)))
            assert 0 < seen.sum() < 0.6 * len(seen)  # a closed surface: at most about half is seen


def test_visible_faces_on_a_convex_surface_are_the_front_faces():
    ball = sphere(4)
    tri = ball.verts[ball.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rng = np.random.default_rng(7)
    for distance in (1.3, 2.0, 10.0):
        direction = rng.normal(size=3)
        eye = distance * direction / np.linalg.norm(direction)
        facing = np.einsum("ij,ij->i", normals, eye - tri.mean(axis=1))
        clear = np.abs(facing) > 1e-9
        seen = visible_faces(ball, eye, np.zeros(3))
        assert np.array_equal(seen[clear], facing[clear] > 0)
        assert 0.1 * len(seen) < seen.sum() < 0.5 * len(seen)


def test_visible_faces_hides_what_lies_behind_an_occluder():
    # a 2 x 2 plate at z=0, a 0.6 x 0.6 plate at z=0.5 in front of it, the eye on the z axis.
    mesh = two_plates(big=(20, 1.0, 0.0), small=(6, 0.3, 0.5))
    n_big = 2 * 20 * 20
    eye = np.array([0.0, 0.0, 5.0])
    seen = visible_faces(mesh, eye, np.zeros(3))
    centroids = mesh.verts[mesh.faces[:n_big]].mean(axis=1)
    hit_small_plate = np.all(np.abs(0.9 * centroids[:, :2]) <= 0.3, axis=1)  # where the ray crosses z = 0.5
    assert hit_small_plate.sum() > 20
    assert np.array_equal(seen[:n_big], ~hit_small_plate)
    assert seen[n_big:].all()
    # from behind, the small plate is hidden by the big one
    assert not visible_faces(mesh, -eye, np.zeros(3))[n_big:].any()


def test_visible_faces_needs_the_camera_outside_the_bounding_sphere():
    with pytest.raises(MeshError, match="outside the bounding sphere"):
        visible_faces(sphere(2), np.array([0.0, 0.0, 0.5]), np.zeros(3))
    with pytest.raises(MeshError, match="camera_distance"):
        ray_partial(sphere(2), 0, camera_distance=1.0)


def test_ray_is_fast_on_a_faust_shape(faust_shapes):
    source = faust_shapes[0]
    timings = []
    for seed in range(3):
        start = time.perf_counter()
        ray_partial(source, seed)
        timings.append(time.perf_counter() - start)
    assert np.median(timings) < 1.0, f"ray_partial took {timings} s on {source.n_vertices} vertices"


# --- the shared helper ---------------------------------------------------------------------------


def test_largest_component_is_by_area_and_by_shared_edges():
    # big plate: 8 large faces (area 4); small plate: 200 tiny faces (area 0.04)
    mesh = two_plates(big=(2, 1.0, 0.0), small=(10, 0.1, 1.0))
    kept = largest_component(mesh, np.arange(len(mesh.faces)))
    assert np.array_equal(kept, np.arange(8))
    # two triangles touching at one vertex (a bow tie) are two components
    bow_tie = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [-2, 0, 0], [0, -2, 0]], [[0, 1, 2], [0, 3, 4]])
    assert np.array_equal(largest_component(bow_tie, [0, 1]), [1])
    assert largest_component(bow_tie, []).size == 0


def test_subset_helper_reindexes_and_drops_unreferenced_vertices():
    mesh = two_plates(big=(4, 1.0, 0.0), small=(2, 0.1, 1.0))
    keep_vertices = mesh.verts[:, 0] >= 0  # right half of each plate
    partial, vertex_map, face_map = largest_component_submesh(mesh, keep_vertices=keep_vertices, name="half")
    assert partial.name == "half" and partial.n_components() == 1
    assert np.all(keep_vertices[vertex_map]) and np.all(np.diff(vertex_map) > 0)
    assert np.array_equal(vertex_map[partial.faces], mesh.faces[face_map])
    assert np.all(mesh.verts[vertex_map, 2] == 0.0)  # the big plate's half wins
    keep_faces = np.zeros(len(mesh.faces), dtype=bool)
    keep_faces[[0, 5]] = True
    _, _, only = largest_component_submesh(mesh, keep_faces=keep_faces, keep_vertices=np.ones(mesh.n_vertices, bool))
    assert only.size == 1
    with pytest.raises(MeshError, match="no faces"):
        submesh(mesh, [])
    with pytest.raises(MeshError, match="boolean mask"):
        largest_component_submesh(mesh, keep_vertices=np.ones(3, bool))


def test_helpers_sort_and_deduplicate_face_ids():
    mesh = two_plates(big=(4, 1.0, 0.0), small=(2, 0.1, 1.0))
    ids = np.array([9, 3, 3, 0, 39, 9, 1, 2])
    expected_mesh, expected_map = submesh(mesh, np.unique(ids))
    shuffled_mesh, shuffled_map = submesh(mesh, ids)
    assert np.array_equal(shuffled_map, expected_map) and np.array_equal(shuffled_map, np.unique(mesh.faces[np.unique(ids)]))
    assert np.array_equal(shuffled_mesh.faces, expected_mesh.faces) and np.array_equal(shuffled_mesh.verts, expected_mesh.verts)
    assert np.array_equal(expected_map[expected_mesh.faces], mesh.faces[np.unique(ids)])
    assert np.array_equal(largest_component(mesh, ids), largest_component(mesh, np.unique(ids)))


def test_cuts_of_one_mesh_object_equal_cuts_of_a_fresh_copy():
    """The full shape's centroid and face areas are computed once per Mesh (cut for many pairs); same cuts."""
    mesh = sphere(3)
    first = cut_partial(mesh, 5)
    again = cut_partial(mesh, 5)  # the mesh's kept centroid and areas
    fresh = cut_partial(sphere(3), 5)  # another Mesh object: computed anew
    for other in (again, fresh):
        np.testing.assert_array_equal(other.face_map, first.face_map)
        np.testing.assert_array_equal(other.info["plane_point"], first.info["plane_point"])


# --- failures ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind, keep_range", [("cuts", (0.999, 1.0)), ("holes", (0.999, 1.0)), ("ray", (0.9, 1.0))])
def test_impossible_keep_range_raises_after_all_tries(kind, keep_range, faust_shapes):
    with pytest.raises(MeshError, match=rf"'{kind}' partial shape of 'tr_reg_000'.*all 3 random draws.*keep_range"):
        make_partial(faust_shapes[0], kind, 0, keep_range=keep_range, max_tries=3)


def test_bad_arguments_get_clear_errors(faust_shapes):
    source = faust_shapes[0]
    with pytest.raises(MeshError, match="unknown partial-shape kind"):
        make_partial(source, "slices", 0)
    with pytest.raises(MeshError, match=r"unknown option\(s\) \['radius_range'\] for partial kind 'cuts'"):
        make_partial(source, "cuts", 0, radius_range=(0.1, 0.2))
    with pytest.raises(MeshError, match="keep_range"):
        cut_partial(source, 0, keep_range=(0.9, 0.1))
    with pytest.raises(MeshError, match="max_tries"):
        ray_partial(source, 0, max_tries=0)
    with pytest.raises(MeshError, match="n_holes"):
        holes_partial(source, 0, n_holes=(0, 3))
    with pytest.raises(MeshError, match="radius_range"):
        holes_partial(source, 0, radius_range=(-0.1, 0.1))
    with pytest.raises(MeshError, match="point cloud"):
        make_partial(Mesh(source.verts), "cuts", 0)
    with pytest.raises(MeshError, match="unknown centre"):
        cut_partial(source, 0, center="middle")
