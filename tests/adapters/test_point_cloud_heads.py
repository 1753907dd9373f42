"""Every head on point clouds: one training step and a match with a cloud on one side and on both, presets included."""

import logging

import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat.adapters.heads import make_head
from geofeat.adapters.inputs import normalized_mesh, surface_area
from geofeat.datasets.records import ShapePair
from geofeat.errors import HeadError, MeshError
from geofeat.geometry import make_partial

#: Tiny networks: the tests check that clouds go through, not what the heads learn.
SETTINGS = {
    "nn": {},
    "fmap": {"k": 20},
    "ulrssm": dict(width=16, width_out=16, n_blocks=1, n_eig=30, diffusion_eig=30, n_fmap=20, dropout=False, tta_steps=0),
    "dpfm": dict(
        n_eig=30, n_fmap=20, width=16, n_blocks=1, dropout=False, attention_dim=16, n_heads=2, sampling_ratio=0.25, nce_pairs=128
    ),
    "echomatch": dict(
        n_eig=24,
        n_fmap=16,
        feature_channels=16,
        width=16,
        n_blocks=1,
        overlap_width=8,
        overlap_blocks=1,
        n_neighbours=16,
        dropout=0.0,
    ),
}
#: The authors' settings (cotangent Laplacian, unit-area shapes), networks shrunk.
PRESETS = {
    "ulrssm": ("reference", {"descriptor_params": {"n_eig": 30, "n_descr": 16, "laplacian": "cotan", "normalize": True}}),
    "dpfm": ("reference_shrec16_cuts", {"augmentation": False}),
    "echomatch": ("reference", {}),
}


def cloud_of(mesh: geofeat.Mesh) -> geofeat.Mesh:
    return geofeat.Mesh(mesh.verts, None, name=f"{mesh.name}-cloud")


@pytest.fixture(scope="module")
def full() -> geofeat.Mesh:
    return bumpy(0, 3)


@pytest.fixture(scope="module")
def part(full):
    return make_partial(full, "cuts", seed=0)


def p2f_pair(full, part, clouds: str) -> ShapePair:
    """A CUTS pair with the partial shape ``y`` as a cloud (``"y"``) or both shapes as clouds (``"both"``)."""
    x = cloud_of(full) if clouds == "both" else full
    return ShapePair(x=x, y=cloud_of(part.mesh), map_yx=np.asarray(part.vertex_map, dtype=np.int64), protocol="p2f")


def check_trains_and_matches(head, pair: ShapePair) -> None:
    losses = head.fit([pair])
    assert len(losses) == (0 if head.name in ("nn", "fmap") else 1) and np.all(np.isfinite(losses))
    match = head.match(pair)
    assert match.map_yx.shape == (pair.y.n_vertices,)
    assert match.map_yx.min() >= 0 and match.map_yx.max() < pair.x.n_vertices
    assert match.overlap_y.shape == (pair.y.n_vertices,)


@pytest.mark.parametrize("clouds", ["y", "both"])
@pytest.mark.parametrize("name", list(SETTINGS))
def test_head_on_clouds(name, clouds, full, part):
    head = make_head(name, progress=False, epochs=1, **SETTINGS[name])
    check_trains_and_matches(head, p2f_pair(full, part, clouds))


@pytest.mark.parametrize("name", list(PRESETS))
def test_reference_preset_on_clouds(name, full, part):
    preset, extra = PRESETS[name]
    head = make_head(name, preset=preset, progress=False, epochs=1, **(SETTINGS[name] | extra))
    check_trains_and_matches(head, p2f_pair(full, part, "both"))


def test_a_cloud_is_scaled_by_its_laplacians_mass(full):
    cloud = cloud_of(full)
    assert surface_area(cloud) == pytest.approx(full.area(), rel=0.05)
    scaled = normalized_mesh(cloud, "unit_area")
    assert surface_area(scaled) == pytest.approx(1.0, rel=1e-5)
    np.testing.assert_allclose(scaled.verts.mean(axis=0), 0.0, atol=1e-7)


def test_spectral_input_named_cotan_uses_the_cloud_laplacian(full):
    cloud = cloud_of(full)
    head = make_head("nn", descriptor="wks", descriptor_params={"n_eig": 20, "n_descr": 8, "laplacian": "cotan"})
    np.testing.assert_array_equal(head.features(cloud), geofeat.compute(cloud, "wks", n_eig=20, n_descr=8, laplacian="robust"))
    with pytest.raises(MeshError, match="only kind='robust'"):
        geofeat.compute(cloud, "wks", n_eig=20, n_descr=8, laplacian="cotan")  # outside a head, no silent change


# ----------------------------------------------------------------------------- bad clouds


def test_too_small_a_cloud_is_refused(full):
    pair = ShapePair(x=full, y=geofeat.Mesh(full.verts[:25], name="tiny"), map_yx=np.arange(25), protocol="p2f")
    for name in ("nn", "ulrssm"):
        with pytest.raises(MeshError, match="'tiny' has 25 points; .* needs at least 31 points"):
            make_head(name, progress=False, **SETTINGS[name]).match(pair)


def test_coincident_points_match_like_their_first_copy(full, part, caplog):
    copies = np.arange(0, part.mesh.n_vertices, 7)
    y = geofeat.Mesh(np.vstack([part.mesh.verts, part.mesh.verts[copies]]), name="with-copies")
    map_yx = np.concatenate([part.vertex_map, part.vertex_map[copies]]).astype(np.int64)
    pair = ShapePair(x=full, y=y, map_yx=map_yx, protocol="p2f")
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        match = make_head("nn", descriptor="wks", descriptor_params={"n_eig": 20, "n_descr": 8}).match(pair)
    assert f"{len(copies)} point(s) repeat the position of an earlier one" in caplog.text
    np.testing.assert_array_equal(match.map_yx[part.mesh.n_vertices :], match.map_yx[copies])  # the same WKS rows
    check_trains_and_matches(make_head("dpfm", progress=False, epochs=1, **SETTINGS["dpfm"]), pair)


def test_isolated_points_are_matched_with_a_warning(full, part, caplog):
    far = part.mesh.verts.mean(axis=0) + np.array([[8.0, 0.0, 0.0], [8.0, 0.05, 0.0]])
    y = geofeat.Mesh(np.vstack([part.mesh.verts, far]), name="with-outliers")
    pair = ShapePair(x=full, y=y, map_yx=np.concatenate([part.vertex_map, [-1, -1]]).astype(np.int64), protocol="p2f")
    with caplog.at_level(logging.WARNING, logger="geofeat"):
        check_trains_and_matches(make_head("echomatch", progress=False, epochs=1, **SETTINGS["echomatch"]), pair)
    assert "2 isolated point(s)" in caplog.text


def test_a_shape_without_area_is_refused_unit_area():
    line = np.column_stack([np.arange(4.0), np.zeros(4), np.zeros(4)])
    flat = geofeat.Mesh(line, np.array([[0, 1, 2], [1, 2, 3]]), name="degenerate")  # triangles of zero area
    head = make_head("dpfm", preset="reference_shrec16_cuts", progress=False, **SETTINGS["dpfm"])
    with pytest.raises(HeadError, match="'degenerate' has no surface area"):
        head.prepare(ShapePair(x=flat, y=flat, map_yx=np.arange(flat.n_vertices), protocol="f2f"))
