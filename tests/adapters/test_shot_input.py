"""ULRSSM, DPFM and EchoMatch with SHOT as their input: one small training step and a match."""

import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat.adapters.dpfm import DPFMHead
from geofeat.adapters.echomatch.head import EchoMatchHead
from geofeat.adapters.ulrssm import ULRSSMHead
from geofeat.datasets.records import ShapePair
from geofeat.geometry import make_partial

#: SHOT on the unit-scale test blobs: the radius is a share of sqrt(area) (about 0.35 on a whole blob).
SHOT_INPUT = {"descriptor": "shot", "descriptor_params": {"radius": 0.1, "radius_unit": "sqrt_area"}}


@pytest.fixture(scope="module")
def full_pair() -> ShapePair:
    x = bumpy(0, 3)
    y = geofeat.Mesh(x.verts * np.array([1.1, 0.95, 1.0]), x.faces, name="bumpy0-stretched")
    return ShapePair(x=x, y=y, map_yx=np.arange(y.n_vertices), protocol="f2f")


@pytest.fixture(scope="module")
def partial_pair() -> ShapePair:
    mesh = bumpy(0, 3)
    part = make_partial(mesh, "cuts", seed=0)
    return ShapePair(x=mesh, y=part.mesh, map_yx=np.asarray(part.vertex_map, dtype=np.int64), protocol="p2f")


@pytest.fixture(scope="module")
def p2p_pair() -> ShapePair:
    mesh = bumpy(0, 3)
    part_x = make_partial(mesh, "cuts", seed=3, keep_range=(0.4, 0.65))
    part_y = make_partial(mesh, "cuts", seed=4, keep_range=(0.4, 0.65))
    vx, vy = part_x.vertex_map, part_y.vertex_map
    pos_yx = np.clip(np.searchsorted(vx, vy), 0, len(vx) - 1)
    map_yx = np.where(vx[pos_yx] == vy, pos_yx, -1).astype(np.int64)
    pos_xy = np.clip(np.searchsorted(vy, vx), 0, len(vy) - 1)
    map_xy = np.where(vy[pos_xy] == vx, pos_xy, -1).astype(np.int64)
    return ShapePair(part_x.mesh, part_y.mesh, map_yx, map_xy >= 0, map_yx >= 0, protocol="p2p")


def _check(head, pair: ShapePair) -> None:
    assert head.features(pair.x).shape == (pair.x.n_vertices, 192)
    losses = head.fit([pair])
    assert len(losses) == 1 and np.all(np.isfinite(losses))
    match = head.match(pair)
    assert match.map_yx.shape == (pair.y.n_vertices,)
    assert match.map_yx.min() >= 0 and match.map_yx.max() < pair.x.n_vertices


def test_ulrssm_trains_and_matches_on_shot(full_pair):
    head = ULRSSMHead(
        **SHOT_INPUT,
        width=16,
        width_out=16,
        n_blocks=1,
        n_eig=30,
        diffusion_eig=30,
        n_fmap=20,
        dropout=False,
        tta_steps=0,
        progress=False,
        epochs=1,
    )
    _check(head, full_pair)


def test_dpfm_trains_and_matches_on_shot(partial_pair):
    head = DPFMHead(
        **SHOT_INPUT,
        n_eig=30,
        n_fmap=20,
        width=16,
        n_blocks=1,
        dropout=False,
        attention_dim=16,
        n_heads=2,
        sampling_ratio=0.25,
        nce_pairs=128,
        progress=False,
        epochs=1,
    )
    _check(head, partial_pair)


def test_echomatch_trains_and_matches_on_shot(p2p_pair):
    head = EchoMatchHead(
        **SHOT_INPUT,
        n_eig=24,
        n_fmap=16,
        feature_channels=16,
        width=16,
        n_blocks=1,
        overlap_width=8,
        overlap_blocks=1,
        n_neighbours=16,
        dropout=0.0,
        progress=False,
        epochs=1,
    )
    _check(head, p2p_pair)
