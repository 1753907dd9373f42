"""Sampling patch features at foreground pixels equals upsampling whole images, and back-projects the same."""

import numpy as np
import pytest
import torch
from shapes import bumpy

from geofeat.backbones import sample_patch_features, upsample_patch_features
from geofeat.errors import RenderError
from geofeat.multiview.backproject import VertexFeatureAccumulator, foreground_pixels
from geofeat.render import make_cameras, render_phong


@pytest.mark.parametrize("grid_hw, out_hw", [((4, 4), (64, 64)), ((5, 3), (37, 50)), ((8, 8), (8, 8))])
def test_sampling_equals_upsampling(grid_hw, out_hw):
    torch.manual_seed(0)
    grid = torch.randn(3, *grid_hw, 6, requires_grad=True)
    pixels = torch.stack(
        [torch.randint(0, n, (500,)) for n in (3, *out_hw)], dim=1
    )  # random (view, row, column), edges included by chance
    pixels = torch.cat([pixels, torch.tensor([[0, 0, 0], [2, out_hw[0] - 1, out_hw[1] - 1]])])
    full = upsample_patch_features(grid, out_hw)[pixels[:, 0], pixels[:, 1], pixels[:, 2]]
    sampled = sample_patch_features(grid, pixels, out_hw)
    torch.testing.assert_close(sampled, full, rtol=0, atol=1e-5)
    (g_full,) = torch.autograd.grad(full.sum(), grid)
    (g_sampled,) = torch.autograd.grad(sampled.sum(), grid)
    torch.testing.assert_close(g_sampled, g_full, rtol=0, atol=1e-5)


def test_sampling_gradient_is_the_same_on_every_run_with_two_threads():
    """Many pixels read the same patch: their gradients must add up in a fixed order."""
    gen = torch.Generator().manual_seed(0)
    grid = torch.randn(4, 8, 8, 64, generator=gen, requires_grad=True)
    pixels = torch.stack([torch.randint(0, n, (60_000,), generator=gen) for n in (4, 128, 128)], dim=1)
    upstream = torch.randn(60_000, 64, generator=gen)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        grads = [
            torch.autograd.grad((sample_patch_features(grid, pixels, (128, 128)) * upstream).sum(), grid)[0] for _ in range(4)
        ]
    finally:
        torch.set_num_threads(threads)
    for g in grads[1:]:
        assert torch.equal(g, grads[0])


@pytest.mark.parametrize("mode", ["ball", "face"])
def test_foreground_back_projection_equals_the_full_one(mode):
    mesh = bumpy(0, 3)
    cameras = make_cameras(mesh, 4, layout="uniform", image_size=64, device="cpu")
    fragments = render_phong(mesh, None, cameras).fragments
    torch.manual_seed(1)
    pixel_features = torch.randn(4, 64, 64, 5)
    full = VertexFeatureAccumulator(mesh.verts, mesh.faces, 5, mode=mode)
    full.add(pixel_features, fragments.pix_to_face, fragments.bary)
    pixels = foreground_pixels(fragments.pix_to_face)
    foreground = VertexFeatureAccumulator(mesh.verts, mesh.faces, 5, mode=mode)
    foreground.add_foreground(pixel_features[pixels[:, 0], pixels[:, 1], pixels[:, 2]], fragments.pix_to_face, fragments.bary)
    (a, seen_a), (b, seen_b) = full.result("zero"), foreground.result("zero")
    np.testing.assert_allclose(a, b, atol=1e-5)
    np.testing.assert_array_equal(seen_a, seen_b)
    with pytest.raises(RenderError, match="one row per foreground pixel"):
        foreground.add_foreground(torch.zeros(3, 5), fragments.pix_to_face, fragments.bary)


def test_result_tensor_is_differentiable_and_fills():
    mesh = bumpy(1, 3)
    cameras = make_cameras(mesh, 2, layout="uniform", image_size=48, device="cpu")
    fragments = render_phong(mesh, None, cameras).fragments
    pixels = foreground_pixels(fragments.pix_to_face)
    features = torch.randn(pixels.shape[0], 3, requires_grad=True)
    accumulator = VertexFeatureAccumulator(mesh.verts, mesh.faces, 3, mode="face")
    accumulator.add_foreground(features, fragments.pix_to_face, fragments.bary)
    values, seen = accumulator.result_tensor("zero")
    assert 0 < int(seen.sum()) < mesh.n_vertices  # two views leave some vertices unseen
    assert bool((values[~seen] == 0).all())
    (grad,) = torch.autograd.grad(values.sum(), features)
    assert bool((grad != 0).any())
    filled, _ = accumulator.result_tensor("nearest")
    assert bool((filled.abs().sum(dim=1) > 0).all())
    torch.testing.assert_close(filled[seen], values[seen])
