"""DPFM release checkpoint: key mapping, refusal of bad files, the reference conventions and a FAUST_r pair."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geofeat.adapters.dpfm import DPFMHead
from geofeat.adapters.dpfm.networks import _MultiHeadAttention
from geofeat.adapters.dpfm.sampling import ReferenceCandidates, reference_sample_interpolation
from geofeat.adapters.heads import load_head, make_head
from geofeat.datasets import load_dataset
from geofeat.errors import HeadError
from geofeat.evaluation.metrics import template_geodesic_errors
from geofeat.geometry.geodesic import geodesic_matrix

#: Measured 2026-11-23 with the reference preset and faust.pth on tr_reg_081 -> tr_reg_080 (x = tr_reg_080,
#: the reference's shape1), template protocol: 1.668 (the reference code: 1.668). The point map does not
#: depend on the sampling (the FAUST_r functional map uses the DiffusionNet features).
DPFM_PAIR_BOUND = 2.0


def _raw(release_checkpoints) -> dict:
    return torch.load(release_checkpoints / "dpfm" / "faust.pth", map_location="cpu", weights_only=True)


def test_release_state_maps_every_key(release_checkpoints):
    raw = _raw(release_checkpoints)
    release = DPFMHead.release_state(raw)
    assert release.in_channels == 3
    assert release.settings == {
        "descriptor": "xyz",
        "descriptor_params": {"normalize": False},
        "width": 128,
        "n_blocks": 4,
        "attention_dim": 128,
        "n_attention_layers": 1,
    }
    assert len(release.state) == len(raw)  # one tensor of ours per tensor of theirs
    torch.testing.assert_close(
        release.state["refiner.layers.0.attention.key.weight"], raw["feat_refiner.layers.0.attn.proj.1.weight"][..., 0]
    )
    torch.testing.assert_close(release.state["refiner.layers.0.out.bias"], raw["feat_refiner.layers.0.mlp.3.bias"])
    torch.testing.assert_close(
        release.state["overlap.net.2.weight"], raw["feat_refiner.overlap_predictor.overlap_score_net.2.weight"]
    )
    torch.testing.assert_close(
        release.state["extractor.blocks.3.mlp.6.weight"], raw["feature_extractor.block_3.mlp.miniMLP_mlp_layer_002.weight"]
    )


@pytest.mark.parametrize(
    ("old", "new"),
    [
        ("feat_refiner.layers.0.attn.proj.1.weight", "feat_refiner.layers.0.attn.proj.7.weight"),
        ("feature_extractor.block_1.diffusion.diffusion_time", "feature_extractor.block_1.diffusion.time"),
    ],
)
def test_renamed_key_is_refused_with_its_name(release_checkpoints, tmp_path, old, new):
    raw = _raw(release_checkpoints)
    raw[new] = raw.pop(old)
    torch.save(raw, tmp_path / "renamed.pth")
    with pytest.raises(HeadError, match=old.replace(".", r"\.")):
        load_head("dpfm", checkpoint=tmp_path / "renamed.pth")


@pytest.mark.parametrize(
    ("key", "shape"),
    [
        ("feat_refiner.layers.0.mlp.3.weight", (128, 200, 1)),
        ("feature_extractor.block_2.gradient_features.A_re.weight", (128, 64)),
        ("feat_refiner.overlap_predictor.overlap_score_net.0.bias", (64,)),
    ],
)
def test_wrongly_shaped_key_is_refused_with_its_name(release_checkpoints, tmp_path, key, shape):
    raw = _raw(release_checkpoints)
    raw[key] = torch.zeros(shape)
    torch.save(raw, tmp_path / "shaped.pth")
    with pytest.raises(HeadError, match=key.replace(".", r"\.") + r": " + str(shape).replace("(", r"\(").replace(")", r"\)")):
        load_head("dpfm", checkpoint=tmp_path / "shaped.pth")


def test_unexpected_key_is_refused(release_checkpoints):
    raw = _raw(release_checkpoints)
    raw["feat_refiner.layers.0.attn.extra.weight"] = torch.zeros(3)
    with pytest.raises(HeadError, match=r"unexpected \['feat_refiner\.layers\.0\.attn\.extra\.weight'\]"):
        DPFMHead.release_state(raw)
    raw = _raw(release_checkpoints)
    raw["fmreg_net.lambda"] = torch.zeros(1)
    with pytest.raises(HeadError, match=r"fmreg_net\.lambda"):
        DPFMHead.release_state(raw)


def test_reference_presets_are_the_reference_settings():
    """config/faust.yaml, shrec16_cuts.yaml, shrec16_holes.yaml and model.py of pvnieo/DPFM."""
    head = make_head("dpfm", preset="reference")
    c = head.config
    assert (c.descriptor, c.descriptor_params, c.mesh_normalization) == ("xyz", {"normalize": False}, "unit_area")
    assert (c.laplacian, c.operators) == ("cotan", "diffusionnet")
    assert (c.n_eig, c.n_fmap, c.width, c.n_blocks, c.dropout) == (128, 50, 128, 4, True)
    assert (c.attention_dim, c.n_heads, c.n_attention_layers, c.sampling_ratio) == (128, 4, 1, 0.7)
    assert (c.head_layout, c.interpolation, c.n_interpolation) == ("interleaved", "reference", 3)
    assert (c.lambda_, c.gamma, c.fmap_features, c.pointmap) == (100.0, 0.5, "extracted", "fmap")
    assert (c.w_fmap, c.w_overlap, c.w_nce, c.single_class_weight) == (1.0, 1.0, 0.0, 0.0)
    assert (c.fmap_ground_truth, c.augmentation, c.overlap_weighted_fmap, c.lr) == ("template_lstsq", True, False, 1e-3)
    cuts = make_head("dpfm", preset="reference_shrec16_cuts").config
    assert cuts.fmap_ground_truth == "projection"
    assert (cuts.mesh_normalization, cuts.n_fmap, cuts.sampling_ratio, cuts.fmap_features, cuts.w_nce) == (
        "unit_area",
        50,
        0.4,
        "extracted",
        0.0,
    )
    holes = make_head("dpfm", preset="reference_shrec16_holes").config
    assert (holes.n_fmap, holes.sampling_ratio, holes.fmap_features, holes.w_nce, holes.nce_pairs) == (
        30,
        0.3,
        "refined",
        1.0,
        512,
    )
    with pytest.raises(HeadError, match="n_interpolation"):
        make_head("dpfm", preset="reference", n_interpolation=4)


def test_interleaved_heads_are_contiguous_heads_with_permuted_channels():
    torch.manual_seed(0)
    dim, heads = 12, 3
    interleaved, contiguous = _MultiHeadAttention(dim, heads, "interleaved"), _MultiHeadAttention(dim, heads, "contiguous")
    # channel c = i * heads + h of the interleaved layout is channel h * (dim / heads) + i of the contiguous one
    perm = torch.arange(dim).reshape(dim // heads, heads).T.reshape(-1)
    with torch.no_grad():
        for name in ("query", "key", "value"):
            getattr(contiguous, name).weight.copy_(getattr(interleaved, name).weight[perm])
            getattr(contiguous, name).bias.copy_(getattr(interleaved, name).bias[perm])
        contiguous.merge.weight.copy_(interleaved.merge.weight[:, perm])
        contiguous.merge.bias.copy_(interleaved.merge.bias)
    x, source = torch.randn(7, dim), torch.randn(9, dim)
    torch.testing.assert_close(interleaved(x, source), contiguous(x, source))


def test_reference_interpolation_reads_candidate_ranks_as_vertices():
    # 6 vertices; samples (the first 3 of the order) are vertices 4, 0, 2
    order = torch.tensor([4, 0, 2, 5, 1])
    ranks = torch.tensor([[1, 0, 3, 2, 4]] * 6)  # ranks 0, 2, 4 name vertices 0, 2, 4: the samples
    sq_dists = torch.tensor([[0.1, 0.2, 0.3, 0.4, 0.5]] * 6)
    interp = reference_sample_interpolation(ReferenceCandidates(order, ranks, sq_dists), 3)
    assert interp.samples.tolist() == [4, 0, 2]
    sampled = torch.tensor([[10.0], [20.0], [40.0]])  # features of vertices 4, 0, 2
    w = 1.0 / (torch.tensor([0.2, 0.4, 0.5]) + 1e-8)  # candidates of ranks 0, 2, 4
    expected = (w * torch.tensor([20.0, 40.0, 10.0])).sum() / w.sum()  # vertices 0, 2, 4
    torch.testing.assert_close(interp.interpolate(sampled)[:, 0], expected.expand(6))
    with pytest.raises(HeadError, match="fewer than 3"):
        reference_sample_interpolation(ReferenceCandidates(order, ranks[:, :3], sq_dists[:, :3]), 3)


def test_release_checkpoint_matches_a_faust_r_pair(release_checkpoints, faust_dir):
    pair = load_dataset("faust_r", root=faust_dir.parent, split="all", pairs=[("tr_reg_081", "tr_reg_080")])[0]
    head = load_head("dpfm", checkpoint=release_checkpoints / "dpfm" / "faust.pth", progress=False)
    match = head.match(pair)
    dist = geodesic_matrix(pair.x, method="dijkstra", normalize=True)
    error = 100 * template_geodesic_errors(match.map_yx, pair.corr_x, pair.corr_y, dist).mean()
    assert error < DPFM_PAIR_BOUND
    assert (
        100
        * template_geodesic_errors(
            np.random.default_rng(0).permutation(pair.x.n_vertices)[: pair.y.n_vertices], pair.corr_x, pair.corr_y, dist
        ).mean()
        > 30
    )
