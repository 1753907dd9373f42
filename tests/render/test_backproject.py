import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.errors import RenderError
from geofeat.render.backproject import VertexFeatureAccumulator


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
