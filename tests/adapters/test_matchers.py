"""Training-free matchers: nearest neighbours, functional maps and ZoomOut, on FAUST_r and small examples."""

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

import geofeat
from geofeat.adapters.blocks import functional_maps as fm
from geofeat.adapters.matchers import fmap_match, nn_match
from geofeat.errors import FunctionalMapError
from geofeat.geometry.geodesic import distances_from
from geofeat.geometry.spectral import mass_normalize, spectral_basis

K = 30
K_END = 60


class Pair:
    """FAUST_r tr_reg_000 (target x) and tr_reg_001 (source y) with WKS, bases and ground truth."""

    def __init__(self, root, ix=0, iy=1, n_eval=300):
        self.x, vts_x = self._load(root, ix)
        self.y, vts_y = self._load(root, iy)
        self.gt = np.full(self.y.n_vertices, -1)
        self.gt[vts_y] = vts_x
        self.feat_x = geofeat.compute(self.x, "wks", cache=False)  # no cache: this fixture outlives the per-test cache dir
        self.feat_y = geofeat.compute(self.y, "wks", cache=False)
        self.basis_x = spectral_basis(self.x, 100)
        self.basis_y = spectral_basis(self.y, 100)
        rng = np.random.default_rng(0)
        self.sample = rng.choice(np.flatnonzero(self.gt >= 0), n_eval, replace=False)
        self.dist = distances_from(self.x, self.gt[self.sample]) / np.sqrt(self.x.area())

    @staticmethod
    def _load(root, index):
        mesh = geofeat.load_mesh(root / "off" / f"tr_reg_{index:03d}.off")
        vts = np.loadtxt(root / "corres" / f"tr_reg_{index:03d}.vts", dtype=np.int64) - 1
        return mesh, vts

    def error(self, map_yx):
        """Mean normalised geodesic error x100 on the sampled vertices of y."""
        return 100 * self.dist[np.arange(self.sample.size), map_yx[self.sample]].mean()


@pytest.fixture(scope="module")
def pair(faust_dir):
    return Pair(faust_dir)


@pytest.fixture(scope="module")
def maps(pair):
    """Point maps of the three matchers (computed once; ZoomOut in steps of 10 to stay fast)."""
    common = {"k": K, "k_final": 100, "zoomout_step": 10}
    return {
        "nn": nn_match(pair.feat_x, pair.feat_y),
        "fmap": fmap_match(pair.x, pair.y, pair.feat_x, pair.feat_y, zoomout=False, **common),
        "zoomout": fmap_match(pair.x, pair.y, pair.feat_x, pair.feat_y, zoomout=True, **common),
    }


# ----------------------------------------------------------------------------- nearest neighbours


@pytest.mark.parametrize("block_entries", [fm.NN_BLOCK_ENTRIES, 5000])
def test_nearest_neighbors_is_exact(block_entries, monkeypatch):
    monkeypatch.setattr(fm, "NN_BLOCK_ENTRIES", block_entries)  # small: many blocks in both passes
    rng = np.random.default_rng(0)
    reference, queries = rng.standard_normal((700, 16)), rng.standard_normal((500, 16))
    np.testing.assert_array_equal(fm.nearest_neighbors(reference, queries), cKDTree(reference).query(queries)[1])
    tiny = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0]])
    np.testing.assert_array_equal(fm.nearest_neighbors(tiny, np.array([[0.1, 0.0], [0.9, 0.0]])), [0, 1])  # tie -> smallest index


@pytest.mark.parametrize("block_entries", [fm.NN_BLOCK_ENTRIES, 5000])
def test_nearest_neighbors_is_exact_when_screening_on_few_axes(block_entries, monkeypatch):
    monkeypatch.setattr(fm, "NN_BLOCK_ENTRIES", block_entries)
    rng = np.random.default_rng(1)
    # variance in 6 of 64 axes (like spectral descriptors) plus a little everywhere: screening on about 6 axes
    spread = np.r_[np.full(6, 10.0), np.full(58, 1e-3)]
    basis = np.linalg.qr(rng.standard_normal((64, 64)))[0]
    reference = (rng.standard_normal((900, 64)) * spread) @ basis.T
    queries = (rng.standard_normal((400, 64)) * spread) @ basis.T
    axes, _ = fm._screening_axes(reference)
    assert axes.shape == (64, 6)  # the screening really uses few axes here
    expected = cKDTree(reference).query(queries)[1]
    np.testing.assert_array_equal(fm.nearest_neighbors(reference, queries), expected)
    # queries far off the screened axes: the distances are large next to their screened parts
    far = queries + 300.0 * basis[:, 40]
    np.testing.assert_array_equal(fm.nearest_neighbors(reference, far), cKDTree(reference).query(far)[1])
    # a duplicated reference point: the smallest index wins, whatever the screening rounding
    doubled = np.vstack([reference, reference[:50]])
    np.testing.assert_array_equal(fm.nearest_neighbors(doubled, reference[:50] + 1e-9), np.arange(50))


def _few_axes_points(seed, n_reference, n_queries):
    """Points with their variance in 6 of 64 axes, and far queries (off those axes)."""
    rng = np.random.default_rng(seed)
    spread = np.r_[np.full(6, 10.0), np.full(58, 1e-3)]
    basis = np.linalg.qr(rng.standard_normal((64, 64)))[0]
    reference = (rng.standard_normal((n_reference, 64)) * spread) @ basis.T
    queries = (rng.standard_normal((n_queries, 64)) * spread) @ basis.T
    return reference, queries, queries + 300.0 * basis[:, 40]


def test_nearest_neighbor_index_is_reusable_and_nn_match_takes_it():
    reference, queries, far = _few_axes_points(2, 800, 300)
    index = fm.NearestNeighborIndex(reference)
    assert (index.n_points, index.dim) == (800, 64)
    tree = cKDTree(reference)
    for q in (queries, far, reference[:40] + 1e-9, queries[:1]):
        expected = tree.query(q)[1]
        np.testing.assert_array_equal(index.query(q), expected)
        np.testing.assert_array_equal(nn_match(index, q), expected)
        np.testing.assert_array_equal(fm.nearest_neighbors(reference, q), expected)
    with pytest.raises(FunctionalMapError, match="same number of channels"):
        nn_match(index, queries[:, :10])
    with pytest.raises(FunctionalMapError, match="same dimension"):
        index.query(queries[:, :10])
    with pytest.raises(FunctionalMapError, match="no points"):
        fm.NearestNeighborIndex(np.zeros((0, 3)))


@pytest.mark.parametrize("residual", [0.9, 1e-9])
def test_nearest_neighbors_do_not_depend_on_the_number_of_screening_axes(residual, monkeypatch):
    reference, queries, far = _few_axes_points(3, 600, 300)
    doubled = np.vstack([reference, reference[:50]])  # exact ties: the smallest index wins
    expected = {name: fm.nearest_neighbors(doubled, q) for name, q in (("near", queries), ("far", far))}
    monkeypatch.setattr(fm, "NN_SCREEN_RESIDUAL", residual)  # 1 axis, or all 64 (the identity)
    assert fm._screening_axes(reference)[0].shape[1] == (1 if residual == 0.9 else 64)
    for name, q in (("near", queries), ("far", far)):
        np.testing.assert_array_equal(fm.nearest_neighbors(doubled, q), expected[name])
    np.testing.assert_array_equal(fm.nearest_neighbors(doubled, reference[:50] + 1e-9), np.arange(50))


def test_torch_screening_gives_the_numpy_result(monkeypatch):
    """The torch screening (used on CUDA) run on the CPU gives the maps of the numpy one."""
    reference, queries, far = _few_axes_points(4, 700, 300)
    doubled = np.vstack([reference, reference[:50]])
    sets = (queries, far, reference[:50] + 1e-9)
    expected = [fm.nearest_neighbors(doubled, q) for q in sets]
    torch_screen, screens = fm._TorchScreen, []

    def spy(*args):
        screens.append(torch_screen(*args))
        return screens[-1]

    monkeypatch.setattr(fm, "_is_cpu", lambda device: False)
    monkeypatch.setattr(fm, "_TorchScreen", spy)
    for q, want in zip(sets, expected, strict=True):
        np.testing.assert_array_equal(fm.nearest_neighbors(doubled, q, device="cpu"), want)
    assert len(screens) == len(sets)  # the torch screen really ran


@pytest.mark.parametrize("device", ["cpu", "auto"] + (["cuda"] if torch.cuda.is_available() else []))
def test_nn_match_hand_example_and_output_type(device):
    feat_x = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]], dtype=np.float32)
    feat_y = np.array([[9.0, 1.0], [1.0, 1.0], [1.0, 8.0], [6.0, 0.0]], dtype=np.float32)
    result = nn_match(feat_x, feat_y, device=device)
    assert result.dtype == np.int64
    np.testing.assert_array_equal(result, [1, 0, 2, 1])


# ----------------------------------------------------------------------------- FAUST


def test_matchers_rank_nn_worse_than_fmap_worse_than_zoomout(pair, maps):
    errors = {name: pair.error(m) for name, m in maps.items()}
    # measured with these settings: nn 20.1, fmap 4.7, fmap + ZoomOut 1.5
    assert errors["fmap"] < 0.5 * errors["nn"], errors
    assert errors["zoomout"] < 0.6 * errors["fmap"], errors
    assert errors["zoomout"] < 3.0, errors
    for m in maps.values():
        assert m.shape == (pair.y.n_vertices,) and m.dtype == np.int64


def test_self_match_is_the_identity(pair):
    identity = np.arange(pair.x.n_vertices)
    assert np.mean(nn_match(pair.feat_x, pair.feat_x) == identity) > 0.99
    c = fm.fmap_from_descriptors(pair.basis_x, pair.basis_x, pair.feat_x, pair.feat_x, K)
    np.testing.assert_allclose(c, np.eye(K), atol=1e-8)  # zero energy, and the minimiser is unique
    assert np.mean(fm.pointmap_from_fmap(c, pair.basis_x, pair.basis_x) == identity) > 0.99
    assert np.mean(fm.zoomout(identity, pair.basis_x, pair.basis_x, K, K_END, 10) == identity) > 0.99
    np.testing.assert_allclose(fm.fmap_from_pointmap(identity, pair.basis_x, pair.basis_x, 20), np.eye(20), atol=1e-10)


# ----------------------------------------------------------------------------- against pyFM


def test_conversions_match_pyfm(pair, maps):
    from pyFM.spectral import FM_to_p2p, p2p_to_FM

    evecs_x, evecs_y = pair.basis_x.evecs, pair.basis_y.evecs
    c = fm.fmap_from_pointmap(maps["nn"], pair.basis_x, pair.basis_y, 40, 35)
    reference = p2p_to_FM(maps["nn"], evecs_x[:, :40], evecs_y[:, :35], A2=pair.basis_y.mass)
    np.testing.assert_allclose(c, reference, atol=1e-10)
    ours = fm.pointmap_from_fmap(c, pair.basis_x, pair.basis_y)
    theirs = FM_to_p2p(c, evecs_x, evecs_y)
    assert np.mean(ours == theirs) > 0.999


def test_zoomout_matches_pyfm(pair, maps):
    from pyFM.refine.zoomout import zoomout_refine

    c0 = fm.fmap_from_pointmap(maps["fmap"], pair.basis_x, pair.basis_y, K)
    _, theirs = zoomout_refine(c0, pair.basis_x.evecs, pair.basis_y.evecs, nit=3, step=10, A2=pair.basis_y.mass, return_p2p=True)
    ours = fm.zoomout(maps["fmap"], pair.basis_x, pair.basis_y, K, K_END, step=10)
    assert np.mean(ours == theirs) > 0.999


def test_descriptor_solver_minimises_pyfm_energy(pair):
    """pyFM's energy with w_dcomm = w_orient = 0 is ours halved: its gradient vanishes at our C."""
    from pyFM.optimize.base_functions import energy_func_std, grad_energy_std
    from pyFM.optimize.weights import resolvent_mask

    lap_weight = 0.3
    c = fm.fmap_from_descriptors(pair.basis_x, pair.basis_y, pair.feat_x, pair.feat_y, K, lap_weight=lap_weight)
    a = fm.project(pair.basis_x, mass_normalize(pair.feat_x.astype(float), pair.basis_x.mass), K)
    b = fm.project(pair.basis_y, mass_normalize(pair.feat_y.astype(float), pair.basis_y.mass), K)
    mask = resolvent_mask(pair.basis_x.evals[:K], pair.basis_y.evals[:K], gamma=0.5)
    np.testing.assert_allclose(fm.laplacian_mask(pair.basis_x.evals[:K], pair.basis_y.evals[:K]), mask, atol=1e-12)
    args = (1.0, lap_weight, 0.0, 0.0, a, b, [], [], mask)
    gradient = grad_energy_std(c, *args).reshape(K, K)[:, 1:]  # pyFM leaves the first column out of its gradient
    assert np.abs(gradient).max() < 1e-8 * np.abs(b @ a.T).max()
    perturbed = c + 1e-3 * np.random.default_rng(0).standard_normal(c.shape)
    assert energy_func_std(c, *args) < energy_func_std(perturbed, *args)


# ----------------------------------------------------------------------------- small problems


def test_row_solver_equals_dense_least_squares():
    rng = np.random.default_rng(1)
    k_x, k_y, p = 5, 4, 7
    a, b, weights = rng.standard_normal((k_x, p)), rng.standard_normal((k_y, p)), rng.uniform(0, 1, (k_y, k_x))
    w_d, w_l = 2.0, 0.7
    # vec(C) row-major: C A - B stacks as kron(I_ky, A^T) vec(C); penalty sqrt(w_l W_ij) C_ij
    system = np.vstack([np.sqrt(w_d) * np.kron(np.eye(k_y), a.T), np.diag(np.sqrt(w_l * weights.ravel()))])
    target = np.concatenate([np.sqrt(w_d) * b.ravel(), np.zeros(k_x * k_y)])
    expected = np.linalg.lstsq(system, target, rcond=None)[0].reshape(k_y, k_x)
    np.testing.assert_allclose(fm._solve_rows(a, b, weights, w_d, w_l), expected, atol=1e-10)


def test_squared_mask_is_the_commutator_of_diagonal_laplacians():
    evals_x, evals_y = np.array([0.0, 1.0, 3.0]), np.array([0.0, 2.0])
    c = np.random.default_rng(2).standard_normal((2, 3))
    commutator = c @ np.diag(evals_x) - np.diag(evals_y) @ c
    weights = fm.laplacian_mask(evals_x, evals_y, kind="squared")
    assert weights.shape == (2, 3)
    assert np.sum(weights * c**2) == pytest.approx(np.sum(commutator**2))
    assert np.all(fm.laplacian_mask(evals_x, evals_y) < 1)


def test_bad_inputs_raise_clear_errors(pair):
    bx, by = pair.basis_x, pair.basis_y
    with pytest.raises(FunctionalMapError, match="same number of channels"):
        nn_match(pair.feat_x, pair.feat_y[:, :10])
    with pytest.raises(FunctionalMapError, match="n_channels"):
        nn_match(pair.feat_x[:, 0], pair.feat_y)
    with pytest.raises(FunctionalMapError, match="NaN"):
        nn_match(np.full((3, 2), np.nan), np.zeros((2, 2)))
    with pytest.raises(FunctionalMapError, match="only 100"):
        fm.fmap_from_descriptors(bx, by, pair.feat_x, pair.feat_y, 150)
    with pytest.raises(FunctionalMapError, match="one row per vertex"):
        fm.fmap_from_descriptors(bx, by, pair.feat_x[:-1], pair.feat_y, K)
    partial = np.arange(pair.y.n_vertices)
    partial[3] = -1
    with pytest.raises(FunctionalMapError, match="-1"):
        fm.fmap_from_pointmap(partial, bx, by, K)
    with pytest.raises(FunctionalMapError, match="multiple of step"):
        fm.zoomout(np.arange(pair.y.n_vertices), bx, by, K, K_END, step=7)
    with pytest.raises(FunctionalMapError, match="2-D"):
        fm.pointmap_from_fmap(np.eye(K)[0], bx, by)
    with pytest.raises(FunctionalMapError, match="vertices"):
        fmap_match(pair.x, pair.y, pair.feat_y[:10], pair.feat_y)
    with pytest.raises(FunctionalMapError, match="k_final"):
        fmap_match(pair.x, pair.y, pair.feat_x, pair.feat_y, k=K, k_final=K - 1)
    with pytest.raises(FunctionalMapError, match="kind"):
        fm.laplacian_mask(bx.evals, by.evals, kind="cubic")
    assert issubclass(FunctionalMapError, geofeat.GeofeatError)
