import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import bumpy, sphere

import geofeat
from geofeat import Mesh
from geofeat.errors import DescriptorError


@pytest.fixture(scope="module")
def pyfm_meshes(faust_dir):
    """Three FAUST_r shapes processed by pyFM (cotan Laplacian, 100 eigenpairs)."""
    from pyFM.mesh import TriMesh

    out = []
    for i in (0, 31, 97):
        mesh = geofeat.load_mesh(faust_dir / "off" / f"tr_reg_{i:03d}.off")
        out.append((mesh, TriMesh(mesh.verts, mesh.faces).process(k=100)))
    return out


def test_wks_matches_pyfm_on_faust(pyfm_meshes):
    from pyFM.signatures import mesh_WKS

    for mesh, tm in pyfm_meshes:
        ours = geofeat.compute(mesh, "wks", cache=False, n_eig=100, n_descr=64, laplacian="cotan", normalize=False)
        theirs = mesh_WKS(tm, 64)
        np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=1e-6 * np.abs(theirs).max())


def test_hks_matches_pyfm_on_faust(pyfm_meshes):
    from pyFM.signatures import mesh_HKS

    for mesh, tm in pyfm_meshes:
        ours = geofeat.compute(mesh, "hks", cache=False, n_eig=100, n_descr=16, laplacian="cotan", normalize=False)
        theirs = mesh_HKS(tm, 16)
        np.testing.assert_allclose(ours, theirs, rtol=2e-4, atol=1e-6 * np.abs(theirs).max())


def test_wks_matches_ulrssm_style_normalisation(faust_mesh):
    """normalize=True: every channel has unit mass-weighted L2 norm (ULRSSM's compute_wks_autoscale)."""
    from geofeat.geometry import spectral_basis

    feats = geofeat.compute(faust_mesh, "wks", cache=False).astype(np.float64)
    mass = spectral_basis(faust_mesh, 128).mass
    norms = np.sqrt((mass[:, None] * feats**2).sum(axis=0))
    np.testing.assert_allclose(norms, 1.0, rtol=1e-5)
    assert feats.shape == (4999, 128)


@pytest.mark.parametrize("name", ["hks", "wks"])
def test_invariant_to_rigid_motion_and_vertex_order(name):
    mesh = bumpy(0, 3)
    rotation = Rotation.random(random_state=1).as_matrix()
    perm = np.random.default_rng(0).permutation(mesh.n_vertices)
    moved = Mesh(mesh.verts[perm] @ rotation.T + 1.0, np.argsort(perm)[mesh.faces])
    a = geofeat.compute(mesh, name, cache=False)
    b = geofeat.compute(moved, name, cache=False)
    np.testing.assert_allclose(b, a[perm], rtol=1e-3, atol=1e-4 * np.abs(a).max())
    # Mass-normalised channels have unit L2 norm on the surface: values scale as 1 / length.
    scaled = geofeat.compute(Mesh(3.0 * mesh.verts, mesh.faces), name, cache=False)
    np.testing.assert_allclose(3.0 * scaled, a, rtol=1e-3, atol=1e-4 * np.abs(a).max())


@pytest.mark.parametrize("name", ["hks", "wks"])
def test_descriptors_discriminate_points(name, faust_mesh):
    """Features vary across a shape (HKS channels at the largest times tend to a constant, so: most channels)."""
    feats = geofeat.compute(faust_mesh, name, cache=False)
    varying = feats.std(axis=0) > 1e-2 * np.abs(feats).mean(axis=0)
    assert varying.mean() > 0.5


def test_several_components_give_finite_wks():
    a = sphere(2)
    two = Mesh(np.vstack([a.verts, a.verts * 0.5 + 3]), np.vstack([a.faces, a.faces + a.n_vertices]))
    feats = geofeat.compute(two, "wks", cache=False, n_eig=40, n_descr=16)
    assert np.isfinite(feats).all()


@pytest.mark.parametrize(
    "params,match",
    [
        ({"n_eig": 0}, "n_eig must be an integer >= 1"),
        ({"n_eig": 2}, "at least 3"),
        ({"n_descr": 2.5}, "n_descr must be an integer >= 1"),
        ({"laplacian": "fem"}, "laplacian must be one of"),
    ],
)
def test_bad_parameter_values(params, match):
    with pytest.raises(DescriptorError, match=match):
        geofeat.compute(sphere(1), "wks", **params)
