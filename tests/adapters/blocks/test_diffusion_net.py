"""DiffusionNet: tangent gradient operators, learned diffusion, the network and its input checks."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from shapes import bumpy, sphere

import geofeat
from geofeat.adapters.blocks import operators as ops_module
from geofeat.adapters.blocks.diffusion_net import (
    DiffusionNet,
    LearnedDiffusion,
    SurfaceOperators,
    clear_operator_cache,
    gradient_matrices,
    spectral_diffusion,
    surface_operators,
    tangent_frames,
    tangent_gradients,
)
from geofeat.descriptors.spectral import heat_kernel_signature, wave_kernel_signature
from geofeat.errors import DiffusionNetError, GeofeatError
from geofeat.geometry.normals import vertex_normals
from geofeat.geometry.spectral import spectral_basis

K = 48


@pytest.fixture(scope="module")
def blob() -> geofeat.Mesh:
    return bumpy(0, subdivisions=3)  # 642 vertices


@pytest.fixture(scope="module")
def blob_ops(blob) -> SurfaceOperators:
    return surface_operators(blob, K)


def flat_grid(nx: int = 9, ny: int = 7, seed: int = 0) -> geofeat.Mesh:
    """A jittered planar grid in z = 0.3 with counter-clockwise (normal +z) triangles."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    verts = np.stack((xs.ravel(), ys.ravel(), np.full(xs.size, 0.3)), axis=1)
    verts[:, :2] += rng.uniform(-0.25, 0.25, size=(len(verts), 2))
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate((np.stack((a, b, c), 1), np.stack((a, c, d), 1)))
    return geofeat.Mesh(verts, faces, name="grid")


def linear_gradient_error(mesh: geofeat.Mesh, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Computed and closed-form (V, 2) tangent gradients of ``f(p) = direction . p``."""
    frames = tangent_frames(vertex_normals(mesh))
    grad_x, grad_y = gradient_matrices(mesh, frames)
    values = mesh.verts @ direction + 1.7
    computed = np.stack((grad_x @ values, grad_y @ values), axis=1)
    # the tangent gradient of a linear function is its direction projected on the tangent plane;
    # its components in the frame are the dot products with the X and Y axes
    expected = frames[:, :2] @ direction
    return computed, expected


# ----------------------------------------------------------------------------- operators


def test_gradient_is_exact_for_linear_functions_on_a_flat_grid():
    mesh = flat_grid()
    direction = np.array([0.8, -1.3, 2.0])  # the z part is normal to the plane: no tangent gradient
    frames = tangent_frames(vertex_normals(mesh))
    np.testing.assert_allclose(frames[:, 2], np.tile([0.0, 0.0, 1.0], (mesh.n_vertices, 1)), atol=1e-12)
    computed, expected = linear_gradient_error(mesh, direction)
    np.testing.assert_allclose(expected, np.tile([0.8, -1.3], (mesh.n_vertices, 1)), atol=1e-12)  # X = x, Y = y
    np.testing.assert_allclose(computed, expected, rtol=0, atol=1e-4)  # only the 1e-5 regularisation
    ops = surface_operators(mesh, 8)  # the float32 torch copies give the same
    values = torch.from_numpy(mesh.verts @ direction + 1.7).float()[:, None]
    gx, gy = tangent_gradients(values, ops)
    np.testing.assert_allclose(torch.cat((gx, gy), dim=1).numpy(), expected, atol=1e-3)


def test_gradient_matches_the_tangent_projection_on_spheres():
    direction = np.array([0.3, -1.2, 0.7])
    errors = []
    for subdivisions in (3, 4):
        mesh = sphere(subdivisions, radius=2.0)
        radial = mesh.verts / np.linalg.norm(mesh.verts, axis=1, keepdims=True)
        frames = tangent_frames(vertex_normals(mesh))
        assert np.abs(frames[:, 2] - radial).max() < 0.02  # outward unit normals, close to radial
        grad_x, grad_y = gradient_matrices(mesh, frames)
        values = mesh.verts @ direction + 1.7
        computed = (grad_x @ values)[:, None] * frames[:, 0] + (grad_y @ values)[:, None] * frames[:, 1]  # (V, 3)
        # closed form: the direction projected on the sphere's exact tangent plane at p
        exact = direction - (radial @ direction)[:, None] * radial
        errors.append(np.linalg.norm(computed - exact, axis=1).max() / np.linalg.norm(direction))
    assert errors[0] < 0.03
    assert errors[1] < 0.6 * errors[0]  # first-order convergence under refinement


def test_frames_are_orthonormal_and_right_handed(blob, blob_ops):
    frames = blob_ops.frames.double().numpy()
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3), frames.shape), atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(frames), 1.0, atol=1e-6)
    assert (np.einsum("vd,vd->v", frames[:, 2], blob.verts) > 0).all()  # outward on a star-shaped blob


def test_operators_dtypes_shapes_and_reused_basis(blob, blob_ops, monkeypatch):
    v = blob.n_vertices
    assert blob_ops.n_vertices == v and blob_ops.k == K
    assert blob_ops.mass.shape == (v,) and blob_ops.evals.shape == (K,) and blob_ops.evecs.shape == (v, K)
    assert blob_ops.grad_x.shape == (v, v) and blob_ops.grad_x.is_sparse and blob_ops.grad_y.is_sparse
    assert blob_ops.faces.shape == blob.faces.shape and blob_ops.edges.shape == (3 * v - 6, 2)  # closed genus 0
    for tensor in (blob_ops.mass, blob_ops.evals, blob_ops.evecs, blob_ops.grad_x, blob_ops.frames):
        assert tensor.dtype == torch.float32
    basis = spectral_basis(blob, K)
    np.testing.assert_array_equal(blob_ops.evecs.numpy(), basis.evecs.astype(np.float32))
    assert (blob_ops.evals >= 0).all()
    # cached by content: the same record for the same mesh under another name
    assert surface_operators(blob.renamed("other"), K) is blob_ops
    # rebuilding reuses the cached eigenpairs instead of solving again
    clear_operator_cache()

    def no_solve(*args, **kwargs):
        raise AssertionError("eigenpairs were recomputed")

    monkeypatch.setattr("geofeat.geometry.spectral.solve_eigenpairs", no_solve)
    rebuilt = surface_operators(blob, K)
    assert rebuilt is not blob_ops
    torch.testing.assert_close(rebuilt.evecs, blob_ops.evecs)


def test_tangent_gradients_backward_equals_torch_sparse_mm(blob_ops):
    """The backward through the kept coalesced transposes gives torch's own gradient, bit for bit."""
    x = torch.randn(blob_ops.n_vertices, 4, generator=torch.Generator().manual_seed(0))
    grads = []
    for ours in (True, False):
        leaf = x.clone().requires_grad_()
        if ours:
            gx, gy = tangent_gradients(leaf, blob_ops)
        else:
            gx, gy = torch.sparse.mm(blob_ops.grad_x, leaf), torch.sparse.mm(blob_ops.grad_y, leaf)
        (gx.square().sum() + (gy * x).sum()).backward()
        grads.append((gx.detach(), gy.detach(), leaf.grad))
    for new, old in zip(*grads, strict=True):
        assert torch.equal(new, old)
    transposed_x, transposed_y = blob_ops.gradient_transposes
    assert transposed_x.is_coalesced() and torch.equal(transposed_x.to_dense(), blob_ops.grad_x.to_dense().T)
    assert blob_ops.gradient_transposes[1] is transposed_y  # made once per record


def test_operators_move_between_devices(blob_ops):
    assert blob_ops.to("cpu") is blob_ops
    with pytest.raises(GeofeatError):
        blob_ops.to("no-such-device")
    if torch.cuda.is_available():
        moved = blob_ops.to("cuda")
        assert moved.grad_x.is_cuda and moved.evecs.is_cuda and moved.edges.is_cuda
        assert moved.to("cpu").mass.device.type == "cpu"


def test_point_cloud_operators():
    mesh = sphere(3)
    cloud = geofeat.Mesh(mesh.verts, None, name="cloud")
    ops = surface_operators(cloud, 16)
    assert ops.faces is None and ops.edges is None
    frames = ops.frames.double().numpy()
    assert (np.einsum("vd,vd->v", frames[:, 2], cloud.verts) > 0.99).all()  # normals oriented outward
    direction = np.array([1.0, 0.5, -0.5])
    computed, expected = linear_gradient_error(cloud, direction)
    assert np.linalg.norm(computed - expected, axis=1).max() < 0.1 * np.linalg.norm(direction)
    out = DiffusionNet(3, 2, width=8, n_blocks=1)(torch.randn(cloud.n_vertices, 3), ops)
    assert out.shape == (cloud.n_vertices, 2)
    with pytest.raises(DiffusionNetError, match="point cloud"):
        DiffusionNet(3, 2, width=8, n_blocks=1, outputs_at="faces")(torch.randn(cloud.n_vertices, 3), ops)


def test_operators_on_faust(faust_mesh):
    ops = surface_operators(faust_mesh, 32)
    assert ops.n_vertices == faust_mesh.n_vertices
    # the gradient of a coordinate function is its axis projected on the tangent plane
    gx, gy = tangent_gradients(torch.tensor(faust_mesh.verts, dtype=torch.float32), ops)  # (V, 3) each
    frames = ops.frames.double().numpy()
    computed = np.stack((gx.double().numpy(), gy.double().numpy()), axis=1)  # (V, 2, 3)
    expected = frames[:, :2, :]  # d(p . e_c) along X is X_c
    error = np.linalg.norm(computed - expected, axis=(1, 2)) / np.sqrt(2)
    assert np.median(error) < 0.05
    net = DiffusionNet(3, 4, width=16, n_blocks=1)
    out = net(torch.tensor(faust_mesh.verts, dtype=torch.float32), ops)
    assert out.shape == (faust_mesh.n_vertices, 4) and torch.isfinite(out).all()


# ----------------------------------------------------------------------------- diffusion


def test_diffusion_for_time_zero_is_the_identity_on_the_basis(blob_ops):
    rng = np.random.default_rng(1)
    coefficients = torch.from_numpy(rng.normal(size=(K, 5))).float()
    values = blob_ops.evecs @ coefficients  # (V, 5) in the span of the basis
    out = spectral_diffusion(values, blob_ops, torch.zeros(5))
    torch.testing.assert_close(out, values, rtol=0, atol=1e-4 * values.abs().max().item())


def test_diffusion_for_large_time_is_the_mass_weighted_mean(blob_ops):
    values = torch.from_numpy(np.random.default_rng(2).normal(size=(blob_ops.n_vertices, 3))).float()
    out = spectral_diffusion(values[None].expand(2, -1, -1), blob_ops, torch.full((3,), 1e3))
    mean = (blob_ops.mass[:, None] * values).sum(0) / blob_ops.mass.sum()
    torch.testing.assert_close(out, mean.expand(2, blob_ops.n_vertices, 3), rtol=0, atol=1e-4)


def test_diffusion_time_stays_non_negative_and_keeps_its_gradient(blob_ops):
    layer = LearnedDiffusion(2)
    with torch.no_grad():
        layer.time.copy_(torch.tensor([-0.5, 0.01]))
    torch.testing.assert_close(layer.diffusion_time(), torch.tensor([0.0, 0.01]))
    values = blob_ops.evecs[:, 1:3] + 0.1
    layer(values, blob_ops).square().sum().backward()
    assert (layer.time.grad != 0).all()  # a time pushed below zero can come back


# ----------------------------------------------------------------------------- network


def test_output_shapes_and_batches(blob, blob_ops):
    torch.manual_seed(0)
    net = DiffusionNet(6, 5, width=16, n_blocks=2).eval()
    x = torch.randn(3, blob.n_vertices, 6)
    single = net(x[1], blob_ops)
    batched = net(x, blob_ops)
    assert single.shape == (blob.n_vertices, 5) and batched.shape == (3, blob.n_vertices, 5)
    torch.testing.assert_close(batched[1], single, rtol=1e-4, atol=1e-5)
    net.outputs_at = "faces"
    assert net(x[0], blob_ops).shape == (len(blob.faces), 5)
    net.outputs_at = "edges"
    assert net(x, blob_ops).shape == (3, blob_ops.edges.shape[0], 5)
    log_probs = DiffusionNet(6, 4, width=8, n_blocks=1, last_activation=lambda t: torch.log_softmax(t, dim=-1))(x[0], blob_ops)
    torch.testing.assert_close(log_probs.exp().sum(-1), torch.ones(blob.n_vertices))
    # float64 input is accepted (cast to the parameters' dtype)
    assert net(x.double(), blob_ops).dtype == torch.float32


def test_gradients_reach_every_parameter(blob, blob_ops):
    torch.manual_seed(0)
    net = DiffusionNet(4, 3, width=8, n_blocks=2, dropout=True)
    assert any(isinstance(m, torch.nn.Dropout) for m in net.modules())
    net(torch.randn(2, blob.n_vertices, 4), blob_ops).square().mean().backward()
    names = [name for name, _ in net.named_parameters()]
    assert any("time" in n for n in names) and any("a_im" in n for n in names)
    for name, parameter in net.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_invariant_to_rigid_motions(blob, blob_ops):
    rotation = Rotation.from_euler("xyz", [0.7, -1.1, 2.3]).as_matrix()
    moved = geofeat.Mesh(blob.verts @ rotation.T + np.array([0.5, -2.0, 1.0]), blob.faces, name="moved")
    moved_ops = surface_operators(moved, K)
    features = torch.from_numpy(heat_kernel_signature(spectral_basis(blob, K), 8)).float()  # intrinsic input
    torch.manual_seed(0)
    net = DiffusionNet(8, 6, width=16, n_blocks=2).eval()
    with torch.no_grad():
        for block in net.blocks:
            block.diffusion.time.uniform_(0.0, 0.05)  # make the diffusion and the gradients matter
        expected = net(features, blob_ops)
        out = net(features, moved_ops)
    scale = expected.abs().max().item()
    torch.testing.assert_close(out, expected, rtol=0, atol=2e-3 * scale)
    # the frames do differ by a rotation in the tangent plane: invariance is not trivial
    frames, moved_frames = blob_ops.frames.double().numpy(), moved_ops.frames.double().numpy()
    assert np.abs(moved_frames[:, 0] - frames[:, 0] @ rotation.T).max() > 0.5


def test_learns_a_smooth_function_from_wks(blob, blob_ops):
    basis = spectral_basis(blob, K)
    features = torch.from_numpy(wave_kernel_signature(basis, 16)).float()
    features = (features - features.mean(0)) / features.std(0)
    target = torch.from_numpy(blob.verts[:, 2] + 0.5 * blob.verts[:, 0] ** 2).float()[:, None]
    target = (target - target.mean()) / target.std()
    torch.manual_seed(0)
    net = DiffusionNet(16, 1, width=32, n_blocks=2)
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(200):
        optimizer.zero_grad()
        loss = torch.nn.functional.mse_loss(net(features, blob_ops), target)
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0] / 10, (losses[0], losses[-1])


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_clear_errors(blob, blob_ops):
    net = DiffusionNet(4, 2, width=8, n_blocks=1)
    v = blob.n_vertices
    cases = [
        (torch.randn(v, 5), blob_ops, "in_channels=4, but x has 5 channels"),
        (torch.randn(v - 1, 4), blob_ops, f"{v - 1} vertices .* {v} vertices"),
        (torch.randn(2, v + 3, 4), blob_ops, f"{v + 3} vertices"),
        (torch.randn(v), blob_ops, r"\(V, C_in\) or \(B, V, C_in\)"),
        (torch.randn(1, 2, v, 4), blob_ops, "4 dimensions"),
        (torch.ones(v, 4, dtype=torch.int64), blob_ops, "floating-point"),
        (np.zeros((v, 4), dtype=np.float32), blob_ops, "torch.Tensor"),
        (torch.randn(v, 4), blob, "SurfaceOperators"),
    ]
    for x, operators, message in cases:
        with pytest.raises(DiffusionNetError, match=message):
            net(x, operators)
    assert issubclass(DiffusionNetError, GeofeatError) and issubclass(DiffusionNetError, ValueError)
    with pytest.raises(GeofeatError, match="k must be"):
        surface_operators(blob, 0)
    for kwargs, message in [
        ({"in_channels": 0}, "in_channels must be a positive integer"),
        ({"width": 2.5}, "width must be a positive integer"),
        ({"n_blocks": -1}, "n_blocks"),
        ({"dropout": 1.5}, "dropout"),
        ({"outputs_at": "corners"}, "outputs_at"),
        ({"last_activation": "relu"}, "last_activation"),
        ({"mlp_hidden": [8, 0]}, "mlp_hidden"),
    ]:
        with pytest.raises(DiffusionNetError, match=message):
            DiffusionNet(**{"in_channels": 4, "out_channels": 2, **kwargs})


def test_the_operator_cache_is_bounded(monkeypatch):
    monkeypatch.setattr(ops_module, "_CACHE_SIZE", 2)
    clear_operator_cache()
    meshes = [flat_grid(seed=seed) for seed in range(3)]
    first = surface_operators(meshes[0], 4)
    for mesh in meshes[1:]:
        surface_operators(mesh, 4)
    assert surface_operators(meshes[0], 4) is not first  # evicted, rebuilt
    assert len(ops_module._operator_cache) == 2
