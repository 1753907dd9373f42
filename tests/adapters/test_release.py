"""Release checkpoints of the reference heads: key mapping, refusal of bad files, and the FAUST_r error of ULRSSM's."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from geofeat.adapters.blocks.diffusion_net import DiffusionNet, SpatialGradientFeatures
from geofeat.adapters.heads import load_head, make_head
from geofeat.adapters.inputs import normalized_mesh
from geofeat.adapters.release import check_state, diffusionnet_state
from geofeat.adapters.ulrssm import ULRSSMHead
from geofeat.datasets import load_dataset
from geofeat.errors import HeadError
from geofeat.evaluation.metrics import template_geodesic_errors
from geofeat.geometry.geodesic import geodesic_matrix

#: Measured 2026-11-23 with the ULRSSM reference preset on tr_reg_081 -> tr_reg_080 (template protocol): 1.03.
ULRSSM_PAIR_BOUND = 1.6


def _ulrssm_raw(path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def test_ulrssm_release_maps_every_key_onto_our_diffusionnet(release_checkpoints):
    raw = _ulrssm_raw(release_checkpoints / "ulrssm" / "faust_scape.pth")
    release = ULRSSMHead.release_state(raw)
    assert release.in_channels == 128
    assert release.settings["width"] == 128 and release.settings["width_out"] == 256 and release.settings["n_blocks"] == 4
    assert release.settings["descriptor"] == "wks" and release.settings["descriptor_params"]["n_descr"] == 128
    source = raw["networks"]["feature_extractor"]
    assert len(release.state) == len(source)  # one tensor of ours per tensor of theirs
    torch.testing.assert_close(release.state["blocks.2.mlp.3.weight"], source["blocks.2.mlp.miniMLP_linear_001.weight"])
    torch.testing.assert_close(release.state["blocks.0.diffusion.time"], source["blocks.0.diffusion.diffusion_time"])


def test_renamed_key_is_refused_with_its_name(release_checkpoints, tmp_path):
    raw = _ulrssm_raw(release_checkpoints / "ulrssm" / "faust_scape.pth")
    state = raw["networks"]["feature_extractor"]
    state["blocks.1.mlp.miniMLP_linaer_001.weight"] = state.pop("blocks.1.mlp.miniMLP_linear_001.weight")
    torch.save(raw, tmp_path / "renamed.pth")
    with pytest.raises(HeadError, match=r"blocks\.1\.mlp\.miniMLP_linear_001\.weight"):
        load_head("ulrssm", checkpoint=tmp_path / "renamed.pth")


def test_wrongly_shaped_key_is_refused_with_its_name(release_checkpoints, tmp_path):
    raw = _ulrssm_raw(release_checkpoints / "ulrssm" / "faust_scape.pth")
    state = raw["networks"]["feature_extractor"]
    state["blocks.2.gradient_features.A_im.weight"] = torch.zeros(128, 64)
    torch.save(raw, tmp_path / "shaped.pth")
    with pytest.raises(HeadError, match=r"blocks\.2\.gradient_features\.a_im\.weight: \(128, 64\) instead of \(128, 128\)"):
        load_head("ulrssm", checkpoint=tmp_path / "shaped.pth")


def test_unexpected_key_and_unreadable_files_are_refused(release_checkpoints, tmp_path):
    raw = _ulrssm_raw(release_checkpoints / "ulrssm" / "faust_scape.pth")
    raw["networks"]["feature_extractor"]["blocks.0.extra.weight"] = torch.zeros(3)
    torch.save(raw, tmp_path / "extra.pth")
    with pytest.raises(HeadError, match=r"unexpected key\(s\) \['blocks\.0\.extra\.weight'\]"):
        load_head("ulrssm", checkpoint=tmp_path / "extra.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(HeadError, match="could not read .*junk.pth as a release checkpoint"):
        load_head("ulrssm", checkpoint=tmp_path / "junk.pth")
    with pytest.raises(HeadError, match="does not exist"):
        load_head("ulrssm", checkpoint=tmp_path / "missing.pth")
    with pytest.raises(HeadError, match="cannot load release checkpoints"):
        load_head("fmap", checkpoint=tmp_path / "extra.pth")


def test_check_state_names_missing_keys():
    net = DiffusionNet(4, 2, width=8, n_blocks=1)
    state = net.state_dict()
    del state["last.bias"]
    with pytest.raises(HeadError, match=r"missing \['last\.bias'\]"):
        check_state(net, state, "test")


def test_dpfm_style_keys_map_like_ulrssm_style_keys():
    torch.manual_seed(0)
    ours = DiffusionNet(3, 5, width=8, n_blocks=2, dropout=True)
    spelled = {}
    for key, value in ours.state_dict().items():  # write our weights in the DPFM spelling, then map them back
        key = (
            key.replace("first.", "first_lin.")
            .replace("last.", "last_lin.")
            .replace("diffusion.time", "diffusion.diffusion_time")
        )
        key = key.replace("a_re", "A_re").replace("a_im", "A_im")
        for j in range(3):
            key = key.replace(f"mlp.{3 * j}.", f"mlp.miniMLP_mlp_layer_{j:03d}.")
        parts = key.split(".")
        if parts[0] == "blocks":
            key = f"block_{parts[1]}." + ".".join(parts[2:])
        spelled["feature_extractor." + key] = value
    sizes, state = diffusionnet_state(spelled, "dpfm", prefix="feature_extractor.")
    assert sizes == {
        "in_channels": 3,
        "width": 8,
        "out_channels": 5,
        "n_blocks": 2,
        "mlp_hidden": [8, 8],
        "with_gradient_rotations": True,
    }
    check_state(ours, state, "test")
    for key, value in ours.state_dict().items():
        torch.testing.assert_close(state[key], value)


def test_ulrssm_gradient_mixing_is_the_reference_variant():
    torch.manual_seed(0)
    layer = SpatialGradientFeatures(3, mixing="ulrssm")
    gx, gy = torch.randn(5, 3), torch.randn(5, 3)
    a_re, a_im = layer.a_re.weight, layer.a_im.weight
    expected = torch.tanh(gx * (gx @ a_re.T - gy @ a_im.T) + gy * (gx @ a_re.T + gy @ a_im.T))
    torch.testing.assert_close(layer(gx, gy), expected)
    complex_layer = SpatialGradientFeatures(3, mixing="complex")
    complex_layer.load_state_dict(layer.state_dict())
    assert not torch.allclose(complex_layer(gx, gy), expected)


def test_reference_preset_and_overrides():
    head = make_head("ulrssm", preset="reference", tta_steps=3)
    c = head.config
    assert (c.mesh_normalization, c.operators, c.laplacian, c.n_fmap, c.diffusion_eig, c.gradient_mixing) == (
        "unit_area",
        "ulrssm",
        "cotan",
        200,
        128,
        "ulrssm",
    )
    assert c.descriptor_params == {"n_eig": 128, "n_descr": 128, "laplacian": "cotan", "normalize": True}
    assert c.tta_steps == 3
    with pytest.raises(HeadError, match="no preset 'paper'"):
        make_head("ulrssm", preset="paper")


def test_unit_area_normalisation(faust_mesh):
    mesh = normalized_mesh(faust_mesh, "unit_area")
    assert abs(mesh.area() - 1.0) < 1e-6
    np.testing.assert_allclose(mesh.verts.mean(axis=0), 0.0, atol=1e-6)
    assert mesh.verts.dtype == np.float64 and np.array_equal(mesh.verts, mesh.verts.astype(np.float32))
    assert normalized_mesh(faust_mesh, None) is faust_mesh
    with pytest.raises(HeadError, match="mesh_normalization"):
        normalized_mesh(faust_mesh, "unit_volume")


def test_ulrssm_release_checkpoint_matches_a_faust_r_pair(release_checkpoints, faust_dir):
    pair = load_dataset("faust_r", root=faust_dir.parent, split="all", pairs=[("tr_reg_081", "tr_reg_080")])[0]
    head = load_head("ulrssm", checkpoint=release_checkpoints / "ulrssm" / "faust_scape.pth", progress=False)
    match = head.match(pair)
    dist = geodesic_matrix(pair.x, method="dijkstra", normalize=True)
    error = 100 * template_geodesic_errors(match.map_yx, pair.corr_x, pair.corr_y, dist).mean()
    assert error < ULRSSM_PAIR_BOUND
    assert (
        100
        * template_geodesic_errors(
            np.random.default_rng(0).permutation(pair.x.n_vertices)[: pair.y.n_vertices], pair.corr_x, pair.corr_y, dist
        ).mean()
        > 30
    )


def test_pair_normalisation_keeps_a_partial_in_the_frame_of_its_full_shape(faust_mesh):
    from geofeat.adapters.inputs import normalized_pair
    from geofeat.datasets.records import ShapePair
    from geofeat.geometry import make_partial

    part = make_partial(faust_mesh, "cuts", seed=0)
    map_yx = part.vertex_map.astype(np.int64)
    p2f = normalized_pair(ShapePair(x=faust_mesh, y=part.mesh, map_yx=map_yx, protocol="p2f"), "unit_area")
    np.testing.assert_array_equal(p2f.y.verts, p2f.x.verts[part.vertex_map])  # moved and scaled with x
    assert abs(p2f.x.area() - 1.0) < 1e-6 and p2f.y.area() < 0.95
    p2p = normalized_pair(ShapePair(x=faust_mesh, y=part.mesh, map_yx=map_yx, protocol="p2p"), "unit_area")
    assert abs(p2p.y.area() - 1.0) < 1e-6  # two partial shapes: each by itself
    assert normalized_pair(p2f, None) is p2f
