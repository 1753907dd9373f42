"""CP2P24 loader on tiny files in the .map format (|V_y| 0-based map entries, then |V_x| overlap flags)."""

import numpy as np
import pytest

from geofeat.datasets.cp2p24 import CP2P24
from geofeat.datasets.registry import load_dataset
from geofeat.errors import DatasetError

MAP_12 = [3, -1, 0, 0, 2]  # cat-01 (5 vertices) -> cat-02 (4 vertices)
FLAGS_2 = [1, 0, 1, 1]  # overlap flags of cat-02 (vertex 1 overlaps nothing; vertex 3 does, though not hit)
MAP_21 = [2, -1, 4, 0]  # cat-02 -> cat-01
FLAGS_1 = [1, 0, 1, 0, 1]  # overlap flags of cat-01: they differ from MAP_12 >= 0 on purpose


@pytest.fixture
def cp2p(tmp_path, off_writer, lines_writer):
    test = tmp_path / "CP2P24" / "test"
    off_writer(test / "off" / "cat-01.off", 5)
    off_writer(test / "off" / "cat-02.off", 4)
    off_writer(test / "off" / "dog-01.off", 3)
    lines_writer(test / "maps" / "cat-01_cat-02.map", MAP_12 + FLAGS_2)
    lines_writer(test / "maps" / "cat-02_cat-01.map", MAP_21 + FLAGS_1)
    lines_writer(test / "maps" / "dog-01_cat-02.map", [1, -1, 3, 0, 1, 0, 1])  # no reverse file
    return tmp_path


def test_map_and_overlap_flags(cp2p):
    dataset = load_dataset("cp2p24", cp2p)  # the folder holding CP2P24/ is enough
    assert dataset.protocol == "p2p"
    assert dataset.pair_names == ["cat-01->cat-02", "cat-02->cat-01", "dog-01->cat-02"]
    pair = dataset[0]
    np.testing.assert_array_equal(pair.map_yx, MAP_12)
    assert pair.map_yx.dtype == np.int64
    np.testing.assert_array_equal(pair.overlap_x, np.array(FLAGS_2, dtype=bool))
    np.testing.assert_array_equal(pair.overlap_y, np.array(FLAGS_1, dtype=bool))  # flags of the reverse file
    np.testing.assert_array_equal(dataset[1].map_yx, MAP_21)
    dog = dataset[2]
    np.testing.assert_array_equal(dog.map_yx, [1, -1, 3])
    np.testing.assert_array_equal(dog.overlap_x, [False, True, False, True])
    np.testing.assert_array_equal(dog.overlap_y, [True, False, True])  # no reverse file: from the map


def test_map_without_flags_reads_as_dpfm_style(cp2p, lines_writer):
    lines_writer(cp2p / "CP2P24" / "test" / "maps" / "dog-01_cat-02.map", [1, -1, 3])
    pair = CP2P24(cp2p)[2]
    np.testing.assert_array_equal(pair.map_yx, [1, -1, 3])
    assert pair.overlap_x is None


def test_malformed_map_files(cp2p, lines_writer):
    path = cp2p / "CP2P24" / "test" / "maps" / "dog-01_cat-02.map"
    lines_writer(path, [1, -1, 3, 0, 1, 0])
    with pytest.raises(DatasetError, match=r"expected 3 \+ 4 = 7 integers"):
        CP2P24(cp2p)[2]
    lines_writer(path, [1, -1, 3, 0, 2, 0, 1])
    with pytest.raises(DatasetError, match="0/1 flags"):
        CP2P24(cp2p)[2]
    lines_writer(path, [1, -1, 4, 0, 1, 0, 1])
    with pytest.raises(DatasetError, match=r"must lie in \[0, 3\]"):
        CP2P24(cp2p)[2]


def test_wrong_layout(tmp_path):
    (tmp_path / "off").mkdir()
    with pytest.raises(DatasetError) as err:
        load_dataset("cp2p24", tmp_path, split="train")
    message = str(err.value)
    assert "no file matches maps/*.map" in message and "Expected layout" in message
    assert "github.com/vikiehm/echo-match" in message
