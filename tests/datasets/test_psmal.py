"""PARTIALSMAL loader on tiny files in the released format (shapes/*.off, maps/<src>_<tgt>.vts, 0-based)."""

import numpy as np
import pytest

from geofeat.datasets.psmal import PartialSmal
from geofeat.datasets.registry import load_dataset
from geofeat.errors import DatasetError

COUGAR, HORSE, HIPPO = "cuts_0_cougar_04", "cuts_14_horse_02", "holes_3_hippo_01"
COUGAR_TO_HORSE = [1, -1, 0, 3, -1]  # cougar: 5 vertices -> horse: 4 vertices
HORSE_TO_COUGAR = [2, 0, -1, 3]


@pytest.fixture
def psmal(tmp_path, off_writer, lines_writer):
    test = tmp_path / "PARTIALSMAL" / "test"
    off_writer(test / "shapes" / f"{COUGAR}.off", 5)
    off_writer(test / "shapes" / f"{HORSE}.off", 4)
    off_writer(test / "shapes" / f"{HIPPO}.off", 3)
    lines_writer(test / "maps" / f"{COUGAR}_{HORSE}.vts", COUGAR_TO_HORSE)
    lines_writer(test / "maps" / f"{HORSE}_{COUGAR}.vts", HORSE_TO_COUGAR)
    lines_writer(test / "maps" / f"{HIPPO}_{HORSE}.vts", [0, -1, 3])  # no reverse file
    return tmp_path / "PARTIALSMAL"


def test_each_map_file_is_one_partial_to_partial_pair(psmal):
    dataset = load_dataset("psmal", psmal)
    assert dataset.protocol == "p2p"
    assert dataset.pair_names == [f"{COUGAR}->{HORSE}", f"{HORSE}->{COUGAR}", f"{HIPPO}->{HORSE}"]
    pair = dataset[0]
    assert pair.y.name == COUGAR and pair.x.name == HORSE
    np.testing.assert_array_equal(pair.map_yx, COUGAR_TO_HORSE)
    assert pair.map_yx.dtype == np.int64
    np.testing.assert_array_equal(pair.overlap_y, [True, False, True, True, False])
    np.testing.assert_array_equal(pair.overlap_x, [True, True, False, True])  # from the reverse file
    np.testing.assert_array_equal(dataset[1].map_yx, HORSE_TO_COUGAR)
    hippo = dataset[2]
    np.testing.assert_array_equal(hippo.map_yx, [0, -1, 3])
    assert hippo.overlap_x is None and hippo.x is pair.x


def test_split_folder_can_be_given_directly(psmal):
    assert len(PartialSmal(psmal / "test")) == 3
    with pytest.raises(DatasetError, match="'test' split folder"):
        PartialSmal(psmal / "test", split="train")


def test_one_based_or_foreign_maps_are_errors(psmal, lines_writer):
    maps = psmal / "test" / "maps"
    lines_writer(maps / f"{COUGAR}_{HORSE}.vts", [2, 4, 1, 4, 3])  # 1-based by mistake: 4 == vertex count
    with pytest.raises(DatasetError, match="looks 1-based"):
        PartialSmal(psmal)[0]
    lines_writer(maps / f"{COUGAR}_{HORSE}.vts", [1, -1, 0, 3])
    with pytest.raises(DatasetError, match="expected 5 entries"):
        PartialSmal(psmal)[0]
    lines_writer(maps / f"{COUGAR}_cuts_9_wolf_01.vts", [0])
    with pytest.raises(DatasetError, match="cannot tell which two shapes"):
        PartialSmal(psmal)


def test_wrong_layout(tmp_path):
    with pytest.raises(DatasetError) as err:
        load_dataset("psmal", tmp_path)
    message = str(err.value)
    assert "no file matches shapes/*.off" in message and "Expected layout" in message
    assert "github.com/vikiehm/gc-ppsm" in message


# ----------------------------------------------------------------------------- the real sample

SAMPLE_PAIRS = [  # (first shape of the map name = y, second = x, vertices of y, vertices of x)
    ("cuts_0_cow_02", "cuts_22_dog_05", 2807, 2676),
    ("cuts_0_cow_04", "cuts_14_lion_04", 2676, 2685),
    ("cuts_0_cow_07", "cuts_6_lion_05", 2954, 2408),
]


def test_real_sample_pairs_names_and_map_direction(psmal_sample):
    """Three real train pairs: names with '_' split at the right place, y = first shape of the file name."""
    dataset = load_dataset("psmal", root=psmal_sample, split="train")
    assert len(dataset) == 3 and dataset.protocol == "p2p"
    assert dataset.pair_names == [f"{y}->{x}" for y, x, _, _ in SAMPLE_PAIRS]
    for (y_name, x_name, n_y, n_x), pair in zip(SAMPLE_PAIRS, dataset, strict=True):
        assert (pair.y.name, pair.x.name) == (y_name, x_name)
        assert (pair.y.n_vertices, pair.x.n_vertices) == (n_y, n_x)
        stored = np.loadtxt(psmal_sample / "train" / "maps" / f"{y_name}_{x_name}.vts", dtype=np.int64)
        np.testing.assert_array_equal(pair.map_yx, stored)  # 0-based as stored, no shift
        assert pair.map_yx.shape == (n_y,) and pair.map_yx.dtype == np.int64  # one entry per vertex of y
        assert pair.map_yx.min() == -1 and pair.map_yx.max() < n_x  # -1 = none; the rest index x
        assert 0 < (pair.map_yx == -1).mean() < 0.8
        np.testing.assert_array_equal(pair.overlap_y, pair.map_yx >= 0)
        assert pair.overlap_x is None  # the sample holds one direction only


def test_real_sample_with_both_directions_as_released(psmal_sample, tmp_path, lines_writer):
    """The released benchmark holds each map in both directions: each file is a pair, and overlap_x comes from the reverse."""
    import shutil

    folder = tmp_path / "PARTIALSMAL" / "train"
    shutil.copytree(psmal_sample / "train", folder)
    y_name, x_name, n_y, n_x = SAMPLE_PAIRS[0]
    forward = np.loadtxt(folder / "maps" / f"{y_name}_{x_name}.vts", dtype=np.int64)
    reverse = np.full(n_x, -1)
    kept = np.flatnonzero(forward >= 0)
    reverse[forward[kept][::-1]] = kept[::-1]  # a vertex of x -> the first vertex of y mapped onto it
    lines_writer(folder / "maps" / f"{x_name}_{y_name}.vts", reverse)
    dataset = load_dataset("psmal", root=tmp_path, split="train")
    assert len(dataset) == 4
    there, back = (dataset[dataset.pair_names.index(name)] for name in (f"{y_name}->{x_name}", f"{x_name}->{y_name}"))
    np.testing.assert_array_equal(there.overlap_x, reverse >= 0)
    np.testing.assert_array_equal(back.map_yx, reverse)
    np.testing.assert_array_equal(back.overlap_x, forward >= 0)
    assert back.y is there.x and back.x is there.y  # one mesh per shape file
