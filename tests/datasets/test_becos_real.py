"""BeCoS loader and checker on files the authors' generator wrote (tests/data/becos_sample, see its README).

The sample holds TOSCA test pairs of the generator's demo: partial_full 11 and 21 (both with
michael0 as the full shape), partial_partial 4 and 10, full_full 0, byte for byte as written.
"""

import pickle
import shutil
import sys
import tarfile
import textwrap
from pathlib import Path

import numpy as np
import pytest

from geofeat.apps.becos_check import _relative_rotation_deg, check_becos
from geofeat.apps.prepare import prepare_becos
from geofeat.datasets.becos import BeCoS, read_becos_info
from geofeat.datasets.registry import load_dataset
from geofeat.mesh import load_mesh

ARCHIVE = Path(__file__).resolve().parents[1] / "data" / "becos_sample" / "becos_sample.tar.xz"


def unpack_sample(target: Path) -> Path:
    if not ARCHIVE.is_file():
        pytest.fail(f"the committed BeCoS sample {ARCHIVE} is missing; restore it from git.", pytrace=False)
    with tarfile.open(ARCHIVE) as tar:
        if hasattr(tarfile, "data_filter"):
            tar.extractall(target, filter="data")
        else:  # pragma: no cover - Pythons without extraction filters
            tar.extractall(target)
    return target


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> Path:
    """The unpacked sample: partial_full/, partial_partial/, full_full/ as in the generator's output/."""
    return unpack_sample(tmp_path_factory.mktemp("becos_sample"))


@pytest.fixture
def copy(sample, tmp_path) -> Path:
    """A copy of the sample to damage."""
    return Path(shutil.copytree(sample, tmp_path / "output"))


def write_off(path: Path, verts: np.ndarray, faces: np.ndarray) -> None:
    lines = ["OFF", f"{len(verts)} {len(faces)} 0"]
    lines += [" ".join(repr(float(v)) for v in row) for row in verts]
    lines += ["3 " + " ".join(str(int(i)) for i in row) for row in faces]
    path.write_text("\n".join(lines) + "\n")


def test_partial_full_pairs_as_the_generator_wrote_them(sample):
    dataset = load_dataset("becos_p2f", root=sample, split="test")
    assert dataset.protocol == "p2f"
    assert dataset.pair_names == ["11_1_victoria21->11_0_michael0", "21_1_victoria24->21_0_michael0"]
    pair, info = dataset[0], dataset.info(0)
    # shape 0 is the full shape (x), shape 1 the partial one (y); corres_10 maps y into x
    assert (pair.x.n_vertices, pair.y.n_vertices) == (9237, 1060)
    assert info.x.name == "michael0" and not info.x.partial and info.y.name == "victoria21" and info.y.partial
    assert info.y.partial2full.shape == (1060,)
    assert pair.map_yx.shape == (1060,) and pair.map_yx.min() >= 0 and pair.map_yx.max() < 9237  # no -1 here
    assert pair.overlap_y.all()
    np.testing.assert_array_equal(pair.overlap_x, info.x.overlap_mask)  # shape 0's record: full-shape vertices seen
    assert pair.overlap_x.sum() == 974
    # areas: the record holds sqrt(area) of the full shapes; the partial shape's own is smaller
    np.testing.assert_allclose(np.sqrt(pair.x.area()), info.sqrt_area_x, rtol=1e-9)
    assert np.sqrt(pair.y.area()) < 0.5 * info.y.sqrt_area
    # orientation: both pairs hold michael0, each randomly rotated; undoing the records' rotations gives one mesh
    other, other_info = dataset[1], dataset.info(1)
    assert not np.allclose(pair.x.verts, other.x.verts, atol=1e-3)
    np.testing.assert_allclose(pair.x.verts @ info.x.rotation.T, other.x.verts @ other_info.x.rotation.T, atol=1e-9)


def test_partial_partial_pairs_and_their_records(sample):
    dataset = load_dataset("becos_p2p", root=sample, split="test")
    assert dataset.pair_names == ["4_1_victoria7->4_0_victoria1", "10_1_victoria17->10_0_victoria21"]
    pair, info = dataset[0], dataset.info(0)
    assert (pair.x.n_vertices, pair.y.n_vertices) == (942, 2327) and info.x.partial and info.y.partial
    assert pair.map_yx.min() == -1 and pair.map_yx.max() < 942 and np.count_nonzero(pair.map_yx < 0) == 1491
    # the generator stores each shape's overlap mask in the OTHER shape's record
    np.testing.assert_array_equal(pair.overlap_y, info.x.overlap_mask)
    np.testing.assert_array_equal(pair.overlap_x, info.y.overlap_mask)
    assert float(info.x.record["overlap_percentage"]) == pytest.approx(pair.overlap_y.mean())
    # the partial target's own sqrt(area) is well below the full shape's, by which BeCoS normalises
    assert 0.3 < np.sqrt(pair.x.area()) / info.sqrt_area_x < 0.5
    assert pair.error_scale == info.sqrt_area_x  # so geodesic errors on x are divided as BeCoS divides them
    both = BeCoS(sample, split="test", setting="partial_partial", both_directions=True)
    reverse = both[1]
    assert reverse.x is both[0].y and reverse.map_yx.shape == (942,)
    np.testing.assert_array_equal(reverse.map_yx, np.load(sample / "partial_partial" / "test" / "4" / "corres_01.npy"))
    assert both.info(1).x.name == "victoria7" and both.info(1).sqrt_area_x == info.y.sqrt_area


def test_full_full_pair_and_its_orientation(sample):
    dataset = load_dataset("becos_f2f", root=sample / "full_full", split="test")
    pair, info = dataset[0], dataset.info(0)
    assert dataset.pair_names == ["0_1_cat6->0_0_cat9"] and pair.overlap_x is None and pair.overlap_y is None
    assert pair.map_yx.min() >= 0 and pair.map_yx.max() < pair.x.n_vertices
    for mesh, record in ((pair.x, info.x), (pair.y, info.y)):
        np.testing.assert_allclose(np.sqrt(mesh.area()), record.sqrt_area, rtol=1e-6)
    # with the recorded random rotations undone, corresponding points line up (the generator aligned the shapes)
    assert _relative_rotation_deg([pair.x, pair.y], [info.x, info.y], pair.map_yx) < 10
    stored = [type("Unrotated", (), {"rotation": np.eye(3)})()] * 2
    assert _relative_rotation_deg([pair.x, pair.y], stored, pair.map_yx) > 90  # as stored: randomly rotated


def test_records_hold_only_builtins_and_numpy(sample):
    record = read_becos_info(sample / "partial_full" / "test" / "11" / "1_victoria21_info.pkl")
    assert sorted(record) == sorted(
        [
            "name",
            "org_dataset",
            "scale_per_dataset",
            "surface_area",
            "random_rotation",
            "align_rotation",
            "align_translation",
            "partial2full",
            "cam_pos",
        ]
    )


def test_check_of_the_sample(sample):
    report = check_becos(sample)
    assert report.ok, report.lines()
    assert report.pair_counts() == {"partial_full": {"test": 2}, "partial_partial": {"test": 2}, "full_full": {"test": 1}}
    p2f = next(s for s in report.splits if s.setting == "partial_full")
    assert p2f.copies == 1 and p2f.unmatched == (0.0, 0.0) and p2f.full_area_error < 1e-9
    assert 0.4 < p2f.partial_area[0] < p2f.partial_area[1] < 0.6
    text = "\n".join(report.lines())
    assert "no pairings.pkl" in text and text.endswith("result: complete; every pair folder is whole and agrees with its records")
    assert check_becos(sample / "partial_partial").pair_counts() == {"partial_partial": {"test": 2}}


def test_check_names_what_is_damaged(copy):
    (copy / "partial_full" / "test" / "21" / "1_victoria24_info.pkl").unlink()  # stopped before the last file
    np.save(copy / "partial_partial" / "test" / "4" / "corres_10.npy", np.full(2327, 942))  # out of range
    info = copy / "full_full" / "test" / "0" / "0_cat9_info.pkl"
    info.write_bytes(info.read_bytes()[:100])  # truncated
    report = check_becos(copy)
    assert not report.ok
    splits = {s.setting: s for s in report.splits}
    assert splits["partial_full"].incomplete == {"21": "lacks 1_victoria24_info.pkl"}
    assert "must lie in [0, 941]" in splits["partial_partial"].incomplete["4"]
    assert "truncated" in splits["full_full"].incomplete["0"]
    assert {s.setting: s.complete for s in report.splits} == {"full_full": 0, "partial_full": 1, "partial_partial": 1}
    text = "\n".join(report.lines())
    assert "21/: lacks 1_victoria24_info.pkl" in text and "result: 3 problem(s)" in text


def test_check_finds_rescaled_and_rotated_meshes(copy):
    folder = copy / "partial_full" / "test"
    shutil.copytree(folder / "21", folder / "22")  # a second copy of pair 21 ...
    mesh = load_mesh(folder / "22" / "0_michael0.off")
    turn = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    write_off(folder / "22" / "0_michael0.off", mesh.verts @ turn, mesh.faces)  # ... rotated after generation
    mesh = load_mesh(folder / "11" / "0_michael0.off")
    write_off(folder / "11" / "0_michael0.off", 2 * mesh.verts, mesh.faces)  # rescaled after generation
    (split,) = check_becos(copy / "partial_full").splits
    assert split.complete == 2 and len(split.problems) == 2
    assert split.problems[0].startswith("11/: 0_michael0.off has sqrt(area) 2.71225")
    assert split.problems[1].startswith("22/: orientation: michael0 does not coincide with its copy in 21/")


def test_check_against_the_drawn_pairs(copy):
    records = {}
    for k in (4, 10):
        folder = copy / "partial_partial" / "test" / str(k)
        records[k] = [read_becos_info(next(folder.glob(f"{side}_*_info.pkl"))) for side in "01"]

    def drawn(record, name=None):
        return {"name": name or str(record["name"]), "org_dataset": "tosca", "random_rot": record["random_rotation"]}

    test = [({"name": f"cat{k}"}, {"name": f"dog{k}"}) for k in range(12)]
    test[4] = (drawn(records[4][0]), drawn(records[4][1]))
    test[10] = (drawn(records[10][0]), drawn(records[10][1], name="victoria99"))
    test[11] = (drawn(records[4][0]), drawn(records[4][1]))
    (copy / "partial_partial" / "pairings.pkl").write_bytes(pickle.dumps([[], test, [({"name": "a"}, {"name": "b"})]]))
    report = check_becos(copy / "partial_partial")
    test_check = next(s for s in report.splits if s.split == "test")
    assert test_check.expected == 12 and test_check.complete == 1
    assert test_check.missing == [0, 1, 2, 3, 5, 6, 7, 8, 9, 11]
    assert test_check.problems == [
        "10/: shape 1 is 'victoria17'; the generator drew 'victoria99' for this pair. The folder belongs to another run "
        "(mixed outputs)."
    ]
    val = next(s for s in report.splits if s.split == "val")
    assert val.missing == [0] and not val.ok  # drawn, never written: the split folder does not even exist
    assert "missing: 10 pair folder(s) never written: 0, 1, 2, 3, 5, 6, 7, 8, 9, 11" in "\n".join(report.lines())


def test_prepare_runs_a_generator_and_checks_real_output(sample, tmp_path):
    """A stand-in main.py that 'generates' by copying the sample's partial_full output, as the generator lays it out."""
    generator = tmp_path / "becos-code"
    (generator / "config").mkdir(parents=True)
    (generator / "config" / "demo_config.yaml").write_text("SEED: 42\nsetting: full_full\n")
    (generator / "main.py").write_text(
        textwrap.dedent(
            f"""\
            import shutil, sys
            assert sys.argv[1:] == ["--config", "demo_config_geofeat_partial_full"], sys.argv
            print("test - 011/22 - Working on: michael0 and victoria21...")
            shutil.copytree({str(sample / "partial_full")!r}, "output/partial_full")
            """
        )
    )
    report = prepare_becos(generator, tmp_path / "BeCoS", python=sys.executable, setting="partial_full")
    assert report.ok, report.lines()
    assert report.output == tmp_path / "BeCoS" / "partial_full"
    assert report.check.pair_counts() == {"partial_full": {"test": 2}}
    assert len(load_dataset("becos_p2f", root=tmp_path / "BeCoS", split="test")) == 2
