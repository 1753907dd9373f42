"""EchoMatch against the facts of the authors' code (DeepShapeMatchingKit), on small hand-checkable inputs.

The full stage-by-stage comparison with the reference code is ``benchmarks/parity/echomatch.py``
(it needs a clone of the reference); these tests pin the conventions it checked: the
reference preset, the checkpoint key mapping, and the formulas of the reflection features
and of every loss term, each written out here the way the reference computes it.
"""

import numpy as np
import pytest
import torch
from shapes import bumpy

import geofeat.adapters.echomatch.head as echomatch
from geofeat.adapters.echomatch.config import EchoMatchConfig
from geofeat.adapters.echomatch.head import EchoMatchHead
from geofeat.adapters.echomatch.losses import balanced_bce_with_logits, cross_nce_loss, regularized_gt_fmap, self_nce_loss
from geofeat.adapters.echomatch.reflection import reflection_features, sampled_reflection, spatial_neighbours
from geofeat.adapters.heads import load_head, make_head
from geofeat.datasets.records import ShapePair
from geofeat.errors import HeadError
from geofeat.geometry import make_partial

#: ``options/echo_match/train/echo_match_*_xyz.yaml`` and the constructor of ``Echo_Match_Net``.
AUTHORS = {
    "descriptor": "xyz",
    "laplacian": "cotan",
    "operators": "ulrssm",
    "n_eig": 128,
    "n_fmap": 50,
    "feature_channels": 128,
    "width": 128,
    "n_blocks": 4,
    "dropout": 0.5,
    "temperature_init": 0.1,
    "n_neighbours": 64,
    "overlap_width": 16,
    "overlap_blocks": 3,
    "fmap_lambda": 100.0,
    "fmap_gamma": 0.5,
    "gt_fmap_lambda": 1e6,
    "w_fmap": 1.0,
    "w_overlap": 1.0,
    "w_nce_self": 0.1,
    "w_nce_cross": 0.1,
    "nce_temperature": 0.07,
    "prune_strategy": "y",
    "overlap_threshold": 0.5,
    "epochs": 900,
    "lr": 1e-3,
    "grad_clip": 1.0,
}


def test_reference_preset_is_the_authors_configuration():
    head = make_head("echomatch", preset="reference", progress=False)
    for key, value in AUTHORS.items():
        assert getattr(head.config, key) == value, key


def test_defaults_are_the_authors_network_loss_and_clipping():
    config = EchoMatchConfig()
    for key, value in AUTHORS.items():
        if key not in ("descriptor", "laplacian", "operators"):  # inputs: geofeat's defaults
            assert getattr(config, key) == value, key


# ----------------------------------------------------------------------------- checkpoint keys


def _reference_diffusionnet(prefix: str, c_in: int, width: int, c_out: int, n_blocks: int, gen) -> dict:
    """Tensors named as the reference's ``DiffusionNet_A`` (DPFM spelling), random values."""
    state = {
        f"{prefix}first_lin.weight": torch.randn(width, c_in, generator=gen),
        f"{prefix}first_lin.bias": torch.randn(width, generator=gen),
        f"{prefix}last_lin.weight": torch.randn(c_out, width, generator=gen),
        f"{prefix}last_lin.bias": torch.randn(c_out, generator=gen),
    }
    for i in range(n_blocks):
        b = f"{prefix}block_{i}."
        state[b + "diffusion.diffusion_time"] = torch.rand(width, generator=gen)
        state[b + "gradient_features.A_re.weight"] = torch.randn(width, width, generator=gen)
        state[b + "gradient_features.A_im.weight"] = torch.randn(width, width, generator=gen)
        for j, n_in in enumerate((3 * width, width, width)):
            state[b + f"mlp.miniMLP_mlp_layer_{j:03d}.weight"] = torch.randn(width, n_in, generator=gen)
            state[b + f"mlp.miniMLP_mlp_layer_{j:03d}.bias"] = torch.randn(width, generator=gen)
    return state


def _reference_checkpoint(c_in: int = 3, module_prefix: str = "") -> dict:
    gen = torch.Generator().manual_seed(0)
    state = _reference_diffusionnet("feature_extractor.", c_in, 8, 6, 2, gen)
    state |= _reference_diffusionnet("overlap_diffusion_net.", 5, 4, 1, 1, gen)
    state["permutation_network.tau"] = torch.tensor([0.25])
    return {"networks": {"echo_match_net": {module_prefix + k: v for k, v in state.items()}}, "epoch": 3}


def test_release_state_maps_every_reference_tensor_to_its_place():
    raw = _reference_checkpoint()
    release = EchoMatchHead.release_state(raw)
    assert release.in_channels == 3
    assert release.settings == {
        "descriptor": "xyz",
        "descriptor_params": {},
        "feature_channels": 6,
        "width": 8,
        "n_blocks": 2,
        "n_neighbours": 5,
        "overlap_width": 4,
        "overlap_blocks": 1,
        "learn_log_temperature": False,
    }
    src = raw["networks"]["echo_match_net"]
    head = make_head("echomatch", preset="reference", progress=False, **release.settings)
    head.load_state(release.state, release.in_channels, "synthetic")
    ours = head.model.state_dict()
    assert len(ours) == len(src)
    pairs = {
        "features.first.weight": "feature_extractor.first_lin.weight",
        "features.last.bias": "feature_extractor.last_lin.bias",
        "features.blocks.1.diffusion.time": "feature_extractor.block_1.diffusion.diffusion_time",
        "features.blocks.1.gradient_features.a_im.weight": "feature_extractor.block_1.gradient_features.A_im.weight",
        "features.blocks.0.mlp.0.weight": "feature_extractor.block_0.mlp.miniMLP_mlp_layer_000.weight",
        "features.blocks.0.mlp.3.weight": "feature_extractor.block_0.mlp.miniMLP_mlp_layer_001.weight",
        "features.blocks.1.mlp.6.bias": "feature_extractor.block_1.mlp.miniMLP_mlp_layer_002.bias",
        "overlap.first.weight": "overlap_diffusion_net.first_lin.weight",
        "overlap.blocks.0.mlp.6.weight": "overlap_diffusion_net.block_0.mlp.miniMLP_mlp_layer_002.weight",
        "temperature": "permutation_network.tau",
    }
    for our_key, ref_key in pairs.items():
        assert torch.equal(ours[our_key], src[ref_key]), our_key


def test_release_checkpoint_loads_through_load_head(tmp_path):
    path = tmp_path / "echo_match_synthetic_xyz.pth"
    torch.save(_reference_checkpoint(module_prefix="module."), path)  # DataParallel prefix, dropped like the reference
    head = load_head("echomatch", checkpoint=path, progress=False)
    assert head.config.n_neighbours == 5 and head.config.descriptor == "xyz"
    assert float(head.model.temperature.detach()) == pytest.approx(0.25)


def test_release_state_names_a_renamed_key_and_refuses_other_inputs():
    raw = _reference_checkpoint()
    state = raw["networks"]["echo_match_net"]
    state["feature_extractor.block_0.diffusion.time"] = state.pop("feature_extractor.block_0.diffusion.diffusion_time")
    with pytest.raises(HeadError, match="feature_extractor.block_0.diffusion.diffusion_time"):
        EchoMatchHead.release_state(raw)
    with pytest.raises(HeadError, match="768 input channels"):
        EchoMatchHead.release_state(_reference_checkpoint(c_in=768))
    with pytest.raises(HeadError, match="EchoMatch layout"):
        EchoMatchHead.release_state({"networks": {"feature_extractor": {}}})


# ----------------------------------------------------------------------------- formulas


def test_reflection_features_are_the_dense_round_trip_at_the_neighbours_over_its_maximum():
    gen = torch.Generator().manual_seed(1)
    p_xy = torch.softmax(torch.randn(5, 4, generator=gen, dtype=torch.float64), dim=1)
    p_yx = torch.softmax(torch.randn(4, 5, generator=gen, dtype=torch.float64), dim=1)
    nbrs = torch.tensor([[0, 1, 2], [1, 0, 4], [2, 3, 1], [3, 2, 4], [4, 3, 0]])
    dense = (p_xy @ p_yx).numpy()
    gathered = np.take_along_axis(dense, nbrs.numpy(), axis=1)  # the reference: matrix.gather(1, idx) / max
    expected = np.concatenate([gathered / gathered.max(), np.zeros((5, 2))], axis=1)  # zero-padded to the width
    got = reflection_features(sampled_reflection(p_xy, p_yx, nbrs), 5)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=1e-15)


def test_spatial_neighbours_are_the_euclidean_top_k_itself_first():
    verts = np.random.default_rng(2).normal(size=(30, 3))
    dist = np.linalg.norm(verts[:, None] - verts[None], axis=-1)
    np.testing.assert_array_equal(spatial_neighbours(verts, 6), np.argsort(dist, axis=1, kind="stable")[:, :6])


def test_balanced_bce_weighs_each_class_by_the_frequency_of_the_other():
    logits = torch.tensor([0.3, -1.2, 2.0, 0.0, -0.5], dtype=torch.float64)
    target = torch.tensor([1, 0, 0, 1, 1])
    p = 1 / (1 + np.exp(-logits.numpy()))
    y = target.numpy()
    bce = -(y * np.log(p) + (1 - y) * np.log(1 - p))
    w = np.where(y == 1, 1 - 3 / 5, 3 / 5)  # positives weigh 1 - n_pos/N, negatives n_pos/N
    assert float(balanced_bce_with_logits(logits, target)) == pytest.approx(float((w * bce).mean()), rel=1e-12)
    ones = torch.ones(5, dtype=torch.int64)  # one class: the plain mean
    assert float(balanced_bce_with_logits(logits, ones)) == pytest.approx(float(-np.log(p).mean()), rel=1e-12)


def _cross_entropy(logits: np.ndarray, labels: np.ndarray) -> float:
    shifted = logits - logits.max(axis=1, keepdims=True)
    log_softmax = shifted - np.log(np.exp(shifted).sum(axis=1, keepdims=True))
    return float(-log_softmax[np.arange(len(labels)), labels].mean())


def test_nce_losses_are_the_references_cross_entropies():
    fx = np.array([[1.0, 0.0], [0.6, 0.8], [0.0, 2.0]])
    fy = np.array([[0.0, 1.0], [3.0, 0.1]])
    corr_x, corr_y = np.array([2, 0]), np.array([0, 1])
    t = 0.07
    nx = fx / np.linalg.norm(fx, axis=1, keepdims=True)
    ny = fy / np.linalg.norm(fy, axis=1, keepdims=True)
    logits = nx @ ny.T / t
    cross = _cross_entropy(logits[corr_x], corr_y) + _cross_entropy(logits.T[corr_y], corr_x)
    got = cross_nce_loss(torch.tensor(fx), torch.tensor(fy), torch.tensor(corr_x), torch.tensor(corr_y), t)
    assert float(got) == pytest.approx(cross, rel=1e-12)
    own = _cross_entropy(nx @ nx.T / t, np.arange(3))
    assert float(self_nce_loss(torch.tensor(fx), t)) == pytest.approx(own, rel=1e-12)


def _resolvent_mask(evals_rows: np.ndarray, evals_cols: np.ndarray, gamma: float) -> np.ndarray:
    """The reference's ``get_mask(evals1=cols, evals2=rows)``: (len(rows), len(cols))."""
    scale = max(evals_rows.max(), evals_cols.max())
    t_rows, t_cols = (evals_rows / scale) ** gamma, (evals_cols / scale) ** gamma
    re = t_rows[:, None] / (t_rows[:, None] ** 2 + 1) - t_cols[None, :] / (t_cols[None, :] ** 2 + 1)
    im = 1 / (t_rows[:, None] ** 2 + 1) - 1 / (t_cols[None, :] ** 2 + 1)
    return re**2 + im**2


@pytest.mark.parametrize("lambda_", [3.0, 1e6])
def test_ground_truth_fmap_solves_the_references_row_systems(lambda_):
    rng = np.random.default_rng(3)
    evecs_x, evecs_y = rng.normal(size=(6, 3)), rng.normal(size=(7, 3))
    evals_x, evals_y = np.array([0.0, 1.5, 4.0]), np.array([0.0, 2.0, 3.0])
    map_yx = np.array([0, 5, -1, 2, 2, 4, 1])
    # the reference: P [corr_y, corr_x] = 1, coeff_X = (P Phi_x)^T, coeff_Y = Phi_y^T, one system per row of C^T
    p = np.zeros((7, 6))
    valid = map_yx >= 0
    p[np.flatnonzero(valid), map_yx[valid]] = 1
    coeff_x, coeff_y = (p @ evecs_x).T, evecs_y.T
    mask = _resolvent_mask(evals_x, evals_y, 0.5)  # get_mask(evals_y, evals_x): rows of x, columns of y
    c_t = np.stack([np.linalg.solve(coeff_y @ coeff_y.T + lambda_ * np.diag(mask[i]), coeff_y @ coeff_x[i]) for i in range(3)])
    got = regularized_gt_fmap(
        torch.tensor(map_yx),
        torch.tensor(evecs_x),
        torch.tensor(evecs_y),
        torch.tensor(evals_x),
        torch.tensor(evals_y),
        lambda_,
        0.5,
    )
    np.testing.assert_allclose(got.numpy(), c_t.T, rtol=1e-10, atol=1e-12)


def test_ground_truth_fmap_without_regularisation_is_the_mass_weighted_projection():
    rng = np.random.default_rng(4)
    evecs_x, evecs_y, mass_y = rng.normal(size=(6, 3)), rng.normal(size=(7, 3)), rng.uniform(0.5, 1.0, size=7)
    map_yx = np.array([0, 5, -1, 2, 2, 4, 1])
    p = np.zeros((7, 6))
    p[np.flatnonzero(map_yx >= 0), map_yx[map_yx >= 0]] = 1
    got = regularized_gt_fmap(
        torch.tensor(map_yx),
        torch.tensor(evecs_x),
        torch.tensor(evecs_y),
        torch.zeros(3, dtype=torch.float64),
        torch.zeros(3, dtype=torch.float64),
        0.0,
        mass_y=torch.tensor(mass_y),
    )
    np.testing.assert_allclose(got.numpy(), evecs_y.T @ np.diag(mass_y) @ p @ evecs_x, rtol=1e-12)


def test_training_prunes_the_features_of_y_only_and_weights_the_terms(monkeypatch):
    mesh = bumpy(0, 2)
    part = make_partial(mesh, "cuts", seed=3, keep_range=(0.5, 0.8))
    y = part.mesh
    map_yx = part.vertex_map.astype(np.int64).copy()
    map_yx[::4] = -1  # some vertices of y without a counterpart, so that pruning shows
    pair = ShapePair(mesh, y, map_yx, protocol="p2f")
    settings = dict(
        descriptor="xyz",
        n_eig=16,
        n_fmap=8,
        feature_channels=8,
        width=8,
        n_blocks=1,
        overlap_width=4,
        overlap_blocks=1,
        n_neighbours=8,
        dropout=0.0,
        progress=False,
    )
    head = make_head("echomatch", **settings)
    seen = {}
    original = echomatch.regularized_fmap

    def spy(feat_x, feat_y, *args, **kwargs):
        seen["x"], seen["y"] = feat_x.detach(), feat_y.detach()
        return original(feat_x, feat_y, *args, **kwargs)

    monkeypatch.setattr(echomatch, "regularized_fmap", spy)
    terms = head.loss_terms(head.prepare(pair))
    out, _, _ = head.network_outputs(head.prepare(pair))
    assert torch.equal(seen["y"][map_yx < 0], torch.zeros_like(seen["y"][map_yx < 0]))
    torch.testing.assert_close(seen["y"][map_yx >= 0], out.feat_y.detach()[map_yx >= 0])
    torch.testing.assert_close(seen["x"], out.feat_x.detach())
    unweighted = make_head("echomatch", **settings, w_nce_self=1.0, w_nce_cross=1.0)
    unweighted.model = head.model
    unweighted.in_channels = head.in_channels
    plain = unweighted.loss_terms(unweighted.prepare(pair))
    for key in ("nce_self", "nce_cross"):
        assert terms[key].item() == pytest.approx(0.1 * plain[key].item(), rel=1e-6)
