"""DiffusionNet's point-cloud operators against the reference code's, recorded in tests/data/diffusion_net_cloud_reference.npz.

The file (see tests/data/README.md) holds what nmwsharp/diffusion-net's ``compute_operators``
gives for a 200-point cloud; ``construction="diffusionnet"`` must give the same, with no
reference code installed. Normals are compared up to sign (the reference keeps its SVD's),
and so are the Y axes and the Y gradient rows, which follow the normal's sign.
"""

from pathlib import Path

import numpy as np
import pytest

import geofeat
from geofeat.adapters.blocks.operators import surface_operators
from geofeat.geometry.laplacian import laplacian

RECORDED = Path(__file__).resolve().parents[2] / "data" / "diffusion_net_cloud_reference.npz"


@pytest.fixture(scope="module")
def recorded() -> dict:
    with np.load(RECORDED) as data:
        return {key: data[key] for key in data.files}


@pytest.fixture(scope="module")
def ours(recorded):
    cloud = geofeat.Mesh(recorded["verts"], name="bumpy200")
    ops = surface_operators(cloud, int(recorded["k_eig"]), laplacian_kind="robust", construction="diffusionnet", cache=False)
    return cloud, ops


def _close(ours, theirs, rtol):
    """Equal up to ``rtol`` of the largest magnitude of the reference's values."""
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=rtol * np.abs(theirs).max())


def _normal_signs(ops, recorded) -> np.ndarray:
    return np.where(np.einsum("vd,vd->v", ops.frames[:, 2].double().numpy(), recorded["normals"]) < 0, -1.0, 1.0)


def test_mass_laplacian_and_eigenvalues(recorded, ours):
    cloud, ops = ours
    _close(ops.mass.numpy(), recorded["mass"], 1e-6)
    _close(laplacian(cloud).stiffness @ recorded["probes"], recorded["L_probes"], 1e-5)
    # the reference solves (L + 1e-8 I) phi = lambda M phi: its eigenvalues are higher by about 1e-8 |phi|^2
    shift = 1e-8 * np.square(recorded["evecs"].astype(np.float64)).sum(axis=0)
    np.testing.assert_allclose(ops.evals.numpy()[1:], (recorded["evals"] - shift)[1:], rtol=1e-5)


def test_eigenvectors_span_the_same_spaces(recorded, ours):
    _, ops = ours
    overlap = ops.evecs.double().numpy().T @ (recorded["mass"][:, None] * recorded["evecs"].astype(np.float64))
    # distinct eigenvalues here (the closest two 0.3% apart): the overlap is diagonal up to the signs
    np.testing.assert_allclose(np.abs(overlap), np.eye(overlap.shape[0]), atol=1e-4)


def test_normals_and_frames_up_to_the_normals_sign(recorded, ours):
    _, ops = ours
    sign = _normal_signs(ops, recorded)
    _close(ops.frames[:, 2].numpy(), sign[:, None] * recorded["normals"], 1e-6)
    _close(ops.frames[:, 0].numpy(), recorded["frames_x"], 1e-6)


def test_gradients(recorded, ours):
    _, ops = ours
    sign = _normal_signs(ops, recorded)
    rows, probes = recorded["rows"], recorded["probes"]
    for name, grad, row_sign in (("gradX", ops.grad_x, np.ones_like(sign)), ("gradY", ops.grad_y, sign)):
        dense = grad.to_dense().double().numpy()
        _close(dense[rows], row_sign[rows, None] * recorded[f"{name}_rows"], 1e-5)
        _close(dense @ probes, row_sign[:, None] * recorded[f"{name}_probes"], 1e-5)
