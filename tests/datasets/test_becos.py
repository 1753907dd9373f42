"""BeCoS loader on tiny pair folders written in the generator's output format."""

import pickle

import numpy as np
import pytest

from geofeat.datasets.becos import BeCoS, read_becos_info, read_shape_info
from geofeat.datasets.registry import load_dataset
from geofeat.errors import DatasetError

# shape 0 has 6 vertices, shape 1 has 4; both maps 0-based with -1
MAP_10 = np.array([5, -1, 0, 2])  # vertex of shape 0 for each vertex of shape 1
MAP_01 = np.array([2, -1, 3, -1, -1, 0])  # vertex of shape 1 for each vertex of shape 0


def write_pair(folder, off_writer, map_10=MAP_10, map_01=MAP_01):
    off_writer(folder / "0_tr_reg_000.off", 6)
    off_writer(folder / "1_cat0.off", 4)
    np.save(folder / "corres_10.npy", np.asarray(map_10))
    if map_01 is not None:
        np.save(folder / "corres_01.npy", np.asarray(map_01))


@pytest.fixture
def becos(tmp_path, off_writer):
    root = tmp_path / "BeCoS"
    for setting in ("full_full", "partial_partial"):
        for k in (0, 2, 10):
            write_pair(root / setting / "test" / str(k), off_writer)
    write_pair(root / "partial_full" / "test" / "0", off_writer, map_01=None)  # the generator writes no corres_01 here
    return root


def test_partial_full_pairs_match_shape_1_to_shape_0(becos):
    dataset = load_dataset("becos_p2f", becos)
    assert dataset.protocol == "p2f" and dataset.pair_names == ["0_1_cat0->0_0_tr_reg_000"]
    pair = dataset[0]
    assert pair.x.n_vertices == 6 and pair.y.n_vertices == 4
    np.testing.assert_array_equal(pair.map_yx, MAP_10)
    assert pair.map_yx.dtype == np.int64
    np.testing.assert_array_equal(pair.overlap_y, [True, False, True, True])
    assert pair.overlap_x is None
    with pytest.raises(DatasetError, match="both_directions"):
        BeCoS(becos, setting="partial_full", both_directions=True)


def test_partial_partial_overlaps_come_from_both_maps(becos):
    dataset = load_dataset("becos_p2p", becos.parent)  # the folder holding BeCoS/ is enough
    assert [name.split("_")[0] for name in dataset.pair_names] == ["0", "2", "10"]  # numeric folder order
    pair = dataset[1]
    np.testing.assert_array_equal(pair.map_yx, MAP_10)
    np.testing.assert_array_equal(pair.overlap_y, MAP_10 >= 0)
    np.testing.assert_array_equal(pair.overlap_x, [True, False, True, False, False, True])
    both = BeCoS(becos, setting="partial_partial", both_directions=True)
    assert len(both) == 6 and both.pair_names[1] == "0_0_tr_reg_000->0_1_cat0"
    reverse = both[1]
    np.testing.assert_array_equal(reverse.map_yx, MAP_01)
    np.testing.assert_array_equal(reverse.overlap_x, MAP_10 >= 0)
    assert reverse.x is both[0].y  # each file read once


def test_full_full_has_no_overlap_masks(becos):
    pair = load_dataset("becos_f2f", becos / "full_full" / "test")
    assert pair[0].protocol == "f2f" and pair[0].overlap_x is None and pair[0].overlap_y is None


def test_bad_maps_are_errors(tmp_path, off_writer):
    folder = tmp_path / "partial_full" / "test" / "0"
    write_pair(folder, off_writer, map_10=[6.0, -1.0, 0.0, 2.0], map_01=None)  # 6 = vertex count: 1-based?
    with pytest.raises(DatasetError, match=r"must lie in \[0, 5\]"):
        BeCoS(tmp_path)[0]
    np.save(folder / "corres_10.npy", np.array([5.0, -1.0, 0.0, 2.0]))  # integral floats are fine
    np.testing.assert_array_equal(BeCoS(tmp_path)[0].map_yx, MAP_10)
    np.save(folder / "corres_10.npy", np.zeros((4, 4)))
    with pytest.raises(DatasetError, match="barycentric"):
        BeCoS(tmp_path)[0]
    np.save(folder / "corres_10.npy", np.array([5, -1, 0]))
    with pytest.raises(DatasetError, match="expected 4 entries"):
        BeCoS(tmp_path)[0]
    (folder / "corres_10.npy").unlink()
    with pytest.raises(DatasetError, match="lacks corres_10.npy"):
        BeCoS(tmp_path)


def test_wrong_folder_errors(becos, tmp_path):
    with pytest.raises(DatasetError, match="'partial_full' setting"):
        BeCoS(becos / "partial_full" / "test", setting="partial_partial")
    with pytest.raises(DatasetError, match="'test' split folder"):
        BeCoS(becos / "partial_full" / "test", split="val")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError) as err:
        load_dataset("becos_p2p", empty)
    message = str(err.value)
    assert "Expected layout" in message and "corres_10.npy" in message and "github.com/NafieAmrani/becos-code" in message


# ----------------------------------------------------------------------------- _info.pkl records


def write_info(path, name, *, partial=False, n_vertices=4, protocol=pickle.DEFAULT_PROTOCOL, sqrt_area=2.0):
    """A record with the keys the generator writes (numpy scalars and arrays, as it pickles them)."""
    record = {
        "name": np.str_(name),
        "org_dataset": "tosca",
        "scale_per_dataset": 0.0095,
        "surface_area": np.float64(sqrt_area),
        "random_rotation": np.eye(3),
        "align_rotation": None,
        "align_translation": None,
    }
    if partial:
        record["partial2full"] = np.arange(n_vertices)
        record["cam_pos"] = np.array([0.0, 0.0, 1.0])
    path.write_bytes(pickle.dumps(record, protocol=protocol))
    return record


@pytest.mark.parametrize("protocol", [2, 4, 5])
def test_records_are_read_without_running_code(tmp_path, protocol):
    path = tmp_path / "0_cat0_info.pkl"
    write_info(path, "cat0", partial=True, protocol=protocol)
    record = read_becos_info(path)
    assert record["name"] == "cat0" and float(record["surface_area"]) == 2.0
    np.testing.assert_array_equal(record["partial2full"], np.arange(4))
    info = read_shape_info(path)
    assert info.partial and info.sqrt_area == 2.0 and info.rotation.shape == (3, 3)


class Planted:
    """Any object that is not a builtin or a numpy array: unpickling it imports this module."""

    def __reduce__(self):
        return (print, ("unpickled",))


def test_records_naming_other_objects_are_refused(tmp_path, capsys):
    path = tmp_path / "0_cat0_info.pkl"
    path.write_bytes(pickle.dumps({"name": "cat0", "surface_area": 1.0, "hook": Planted()}))
    with pytest.raises(DatasetError, match=r"refused for safety.*builtins\.print"):
        read_becos_info(path)
    assert "unpickled" not in capsys.readouterr().out
    path.write_bytes(pickle.dumps({"name": "cat0", "surface_area": 1.0})[:-5])  # truncated
    with pytest.raises(DatasetError, match="truncated"):
        read_becos_info(path)
    path.write_bytes(pickle.dumps([1, 2]))
    with pytest.raises(DatasetError, match="expected a dictionary"):
        read_becos_info(path)
    path.write_bytes(pickle.dumps({"name": "cat0"}))
    with pytest.raises(DatasetError, match="no surface_area_after_scaling or surface_area"):
        read_shape_info(path)


def test_released_key_surface_area_after_scaling_is_preferred(tmp_path):
    path = tmp_path / "0_cat0_info.pkl"
    record = write_info(path, "cat0", sqrt_area=2.0)
    path.write_bytes(pickle.dumps({**record, "surface_area_after_scaling": 3.0}))
    assert read_shape_info(path).sqrt_area == 3.0


def test_records_give_partial_full_overlap_and_areas(becos):
    folder = becos / "partial_full" / "test" / "0"
    write_info(folder / "0_tr_reg_000_info.pkl", "tr_reg_000", n_vertices=6, sqrt_area=5.0)
    mask = np.array([True, False, True, False, False, True])
    record = read_becos_info(folder / "0_tr_reg_000_info.pkl")
    (folder / "0_tr_reg_000_info.pkl").write_bytes(pickle.dumps({**record, "overlap_mask": mask}))
    write_info(folder / "1_cat0_info.pkl", "cat0", partial=True, sqrt_area=7.0)
    dataset = load_dataset("becos_p2f", becos)
    np.testing.assert_array_equal(dataset[0].overlap_x, mask)  # shape 0's record, no corres_01 in partial_full
    info = dataset.info(0)
    assert info.sqrt_area_x == 5.0 and info.y.sqrt_area == 7.0 and info.y.partial and not info.x.partial
    assert folder / "1_cat0_info.pkl" in dataset.files_read()


def test_records_that_contradict_the_files_are_errors(becos):
    folder = becos / "partial_full" / "test" / "0"
    write_info(folder / "0_tr_reg_000_info.pkl", "tr_reg_000", partial=True, n_vertices=6)  # shape 0 partial?
    write_info(folder / "1_cat0_info.pkl", "cat0", partial=True)
    with pytest.raises(DatasetError, match="recorded as a partial shape, but in partial_full shape 0 is full"):
        load_dataset("becos_p2f", becos)[0]
    write_info(folder / "0_tr_reg_000_info.pkl", "tr_reg_001")
    with pytest.raises(DatasetError, match="records shape 'tr_reg_001'"):
        load_dataset("becos_p2f", becos)[0]
    write_info(folder / "0_tr_reg_000_info.pkl", "tr_reg_000")
    write_info(folder / "1_cat0_info.pkl", "cat0", partial=True, n_vertices=3)
    with pytest.raises(DatasetError, match="partial2full has 3 entries"):
        load_dataset("becos_p2f", becos)[0]


def test_half_written_pair_folders_are_named(becos):
    split = becos / "partial_partial" / "test"
    for k in (0, 2):
        write_info(split / str(k) / "0_tr_reg_000_info.pkl", "tr_reg_000", partial=True, n_vertices=6)
        write_info(split / str(k) / "1_cat0_info.pkl", "cat0", partial=True)
    # folder 10 has no records: the generator was stopped before it wrote them
    with pytest.raises(
        DatasetError, match=r"1 pair folder\(s\) .* incomplete(.|\n)*10/: lacks 0_tr_reg_000_info.pkl, 1_cat0_info.pkl"
    ):
        load_dataset("becos_p2p", becos)
    (split / "10" / "corres_01.npy").unlink()
    write_info(split / "10" / "0_tr_reg_000_info.pkl", "tr_reg_000", partial=True, n_vertices=6)
    with pytest.raises(DatasetError, match="10/: lacks 1_cat0_info.pkl, corres_01.npy"):
        load_dataset("becos_p2p", becos)
