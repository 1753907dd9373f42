"""Differentiable functional-map layers and losses, on a mesh and a copy of it with permuted vertices."""

import numpy as np
import pytest
import torch
from shapes import bumpy

import geofeat
from geofeat.adapters.blocks import fmap_layers as fl
from geofeat.adapters.blocks import fmap_losses as fls
from geofeat.adapters.blocks import functional_maps as fm
from geofeat.errors import FunctionalMapError, GeofeatError
from geofeat.geometry.spectral import spectral_basis

K = 30


class PermutedPair:
    """A bumpy sphere ``x`` and the same surface ``y`` with permuted vertices: ``map_yx = perm`` is the truth."""

    def __init__(self, k=K):
        self.x = bumpy(0, 3)
        rng = np.random.default_rng(0)
        self.perm = rng.permutation(self.x.n_vertices)
        inverse = np.argsort(self.perm)
        self.y = geofeat.Mesh(self.x.verts[self.perm], inverse[self.x.faces], name="bumpy0-permuted")
        self.basis_x, self.basis_y = spectral_basis(self.x, k), spectral_basis(self.y, k)
        wks = geofeat.compute(self.x, "wks", cache=False)
        self.feat_x = torch.tensor(wks, dtype=torch.float64)
        self.feat_y = self.feat_x[self.perm]
        self.c_true = fm.fmap_from_pointmap(self.perm, self.basis_x, self.basis_y, k)  # +-1 diagonal

    def spectral(self):
        """Arguments evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y of `regularized_fmap`."""
        bx, by = self.basis_x, self.basis_y
        return bx.evecs, by.evecs, bx.mass, by.mass, bx.evals, by.evals


@pytest.fixture(scope="module")
def pair():
    return PermutedPair()


def tiny_problem(seed=0, n_x=9, n_y=8, k=3, p=5):
    """Random float64 features and bases small enough for gradcheck."""
    g = torch.Generator().manual_seed(seed)
    feat_x, feat_y = torch.randn(n_x, p, generator=g, dtype=torch.float64), torch.randn(n_y, p, generator=g, dtype=torch.float64)
    mass_x, mass_y = (
        torch.rand(n_x, generator=g, dtype=torch.float64) + 0.5,
        torch.rand(n_y, generator=g, dtype=torch.float64) + 0.5,
    )
    evecs_x, evecs_y = (
        torch.randn(n_x, k, generator=g, dtype=torch.float64),
        torch.randn(n_y, k, generator=g, dtype=torch.float64),
    )
    evals_x = torch.cat(
        [torch.zeros(1, dtype=torch.float64), torch.rand(k - 1, generator=g, dtype=torch.float64).sort().values * 10]
    )
    evals_y = torch.cat(
        [torch.zeros(1, dtype=torch.float64), torch.rand(k - 1, generator=g, dtype=torch.float64).sort().values * 10]
    )
    return feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y


# ----------------------------------------------------------------------------- regularised functional map


def test_regularized_fmap_recovers_the_true_map(pair):
    c_xy, c_yx = fl.regularized_fmap(pair.feat_x, pair.feat_y, *pair.spectral(), bidirectional=True)
    assert c_xy.shape == (K, K) and c_xy.dtype == torch.float64
    np.testing.assert_allclose(c_xy.numpy(), pair.c_true, atol=5e-3)
    np.testing.assert_allclose(c_yx.numpy(), pair.c_true.T, atol=5e-3)  # the inverse of a +-1 diagonal
    c32 = fl.regularized_fmap(pair.feat_x.float(), pair.feat_y.float(), *pair.spectral())
    assert c32.dtype == torch.float32
    np.testing.assert_allclose(c32.numpy(), pair.c_true, atol=5e-3)
    # the losses of the true map are about zero
    assert fls.fmap_bijectivity_loss(c_xy, c_yx) < 1e-4
    assert fls.fmap_orthogonality_loss(c_xy) < 1e-4 and fls.fmap_orthogonality_loss(c_yx) < 1e-4
    assert fls.laplacian_commutativity_loss(c_xy, pair.basis_x.evals, pair.basis_y.evals) < 1e-2
    hard = torch.zeros(pair.y.n_vertices, pair.x.n_vertices, dtype=torch.float64)
    hard[torch.arange(pair.y.n_vertices), torch.as_tensor(pair.perm)] = 1.0
    assert fls.coupling_loss(c_xy, hard, pair.basis_x.evecs, pair.basis_y.evecs, pair.basis_y.mass) < 1e-4


def test_regularized_fmap_matches_the_numpy_solver(pair):
    rng = np.random.default_rng(1)
    desc_x = rng.standard_normal((pair.x.n_vertices, 40))
    desc_y = rng.standard_normal((pair.y.n_vertices, 40))
    for mask, lam in [("resolvent", 100.0), ("squared", 0.01)]:
        expected = fm.fmap_from_descriptors(
            pair.basis_x, pair.basis_y, desc_x, desc_y, k_x=20, k_y=K, lap_weight=lam, mask=mask, normalize_descriptors=False
        )
        bx, by = pair.basis_x, pair.basis_y
        got = fl.regularized_fmap(
            torch.tensor(desc_x),
            torch.tensor(desc_y),
            bx.evecs[:, :20],
            by.evecs,
            bx.mass,
            by.mass,
            bx.evals[:20],
            by.evals,
            lam,
            mask=mask,
        )
        assert got.shape == (K, 20)
        np.testing.assert_allclose(got.numpy(), expected, atol=1e-10)


def test_resolvent_mask_by_hand():
    evals_x, evals_y, gamma = [0.0, 1.0, 4.0], [0.0, 2.0, 3.0], 0.5
    scale = 4.0  # the largest eigenvalue of both spectra

    def resolvent(value):
        return 1.0 / ((value / scale) ** gamma - 1j)

    expected = np.array([[abs(resolvent(mu) - resolvent(lam)) ** 2 for lam in evals_x] for mu in evals_y])
    got = fl.resolvent_mask(torch.tensor(evals_x, dtype=torch.float64), torch.tensor(evals_y, dtype=torch.float64), gamma=gamma)
    assert got.shape == (3, 3)  # rows y, columns x
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=1e-15)
    # one entry fully by hand: mu = 2 -> t = sqrt(1/2), lambda = 1 -> t = 1/2
    re = np.sqrt(0.5) / 1.5 - 0.5 / 1.25
    im = 1 / 1.5 - 1 / 1.25
    assert got[1, 1].item() == pytest.approx(re**2 + im**2, rel=1e-12)
    assert got[0, 0].item() == 0.0 and got[2, 2].item() > 0.0
    np.testing.assert_allclose(
        fl.resolvent_mask(evals_x, evals_y, kind="squared").numpy(), np.square(np.subtract.outer(evals_y, evals_x))
    )


def test_gradients_flow_and_match_finite_differences():
    feat_x, feat_y, *spectral = tiny_problem()
    feat_x.requires_grad_(True)
    feat_y.requires_grad_(True)

    def both_maps(fx, fy):
        return fl.regularized_fmap(fx, fy, *spectral, lambda_=0.5, bidirectional=True)

    assert torch.autograd.gradcheck(both_maps, (feat_x, feat_y), eps=1e-6, atol=1e-6)
    c_xy, c_yx = both_maps(feat_x, feat_y)
    loss = fls.fmap_bijectivity_loss(c_xy, c_yx) + fls.fmap_orthogonality_loss(c_xy)
    loss.backward()
    assert feat_x.grad.abs().sum() > 0 and feat_y.grad.abs().sum() > 0

    evecs_x, evecs_y, mass_x, mass_y = spectral[:4]

    def coupled(fx, fy):
        c = fl.regularized_fmap(fx, fy, *spectral, lambda_=0.5)
        return fls.coupling_loss(c, fl.soft_pointmap(fx, fy, temperature=0.5), evecs_x, evecs_y, mass_y)

    assert torch.autograd.gradcheck(coupled, (feat_x, feat_y), eps=1e-6, atol=1e-6)


def test_batched_equals_unbatched():
    problems = [tiny_problem(seed) for seed in (0, 1)]
    stacked = [torch.stack(parts) for parts in zip(*problems, strict=True)]
    c_xy, c_yx = fl.regularized_fmap(*stacked, lambda_=0.5, bidirectional=True)
    assert c_xy.shape == (2, 3, 3) and c_yx.shape == (2, 3, 3)
    for b, problem in enumerate(problems):
        single_xy, single_yx = fl.regularized_fmap(*problem, lambda_=0.5, bidirectional=True)
        torch.testing.assert_close(c_xy[b], single_xy)
        torch.testing.assert_close(c_yx[b], single_yx)
    # unbatched inputs are shared by the batch: two feature sets on one pair of bases
    feats_x = torch.stack([problems[0][0], problems[1][0]])
    shared = fl.regularized_fmap(feats_x, problems[0][1], *problems[0][2:], lambda_=0.5)
    torch.testing.assert_close(shared[0], fl.regularized_fmap(*problems[0], lambda_=0.5))
    # losses of a batch are the means of the single losses
    evals_x, evals_y = stacked[6], stacked[7]
    for loss, args, single in [
        (fls.fmap_bijectivity_loss, (c_xy, c_yx), lambda b: (c_xy[b], c_yx[b])),
        (fls.fmap_orthogonality_loss, (c_xy,), lambda b: (c_xy[b],)),
        (fls.laplacian_commutativity_loss, (c_xy, evals_x, evals_y), lambda b: (c_xy[b], evals_x[b], evals_y[b])),
        (fls.partial_orthogonality_loss, (c_xy, evals_x, evals_y), lambda b: (c_xy[b], evals_x[b], evals_y[b])),
    ]:
        torch.testing.assert_close(loss(*args), (loss(*single(0)) + loss(*single(1))) / 2)
    p = fl.soft_pointmap(stacked[0], stacked[1])
    assert p.shape == (2, 8, 9)
    torch.testing.assert_close(p[1], fl.soft_pointmap(problems[1][0], problems[1][1]))


def test_module_wraps_the_function():
    problem = tiny_problem()
    layer = fl.RegularizedFMap(lambda_=0.5, bidirectional=True)
    assert "lambda_=0.5" in repr(layer)
    for got, expected in zip(layer(*problem), fl.regularized_fmap(*problem, lambda_=0.5, bidirectional=True), strict=True):
        torch.testing.assert_close(got, expected)


# ----------------------------------------------------------------------------- point maps


def test_pointmap_to_fmap_of_a_permutation_equals_the_numpy_conversion(pair):
    expected = fm.fmap_from_pointmap(pair.perm, pair.basis_x, pair.basis_y, K)
    hard = torch.zeros(pair.y.n_vertices, pair.x.n_vertices, dtype=torch.float64)
    hard[torch.arange(pair.y.n_vertices), torch.as_tensor(pair.perm)] = 1.0
    bx, by = pair.basis_x, pair.basis_y
    np.testing.assert_allclose(fl.pointmap_to_fmap(hard, bx.evecs, by.evecs, by.mass).numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(fl.pointmap_to_fmap(pair.perm, bx.evecs, by.evecs, by.mass).numpy(), expected, atol=1e-12)
    # a non-square map: k_y = 10 rows, k_x = 20 columns
    small = fm.fmap_from_pointmap(pair.perm, bx, by, 20, 10)
    np.testing.assert_allclose(fl.pointmap_to_fmap(hard, bx.evecs[:, :20], by.evecs[:, :10], by.mass).numpy(), small, atol=1e-12)


def test_soft_pointmaps_equal_two_soft_pointmaps_with_their_gradients():
    feat_x, feat_y, *_ = tiny_problem(p=4)
    grads = []
    for both in (True, False):
        fx, fy = feat_x.clone().requires_grad_(), feat_y.clone().requires_grad_()
        if both:
            p_yx, p_xy = fl.soft_pointmaps(fx, fy, temperature=0.3)
        else:
            p_yx, p_xy = fl.soft_pointmap(fx, fy, temperature=0.3), fl.soft_pointmap(fy, fx, temperature=0.3)
        weights = torch.arange(p_yx.numel(), dtype=p_yx.dtype).reshape(p_yx.shape)
        ((p_yx * weights).sum() + (p_xy * weights.T).square().sum()).backward()
        grads.append((p_yx.detach(), p_xy.detach(), fx.grad, fy.grad))
    for new, old in zip(*grads, strict=True):
        torch.testing.assert_close(new, old, rtol=1e-12, atol=1e-12)


def test_soft_pointmap_of_identical_features_is_the_permutation(pair):
    p = fl.soft_pointmap(pair.feat_x, pair.feat_y, temperature=0.01)
    assert p.shape == (pair.y.n_vertices, pair.x.n_vertices)
    torch.testing.assert_close(p.sum(dim=1), torch.ones(pair.y.n_vertices, dtype=torch.float64))
    np.testing.assert_array_equal(p.argmax(dim=1).numpy(), pair.perm)
    # cosine similarity by hand on two vectors
    fx, fy = torch.tensor([[1.0, 0.0], [0.0, 2.0]]), torch.tensor([[3.0, 3.0]])
    logits = torch.tensor([0.5**0.5, 0.5**0.5]) / 0.1
    torch.testing.assert_close(fl.soft_pointmap(fx, fy, temperature=0.1)[0], torch.softmax(logits, 0))
    raw = fl.soft_pointmap(fx, fy, temperature=1.0, normalize=False)[0]
    torch.testing.assert_close(raw, torch.softmax(torch.tensor([3.0, 6.0]), 0))


def test_fmap_to_pointmap_soft_relaxes_the_nearest_neighbour_conversion(pair):
    scale = np.sqrt(pair.x.area())  # unit-area eigenvectors
    evecs_x, evecs_y = pair.basis_x.evecs * scale, pair.basis_y.evecs * scale
    c = torch.tensor(pair.c_true, requires_grad=True)
    p = fl.fmap_to_pointmap_soft(c, evecs_x, evecs_y, temperature=0.1)
    torch.testing.assert_close(p.sum(dim=1), torch.ones(pair.y.n_vertices, dtype=torch.float64))
    np.testing.assert_array_equal(p.argmax(dim=1).numpy(), pair.perm)
    np.testing.assert_array_equal(p.argmax(dim=1).numpy(), fm.pointmap_from_fmap(pair.c_true, pair.basis_x, pair.basis_y))
    p[:, 0].sum().backward()
    assert torch.isfinite(c.grad).all() and c.grad.abs().sum() > 0


# ----------------------------------------------------------------------------- losses


def test_losses_are_zero_for_the_identity_and_positive_for_a_random_map():
    k = 6
    eye = torch.eye(k, dtype=torch.float64)
    evals = torch.linspace(0.0, 5.0, k, dtype=torch.float64)
    assert fls.fmap_bijectivity_loss(eye, eye) == 0
    assert fls.fmap_orthogonality_loss(eye) == 0
    assert fls.laplacian_commutativity_loss(eye, evals, evals) == 0
    random = torch.randn(k, k, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert fls.fmap_bijectivity_loss(random, random.T) > 0.1
    assert fls.fmap_orthogonality_loss(random) > 0.1
    assert fls.laplacian_commutativity_loss(random, evals, evals) > 0.1
    # values by hand: C = 2 I gives ||4 I - I||^2 = 9 k for each product
    assert fls.fmap_orthogonality_loss(2 * eye).item() == pytest.approx(9 * k)
    assert fls.fmap_bijectivity_loss(2 * eye, eye).item() == pytest.approx(2 * k)
    swap = torch.tensor([[0.0, 1.0], [1.0, 0.0]], dtype=torch.float64)  # ||C diag(0, 1) - diag(0, 1) C||^2 = 2
    assert fls.laplacian_commutativity_loss(swap, [0.0, 1.0], [0.0, 1.0]).item() == pytest.approx(2.0)


def test_partial_rank_and_losses():
    evals_full = torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0])
    evals_part = torch.tensor([0.0, 2.5, 3.9, 6.0, 9.0])  # two below 4 besides 0: n = 3, r = n + 1 = 4
    assert fls.partial_rank(evals_full, evals_part).item() == 4
    assert fls.partial_rank(evals_full, evals_full * 10).item() == 2  # n = 1 (only the zero eigenvalue)
    assert fls.partial_rank(evals_full, evals_full).item() == 5  # n = 4, clamped at k_y = 5
    batched = fls.partial_rank(torch.stack([evals_full, evals_full]), torch.stack([evals_part, evals_full]))
    assert batched.tolist() == [4, 5]
    truncated = torch.diag(torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0]))
    assert fls.partial_orthogonality_loss(truncated, evals_full, evals_part) == 0
    assert fls.partial_bijectivity_loss(truncated, truncated, evals_full, evals_part) == 0
    assert fls.partial_orthogonality_loss(torch.eye(5), evals_full, evals_part).item() == pytest.approx(1.0)
    # a non-square map (k_y = 3 rows of the part, k_x = 5 columns of the full shape): C C^T is (3, 3)
    wide = torch.zeros(3, 5)
    wide[0, 0] = wide[1, 1] = 1.0
    assert fls.partial_orthogonality_loss(wide, evals_full, torch.tensor([0.0, 5.0, 8.0])) == 0  # n = 1, r = 2


def test_partial_orthogonality_of_a_real_part():
    """The map of a half of a shape into the whole satisfies the partial penalty far better than the full one."""
    x = bumpy(1, 3)
    keep = np.flatnonzero(x.verts[:, 2] > 0.0)  # about half of the area
    index = np.full(x.n_vertices, -1)
    index[keep] = np.arange(keep.size)
    faces = index[x.faces]
    y = geofeat.Mesh(x.verts[keep], faces[(faces >= 0).all(axis=1)], name="bumpy1-part")
    k = 20
    bx, by = spectral_basis(x, k), spectral_basis(y, k)
    c = fm.fmap_from_pointmap(keep, bx, by, k)  # map_yx: vertex i of the part is vertex keep[i] of x
    partial = fls.partial_orthogonality_loss(c, bx.evals, by.evals).item()
    full = fls.fmap_orthogonality_loss(torch.tensor(c).T).item()  # ||C C^T - I||^2
    area_ratio = y.area() / x.area()
    assert abs(fls.partial_rank(bx.evals, by.evals).item() - area_ratio * k) <= 0.25 * k  # r follows the area ratio
    assert partial < 0.5 * full


# ----------------------------------------------------------------------------- errors


def test_bad_inputs_raise_clear_errors():
    feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y = tiny_problem()
    cases = [
        (
            lambda: fl.regularized_fmap(feat_x[:, :4], feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y),
            "same number of channels",
        ),
        (
            lambda: fl.regularized_fmap(feat_x, feat_y, evecs_y, evecs_y, mass_x, mass_y, evals_x, evals_y),
            "evecs_x must have one row per vertex",
        ),
        (lambda: fl.regularized_fmap(feat_x, feat_y, evecs_x, evecs_y, mass_y, mass_y, evals_x, evals_y), "mass_x"),
        (lambda: fl.regularized_fmap(feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x[:2], evals_y), "evals_x"),
        (lambda: fl.regularized_fmap(feat_x[0], feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y), "2 dimensions"),
        (
            lambda: fl.regularized_fmap(feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y, lambda_=-1.0),
            "lambda_",
        ),
        (lambda: fl.regularized_fmap(feat_x, feat_y, evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y, mask="cubic"), "mask"),
        (
            lambda: fl.regularized_fmap(
                torch.stack([feat_x] * 2), torch.stack([feat_y] * 3), evecs_x, evecs_y, mass_x, mass_y, evals_x, evals_y
            ),
            "same batch size",
        ),
        (lambda: fl.soft_pointmap(feat_x, feat_y, temperature=0.0), "temperature"),
        (lambda: fl.pointmap_to_fmap(torch.zeros(8, 7), evecs_x, evecs_y, mass_y), "columns"),
        (lambda: fl.pointmap_to_fmap(torch.full((8,), 9), evecs_x, evecs_y, mass_y), r"\[0, 8\]"),
        (lambda: fl.fmap_to_pointmap_soft(torch.eye(3), evecs_x[:, :2], evecs_y), "evecs_x"),
        (lambda: fls.fmap_bijectivity_loss(torch.eye(3), torch.zeros(3, 4)), "transposed shape"),
        (lambda: fls.laplacian_commutativity_loss(torch.eye(3), evals_x[:2], evals_y), "evals_x"),
        (lambda: fls.coupling_loss(torch.eye(2), torch.eye(8, 9), evecs_x, evecs_y, mass_y), "shape"),
        (lambda: fls.partial_orthogonality_loss(torch.eye(3), evals_x, evals_y[:2]), "evals_y"),
        (lambda: fl.resolvent_mask(evals_x, evals_y, gamma=2.0), "gamma"),
        (lambda: fl.RegularizedFMap(mask="cubic"), "mask"),
        (lambda: fls.fmap_orthogonality_loss([["a", "b"], ["c", "d"]]), "array of numbers"),
        (lambda: fls.fmap_orthogonality_loss(torch.ones(2, 2, dtype=torch.bool)), "real numbers"),
    ]
    for call, message in cases:
        with pytest.raises(FunctionalMapError, match=message) as info:
            call()
        assert isinstance(info.value, GeofeatError)


@pytest.mark.numerically_sensitive
def test_singular_system_raises():
    feat_x, feat_y, *spectral = tiny_problem(p=1)
    with pytest.raises(FunctionalMapError, match="singular"):
        fl.regularized_fmap(feat_x, feat_y, *spectral, lambda_=0.0)


@pytest.mark.numerically_sensitive
def test_singular_system_is_detected_without_the_solver_raising(monkeypatch):
    """Some LAPACK kernels (Intel, 1 or 2 threads) return a result for this singular system instead of raising."""
    feat_x, feat_y, *spectral = tiny_problem(p=1)

    def quiet_solve(systems, rhs):
        return torch.zeros_like(rhs)

    monkeypatch.setattr(fl.torch.linalg, "solve", quiet_solve)
    with pytest.raises(FunctionalMapError, match="singular for 3 row"):
        fl.regularized_fmap(feat_x, feat_y, *spectral, lambda_=0.0)
