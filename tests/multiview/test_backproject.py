import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.errors import RenderError
from geofeat.multiview.backproject import VertexFeatureAccumulator


def fake_view(mesh, face_ids, bary):
    """One 'view' of shape (1, 1, M) whose pixels hit the given faces at the given barycentrics."""
    pix_to_face = torch.as_tensor(face_ids, dtype=torch.int64)[None, None]
    bary = torch.as_tensor(bary, dtype=torch.float32)[None, None]
    points = np.einsum("mk,mkd->md", bary[0, 0].double().numpy(), mesh.verts[mesh.faces[face_ids]])
    return pix_to_face, bary, torch.as_tensor(points, dtype=torch.float32)[None, None]


def test_face_mode_is_the_barycentric_weighted_mean():
    mesh = bumpy(0, 2)
    rng = np.random.default_rng(0)
    face_ids = np.array([0, 0, 5, -1])
    bary = rng.dirichlet(np.ones(3), size=4)
    pix_to_face, bary_t, _ = fake_view(mesh, np.maximum(face_ids, 0), bary)
    pix_to_face[0, 0, 3] = -1  # background pixel: ignored
    features = torch.as_tensor(rng.normal(size=(1, 1, 4, 2)), dtype=torch.float32)
    acc = VertexFeatureAccumulator(mesh.verts, mesh.faces, 2, mode="face")
    acc.add(features, pix_to_face, bary_t)
    result, seen = acc.result(fill="zero")
    sums = np.zeros((mesh.n_vertices, 2))
    weights = np.zeros(mesh.n_vertices)
    for p in range(3):
        for corner in range(3):
            v = mesh.faces[face_ids[p], corner]
            sums[v] += bary[p, corner] * features[0, 0, p].numpy()
            weights[v] += bary[p, corner]
    np.testing.assert_array_equal(seen, weights > 0)
    np.testing.assert_allclose(result[seen], sums[seen] / weights[seen, None], rtol=1e-5)
    assert np.all(result[~seen] == 0)


def test_ball_mode_with_positions_as_features_recovers_vertex_positions():
    """Identity 'backbone': each pixel's feature is its 3D point; every vertex sees pixels within the ball."""
    mesh = bumpy(1, 3)
    rng = np.random.default_rng(1)
    face_ids = rng.integers(0, len(mesh.faces), size=60000)
    bary = rng.dirichlet(np.ones(3), size=60000)
    pix_to_face, bary_t, points = fake_view(mesh, face_ids, bary)
    radius = 0.02
    acc = VertexFeatureAccumulator(mesh.verts, mesh.faces, 3, mode="ball", radius=radius)
    acc.add(points, pix_to_face, bary_t)
    result, seen = acc.result(fill="nearest")
    assert seen.mean() > 0.9
    error = np.linalg.norm(result[seen] - mesh.verts[seen], axis=1)
    assert error.max() < radius  # a mean of points inside the ball stays inside it
    assert error.mean() < 0.5 * radius
    # unseen vertices copy their nearest seen neighbour
    if (~seen).any():
        assert np.isfinite(result[~seen]).all()


def test_batches_accumulate_like_one_pass():
    mesh = bumpy(2, 2)
    rng = np.random.default_rng(2)
    face_ids = rng.integers(0, len(mesh.faces), size=600)
    bary = rng.dirichlet(np.ones(3), size=600)
    pix_to_face, bary_t, points = fake_view(mesh, face_ids, bary)
    one = VertexFeatureAccumulator(mesh.verts, mesh.faces, 3, mode="ball")
    one.add(points, pix_to_face, bary_t)
    two = VertexFeatureAccumulator(mesh.verts, mesh.faces, 3, mode="ball")
    two.add(points[:, :, :300], pix_to_face[:, :, :300], bary_t[:, :, :300])
    two.add(points[:, :, 300:], pix_to_face[:, :, 300:], bary_t[:, :, 300:])
    np.testing.assert_allclose(one.result()[0], two.result()[0], rtol=1e-5, atol=1e-6)


def test_bad_mode_and_shapes():
    mesh = bumpy(0, 1)
    with pytest.raises(RenderError, match="mode"):
        VertexFeatureAccumulator(mesh.verts, mesh.faces, 3, mode="splat")
    acc = VertexFeatureAccumulator(mesh.verts, mesh.faces, 3)
    with pytest.raises(RenderError, match="do not match"):
        acc.add(torch.zeros(1, 2, 2, 4), torch.zeros(1, 2, 2, dtype=torch.int64), torch.zeros(1, 2, 2, 3))
    with pytest.raises(RenderError, match="fill"):
        acc.result(fill="mean")


# ----------------------------------------------------------------------------- the neighbour search on the device


def _kdtree_pairs(verts: np.ndarray, points: np.ndarray, radius: float) -> set[tuple[int, int]]:
    """Every (vertex, point) pair within ``radius``, from a KD-tree over the points (the search as it was)."""
    from scipy.spatial import cKDTree

    found = cKDTree(points).query_ball_point(verts, radius)
    return {(v, p) for v, near in enumerate(found) for p in near}


def _faust_view_batches(faust_mesh, n_views=9, size=128, batch=3):
    from geofeat.multiview.backproject import foreground_pixels
    from geofeat.render import make_cameras, render_phong

    cameras = make_cameras(faust_mesh, n_views, layout="official", image_size=size, device="cpu")
    batches = []
    rng = np.random.default_rng(0)
    for start in range(0, n_views, batch):
        fragments = render_phong(faust_mesh, None, cameras[start : start + batch]).fragments
        n = foreground_pixels(fragments.pix_to_face).shape[0]
        batches.append((torch.as_tensor(rng.normal(size=(n, 6)), dtype=torch.float32), fragments))
    return batches


@pytest.mark.parametrize("mode", ["ball", "ball_last"])
def test_a_plan_lists_the_pixels_within_the_radius_of_a_vertex_and_reads_no_other(faust_mesh, mode):
    """Only the pixels a KD-tree finds within the radius of some vertex are planned; the others' features are never read."""
    from geofeat.multiview.backproject import Backprojector

    for features, fragments in _faust_view_batches(faust_mesh)[:2]:
        backprojector = Backprojector(faust_mesh.verts, faust_mesh.faces, mode, max_neighbours=100)
        plan = backprojector.plan(fragments.pix_to_face, fragments.bary)
        foreground = (fragments.pix_to_face >= 0).reshape(-1).numpy()
        face_ids = fragments.pix_to_face.reshape(-1).numpy()[foreground]
        bary = fragments.bary.reshape(-1, 3).numpy()[foreground].astype(np.float64)
        points = np.einsum("mk,mkd->md", bary, faust_mesh.verts[faust_mesh.faces[face_ids]])
        reaching = sorted({pixel for _, pixel in _kdtree_pairs(faust_mesh.verts, points, backprojector.radius)})
        assert plan.pixels.tolist() == reaching
        assert 0 < len(reaching) < len(points)  # some pixels reach no vertex at this radius
        poisoned = features.clone()
        unused = torch.ones(len(points), dtype=torch.bool)
        unused[plan.pixels] = False
        poisoned[unused] = float("nan")
        clean = VertexFeatureAccumulator(faust_mesh.verts, faust_mesh.faces, 6, mode=mode, max_neighbours=100)
        clean.add_foreground(features, fragments.pix_to_face, fragments.bary)
        dirty = VertexFeatureAccumulator(faust_mesh.verts, faust_mesh.faces, 6, mode=mode, max_neighbours=100)
        dirty.add_foreground(poisoned, fragments.pix_to_face, fragments.bary)
        assert torch.equal(clean.sums, dirty.sums) and torch.equal(clean.weights, dirty.weights)


def test_ball_on_a_real_render_equals_the_kdtree_search_to_1e_6(faust_mesh):
    """A FAUST shape from 9 views: the face-candidate search gives each vertex the mean of exactly the pixels
    a KD-tree finds within the radius (float64 points, as the rasterizer's barycentrics give them)."""
    batches = _faust_view_batches(faust_mesh)
    acc = VertexFeatureAccumulator(faust_mesh.verts, faust_mesh.faces, 6, mode="ball")
    sums = np.zeros((faust_mesh.n_vertices, 6))
    counts = np.zeros(faust_mesh.n_vertices)
    for features, fragments in batches:
        acc.add_foreground(features, fragments.pix_to_face, fragments.bary)
        foreground = (fragments.pix_to_face >= 0).reshape(-1).numpy()
        face_ids = fragments.pix_to_face.reshape(-1).numpy()[foreground]
        bary = fragments.bary.reshape(-1, 3).numpy()[foreground].astype(np.float64)
        points = np.einsum("mk,mkd->md", bary, faust_mesh.verts[faust_mesh.faces[face_ids]])
        pairs = np.array(sorted(_kdtree_pairs(faust_mesh.verts, points, acc.radius)))
        np.add.at(sums, pairs[:, 0], features.numpy().astype(np.float64)[pairs[:, 1]])
        np.add.at(counts, pairs[:, 0], 1.0)
    result, seen = acc.result(fill="zero")
    np.testing.assert_array_equal(seen, counts > 0)
    assert seen.mean() > 0.6
    np.testing.assert_allclose(result[seen], sums[seen] / counts[seen, None], rtol=0, atol=1e-6)
    assert np.all(result[~seen] == 0)


@pytest.mark.parametrize("off_face", [0.0, 0.3])
def test_pairs_within_equal_the_kdtree_pairs_on_and_off_the_faces(off_face):
    """Points on their faces, and points pushed off them (as depth-lifted points are): the same pairs as a KD-tree.

    The brute-force listing (the GPU's) and the KD-tree listing (the CPU's) give the same pairs.
    """
    from geofeat.multiview.backproject import FaceCandidates

    mesh = bumpy(3, 3)
    rng = np.random.default_rng(3)
    face_ids = rng.integers(0, len(mesh.faces), size=3000)
    bary = rng.dirichlet(np.ones(3), size=3000)
    points = np.einsum("mk,mkd->md", bary, mesh.verts[mesh.faces[face_ids]])
    edge = np.linalg.norm(mesh.verts[mesh.faces[:, 0]] - mesh.verts[mesh.faces[:, 1]], axis=1).mean()
    points += off_face * edge * rng.normal(size=points.shape)
    radius = 0.6 * edge
    expected = _kdtree_pairs(mesh.verts, points, radius)
    assert len(expected) > 1000
    for listing in ("kdtree", "brute_force"):
        candidates = FaceCandidates(mesh.verts, mesh.faces, radius, "cpu")
        if listing == "brute_force":
            count, vertices = candidates._list_by_brute_force(
                torch.as_tensor(radius + candidates._reach_np + candidates.slack, dtype=torch.float64)
            )
            assert torch.equal(count, candidates.count)
            candidates.vertices = vertices
        rows, cols = candidates.pairs_within(torch.as_tensor(face_ids), torch.as_tensor(points), radius, on_faces=off_face == 0.0)
        assert set(zip(rows.tolist(), cols.tolist(), strict=True)) == expected, listing
        assert rows.numel() == len(expected)  # no pair twice


def test_pairs_within_refuse_a_larger_radius():
    from geofeat.multiview.backproject import FaceCandidates

    mesh = bumpy(0, 1)
    candidates = FaceCandidates(mesh.verts, mesh.faces, 0.1, "cpu")
    with pytest.raises(RenderError, match="larger"):
        candidates.pairs_within(torch.zeros(1, dtype=torch.int64), torch.zeros(1, 3, dtype=torch.float64), 0.2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("mode", ["ball", "face", "ball_last"])
def test_cuda_backprojection_equals_the_cpu(faust_mesh, mode):
    batches = _faust_view_batches(faust_mesh)
    results = []
    for device in ("cpu", "cuda"):
        acc = VertexFeatureAccumulator(faust_mesh.verts, faust_mesh.faces, 6, mode=mode, device=device, max_neighbours=100)
        for features, fragments in batches:
            acc.add_foreground(features.to(device), fragments.pix_to_face.to(device), fragments.bary.to(device))
        results.append([t.cpu() for t in acc.result_tensor(fill="nearest")])
    assert torch.equal(results[0][1], results[1][1])
    torch.testing.assert_close(results[0][0], results[1][0], rtol=0, atol=1e-6)
