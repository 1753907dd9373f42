"""`geofeat extract`: the store, skip-what-exists, the manifest, the export layouts, errors, and 2 torchrun ranks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest
from shapes import bumpy, free_port, write_off

import geofeat
from geofeat.apps.cli import main
from geofeat.apps.extract import ExportSpec, ShapeSource, dataset_shapes, extract, folder_shapes, parse_params
from geofeat.errors import ExtractError
from geofeat.runtime import distributed

PARAMS = ["--param", "n_eig=12", "--param", "n_descr=8"]
KW = {"n_eig": 12, "n_descr": 8}


@pytest.fixture(autouse=True)
def in_tmp_path(tmp_path, monkeypatch):
    """Run in a folder of the test's own, so a file written into the current folder by mistake would be seen."""
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")


@pytest.fixture
def collection(tmp_path) -> Path:
    """Five small seeded meshes (162 vertices), two of them in a sub-folder."""
    root = tmp_path / "meshes"
    for seed in range(3):
        write_off(root / f"shape_{seed}.off", bumpy(seed, subdivisions=2))
    for seed in range(3, 5):
        write_off(root / "more" / f"shape_{seed}.off", bumpy(seed, subdivisions=2))
    return root


def run_cli(*args: str) -> int:
    return main(["extract", "--descriptor", "hks", *PARAMS, "--no-progress", *args])


def expected(path: Path) -> np.ndarray:
    return geofeat.compute(geofeat.load_mesh(path), "hks", cache=False, **KW)


def test_cli_computes_every_shape_then_skips_them_all(collection, tmp_path, capsys):
    store, manifest = tmp_path / "store", tmp_path / "m.json"
    assert run_cli("--data", str(collection), "--out", str(store), "--manifest", str(manifest)) == 0
    assert "5 shapes: 5 computed, 0 already in the store, 0 failed" in capsys.readouterr().out
    first = json.loads(manifest.read_text())
    assert (first["descriptor"], first["params"]["n_eig"], first["world_size"]) == ("hks", 12, 1)
    records = {r["shape"]: r for r in first["shapes"]}
    assert sorted(records) == ["more/shape_3", "more/shape_4", "shape_0", "shape_1", "shape_2"]
    for name, record in records.items():
        mesh = geofeat.load_mesh(collection / f"{name}.off")
        assert record["status"] == "computed" and record["rank"] == 0 and record["seconds"] >= 0
        assert record["mesh_hash"] == mesh.hash and record["path"] == str(collection / f"{name}.off")
        assert record["feature_shape"] == [mesh.n_vertices, 8] and record["n_channels"] == 8
        assert Path(record["entry"]).is_file() and Path(record["entry"]).stem == record["key"]
        np.testing.assert_allclose(geofeat.FeatureCache(store).get(record["key"]), expected(collection / f"{name}.off"))
    assert geofeat.FeatureCache(store).info().entries == 5
    mtimes = {p: p.stat().st_mtime_ns for p in geofeat.FeatureCache(store).entries()}

    assert run_cli("--data", str(collection), "--out", str(store), "--manifest", str(manifest)) == 0
    again = json.loads(manifest.read_text())
    assert (again["n_computed"], again["n_present"]) == (0, 5)
    assert {r["status"] for r in again["shapes"]} == {"present"}
    assert [r["key"] for r in again["shapes"]] == [r["key"] for r in first["shapes"]]
    assert {p: p.stat().st_mtime_ns for p in geofeat.FeatureCache(store).entries()} == mtimes  # nothing rewritten


def test_prefetch_changes_no_record_and_the_throughput_is_reported(collection, tmp_path, capsys):
    manifests = {}
    for prefetch in ("0", "2", None):
        store, manifest = tmp_path / f"store{prefetch}", tmp_path / f"m{prefetch}.json"
        flag = ["--prefetch", prefetch] if prefetch is not None else []
        assert run_cli("--data", str(collection), "--out", str(store), "--manifest", str(manifest), *flag) == 0
        assert "throughput: 5 shapes computed in " in capsys.readouterr().out
        manifests[prefetch] = json.loads(manifest.read_text())
    assert [m["prefetch"] for m in manifests.values()] == [0, 2, 0]  # hks prepares nothing ahead: none by default

    def same(record):
        return {k: v for k, v in record.items() if k not in ("seconds", "entry")}

    assert [same(r) for r in manifests["2"]["shapes"]] == [same(r) for r in manifests["0"]["shapes"]]
    for result in manifests.values():
        assert result["format"] == 1 and result["n_computed"] == 5 and result["wall_seconds"] > 0
        assert result["shapes_per_second"] == pytest.approx(5 / result["wall_seconds"], rel=0.01)  # both rounded
    again = extract(folder_shapes(collection), "hks", KW, store=tmp_path / "store2", prefetch=2, progress=False)
    assert (again["n_present"], again["shapes_per_second"], again["prefetch"]) == (5, None, 2)  # skipped shapes do not count
    assert run_cli("--data", str(collection), "--out", str(tmp_path / "store2"), "--prefetch", "2") == 0
    assert "throughput: no shape computed (" in capsys.readouterr().out
    with pytest.raises(ExtractError, match="prefetch"):
        extract(folder_shapes(collection), "hks", KW, store=tmp_path / "s", prefetch=1.5)


def test_a_rerun_computes_only_what_is_missing(collection, tmp_path):
    store = geofeat.FeatureCache(tmp_path / "store")
    shapes = folder_shapes(collection)
    first = extract(shapes, "hks", KW, store=store, progress=False)
    lost = first["shapes"][2]
    Path(lost["entry"]).unlink()
    again = extract(shapes, "hks", KW, store=store, progress=False)
    computed = [r["shape"] for r in again["shapes"] if r["status"] == "computed"]
    assert computed == [lost["shape"]] and again["n_present"] == 4
    assert store.info().entries == 5


def test_without_out_the_manifest_goes_into_the_feature_cache(collection, tmp_path, isolated_cache, capsys):
    assert run_cli("--data", str(collection)) == 0
    out = capsys.readouterr().out
    store = isolated_cache / "features"
    (manifest,) = store.glob("hks-*.manifest.json")
    assert f"manifest: {manifest}" in out.splitlines() and f"store: {store}" in out.splitlines()
    assert json.loads(manifest.read_text())["store"] == str(store)
    assert list(Path.cwd().iterdir()) == []  # nothing left in the folder the command ran from
    cache = geofeat.FeatureCache(store)
    assert cache.info().entries == 5 and cache.info().other_paths == ()  # the manifest is not a stray file of the store
    assert main(["cache", "verify", "--dir", str(store)]) == 0
    assert "not an entry" not in capsys.readouterr().out and manifest.exists()


def test_with_a_relative_out_the_manifest_goes_there_with_absolute_paths(collection, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative --data, --out and --export-to, as a user types them
    args = ["--data", "meshes", "--out", "store", "--export", "npy", "--export-to", "npy"]
    assert run_cli(*args) == 0
    (manifest,) = (tmp_path / "store").glob("hks-*.manifest.json")
    assert f"manifest: {manifest}" in capsys.readouterr().out.splitlines()
    assert list(tmp_path.glob("*.json")) == []  # none in the folder the command ran from
    monkeypatch.chdir(tmp_path / "cwd")  # read from elsewhere: every path still leads to its file
    content = json.loads(manifest.read_text())
    assert content["store"] == str(tmp_path / "store")
    for record in content["shapes"]:
        for key in ("path", "entry", "export"):
            assert Path(record[key]).is_absolute() and Path(record[key]).is_file(), (key, record[key])
        assert record["path"] == str(collection / f"{record['shape']}.off")
    assert run_cli("--data", str(collection), "--out", str(tmp_path / "store")) == 0  # the same run, named absolutely
    assert list((tmp_path / "store").glob("*.manifest.json")) == [manifest]  # rewrites the same manifest


def test_export_mirror_beside_and_h5_read_back_equal_compute(collection, tmp_path):
    store = str(tmp_path / "store")
    mirror = tmp_path / "mirror"
    assert run_cli("--data", str(collection), "--out", store, "--export", "npy", "--export-to", str(mirror)) == 0
    for name in ("shape_0", "shape_2", "more/shape_4"):
        array = np.load(mirror / f"{name}.npy")
        assert array.dtype == np.float32 and array.flags.c_contiguous
        np.testing.assert_allclose(array, expected(collection / f"{name}.off"), rtol=1e-6)

    assert run_cli("--data", str(collection), "--out", store, "--export", "npy", "--layout", "beside") == 0
    np.testing.assert_allclose(np.load(tmp_path / "hks" / "shape_1.npy"), expected(collection / "shape_1.off"), rtol=1e-6)
    np.testing.assert_allclose(
        np.load(collection / "hks" / "shape_3.npy"), expected(collection / "more" / "shape_3.off"), rtol=1e-6
    )

    h5 = tmp_path / "features.h5"
    assert run_cli("--data", str(collection), "--out", store, "--export", "h5", "--export-to", str(h5)) == 0
    with h5py.File(h5, "r") as fh:
        np.testing.assert_allclose(fh["more/shape_4"][()], expected(collection / "more" / "shape_4.off"), rtol=1e-6)
        assert fh["shape_0"].attrs["descriptor"] == "hks"
        assert json.loads(fh["shape_0"].attrs["params"])["n_eig"] == 12


def test_faust_r_dataset_in_its_folder_layout(faust_dir, tmp_path):
    """--dataset faust_r: shapes named off/<stem>; --layout beside writes <dataset>/<descriptor>/<stem>.npy next to off/."""
    dataset = tmp_path / "FAUST_r"
    for sub, suffix in (("off", ".off"), ("corres", ".vts")):
        (dataset / sub).mkdir(parents=True)
        for stem in ("tr_reg_000", "tr_reg_001"):
            (dataset / sub / f"{stem}{suffix}").symlink_to(faust_dir / sub / f"{stem}{suffix}")
    shapes, folder = dataset_shapes("faust_r", tmp_path, split="all")
    assert [s.name for s in shapes] == ["off/tr_reg_000", "off/tr_reg_001"] and folder == dataset
    args = ["--dataset", "faust_r", "--data-root", str(tmp_path), "--out", str(tmp_path / "store")]
    assert run_cli(*args, "--export", "npy", "--layout", "beside", "--feature-folder", "hks_12") == 0
    got = np.load(dataset / "hks_12" / "tr_reg_001.npy")
    np.testing.assert_allclose(got, expected(faust_dir / "off" / "tr_reg_001.off"), rtol=1e-6)
    assert got.shape == (5000, 8)


def test_param_values_are_json_when_they_parse():
    assert parse_params(["n_eig=12", "scale=0.5", "normalize=false", "laplacian=cotan", "x=[1, 2]"]) == {
        "n_eig": 12,
        "scale": 0.5,
        "normalize": False,
        "laplacian": "cotan",
        "x": [1, 2],
    }
    with pytest.raises(ExtractError, match="KEY=VALUE"):
        parse_params(["n_eig"])
    with pytest.raises(ExtractError, match="twice"):
        parse_params(["n_eig=3", "n_eig=4"])


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--descriptor", "hsk"], "unknown descriptor 'hsk'"),
        (["--descriptor", "hks", "--param", "n_eig=-3"], "n_eig"),
        (["--descriptor", "hks", "--param", "n_eigs=30"], "unknown parameter"),
        (["--descriptor", "hks", "--param", "normalize=yes"], "normalize"),
        (["--descriptor", "hks", "--param", "n_eig"], "KEY=VALUE"),
        (["--descriptor", "hks", "--export", "h5"], "--export-to FILE.h5"),
        (["--descriptor", "hks", "--export-to", "x"], "need --export"),
        (["--descriptor", "hks", "--prefetch", "-1"], "prefetch"),
    ],
)
def test_bad_input_is_a_clear_error(collection, tmp_path, capsys, args, message):
    assert main(["extract", *args, "--data", str(collection), "--out", str(tmp_path / "s"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("geofeat: error:") and message in err
    assert not (tmp_path / "s").exists() or geofeat.FeatureCache(tmp_path / "s").info().entries == 0


def test_missing_and_empty_folders(tmp_path, capsys):
    assert main(["extract", "--descriptor", "hks", "--data", str(tmp_path / "nope")]) == 2
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no meshes here")
    with pytest.raises(ExtractError, match="holds no mesh file"):
        folder_shapes(tmp_path / "empty")
    with pytest.raises(ExtractError, match="in memory"):
        ExportSpec("npy", "beside").check([ShapeSource("blob", mesh=bumpy(0, subdivisions=1))], "hks")


def test_nccl_only_when_every_local_rank_has_its_own_gpu(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert distributed._backend(torch.device("cpu")) == "gloo"
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "1")
    assert distributed._backend(torch.device("cuda", 0)) == "nccl"
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")  # NCCL would refuse: "Duplicate GPU detected" (seen on an H100 machine)
    assert distributed._backend(torch.device("cuda", 0)) == "gloo"


def test_shard_and_rank_environment(monkeypatch, tmp_path):
    for name in distributed.TORCHRUN_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    assert distributed.rank_info() == distributed.RankInfo(0, 1, 0) and not distributed.launched_by_torchrun()
    assert distributed.init_process_group("cpu") is False  # not under torchrun: nothing started
    items = list(range(7))
    parts = [distributed.shard(items, distributed.RankInfo(r, 3, r)) for r in range(3)]
    assert parts == [[0, 3, 6], [1, 4], [2, 5]]
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert distributed.rank_info() == distributed.RankInfo(1, 2, 1) and distributed.world_size() == 2
    assert distributed.local_device("cpu").type == "cpu"
    # WORLD_SIZE without the rendezvous variables: no group, so the work that needs one refuses to take half
    with pytest.raises(distributed.DistributedError, match="WORLD_SIZE=2 is set but no process group"):
        distributed.group_rank_info()
    with pytest.raises(distributed.DistributedError, match="WORLD_SIZE=2 is set but no process group"):
        extract([ShapeSource("blob", mesh=bumpy(0, subdivisions=1))], "hks", {}, store=tmp_path / "s", progress=False)
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(distributed.DistributedError, match="0 <= RANK < WORLD_SIZE"):
        distributed.rank_info()


# ----------------------------------------------------------------------------- torchrun, 2 gloo ranks

LAUNCHER = """
import os, signal, sys
from geofeat.apps.cli import main
from geofeat.descriptors.registry import RegistryEntry, register
from geofeat.descriptors.spectral import HKS


class KilledHKS(HKS):
    '''HKS whose rank 1 dies (SIGKILL) when it reaches the shape named in $KILL_AT.'''

    name = "killed_hks"

    def compute(self, mesh):
        if os.environ.get("RANK") == "1" and mesh.name == os.environ.get("KILL_AT"):
            os.kill(os.getpid(), signal.SIGKILL)
        return super().compute(mesh)


register(RegistryEntry("killed_hks", KilledHKS))
sys.exit(main())
"""


def torchrun(args: list[str], script: Path | None = None, nproc: int = 2, **env) -> subprocess.CompletedProcess:
    target = [str(script)] if script is not None else ["-m", "geofeat"]
    command = [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={nproc}", f"--master_port={free_port()}"]
    environment = {**os.environ, "OMP_NUM_THREADS": "1", **env}
    return subprocess.run(command + target + args, capture_output=True, text=True, env=environment, timeout=120)


def test_two_ranks_give_the_entries_of_one_process_each_computed_once(collection, tmp_path):
    args = ["extract", "--descriptor", "hks", *PARAMS, "--data", str(collection), "--no-progress"]
    two = torchrun([*args, "--out", str(tmp_path / "two"), "--manifest", str(tmp_path / "two.json")])
    assert two.returncode == 0, two.stderr[-3000:]
    assert main([*args, "--out", str(tmp_path / "one"), "--manifest", str(tmp_path / "one.json")]) == 0
    m2, m1 = (json.loads((tmp_path / f"{n}.json").read_text()) for n in ("two", "one"))
    assert m2["world_size"] == 2 and m2["n_computed"] == 5 and m2["n_shapes"] == 5
    assert [r["shape"] for r in m2["shapes"]] == [r["shape"] for r in m1["shapes"]]  # each shape once
    assert [r["rank"] for r in m2["shapes"]] == [0, 1, 0, 1, 0]  # sorted shapes, i % 2
    assert [r["key"] for r in m2["shapes"]] == [r["key"] for r in m1["shapes"]]
    one, two_store = geofeat.FeatureCache(tmp_path / "one"), geofeat.FeatureCache(tmp_path / "two")
    assert [p.name for p in two_store.entries()] == [p.name for p in one.entries()]
    assert two_store.temporary_files() == []
    for record in m1["shapes"]:
        np.testing.assert_allclose(two_store.get(record["key"]), one.get(record["key"]), rtol=1e-5, atol=1e-7)


def test_a_killed_rank_leaves_a_store_that_a_rerun_completes(collection, tmp_path):
    script = tmp_path / "launch.py"
    script.write_text(textwrap.dedent(LAUNCHER))
    store = geofeat.FeatureCache(tmp_path / "store")
    args = ["extract", "--descriptor", "killed_hks", *PARAMS, "--data", str(collection), "--out", str(store.root)]
    args += ["--no-progress", "--manifest", str(tmp_path / "m.json")]
    # sorted: more/shape_3, more/shape_4, shape_0, shape_1, shape_2; rank 1 takes more/shape_4, then dies on shape_1
    shapes = folder_shapes(collection)
    killed = torchrun(args, script, KILL_AT=shapes[3].load().name)
    assert killed.returncode != 0
    assert not (tmp_path / "m.json").exists()  # no manifest from a failed run
    n_ok, damaged = store.verify(remove=False)
    assert damaged == [] and 1 <= n_ok < 5  # complete entries only, some missing
    rerun = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, env={**os.environ})
    assert rerun.returncode == 0, rerun.stderr[-3000:]
    manifest = json.loads((tmp_path / "m.json").read_text())
    assert (manifest["n_present"], manifest["n_computed"]) == (n_ok, 5 - n_ok)
    assert store.verify(remove=False) == (5, [])
    for record in manifest["shapes"]:
        np.testing.assert_allclose(store.get(record["key"]), expected(Path(record["path"])), rtol=1e-6)


def test_writes_that_fail_after_the_checks_are_recorded_and_the_manifest_kept(collection, tmp_path, monkeypatch, capsys):
    """A disk that fills after the up-front checks: each lost export is in the manifest, the HDF5 one too, exit 1."""
    from geofeat.apps import extract as extract_module

    real_save = extract_module.save_npy

    def save_npy(path, features):
        if "shape_1" in str(path):
            raise OSError(28, "No space left on device", str(path))
        return real_save(path, features)

    monkeypatch.setattr(extract_module, "save_npy", save_npy)
    store, manifest, out = tmp_path / "store", tmp_path / "m.json", tmp_path / "npy"
    args = ["--data", str(collection), "--out", str(store), "--manifest", str(manifest)]
    assert run_cli(*args, "--export", "npy", "--layout", "mirror", "--export-to", str(out)) == 1
    printed = capsys.readouterr().out
    assert "export failed: shape_1: could not write" in printed and "No space left on device" in printed
    written = json.loads(manifest.read_text())
    assert written["n_export_failed"] == 1 and written["n_failed"] == 0
    (lost,) = [r for r in written["shapes"] if "export_error" in r]
    assert lost["shape"] == "shape_1" and lost["export"] is None and Path(lost["entry"]).is_file()
    assert sorted(p.name for p in out.rglob("*.npy")) == ["shape_0.npy", "shape_2.npy", "shape_3.npy", "shape_4.npy"]

    def failing_h5(path, records, store):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(extract_module, "write_h5", failing_h5)
    assert run_cli(*args, "--export", "h5", "--export-to", str(tmp_path / "all.h5")) == 1
    assert "export failed: could not write" in capsys.readouterr().out
    written = json.loads(manifest.read_text())
    assert "No space left on device" in written["export_error"] and written["n_present"] == 5
