import multiprocessing as mp
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from cache_writers import N_SHARED_KEYS, shared_key, write_shared_and_own_keys
from shapes import REPO, bumpy

import geofeat
from geofeat import FeatureCache
from geofeat.apps.cli import main as cli_main
from geofeat.descriptors.spectral import WKS


def test_default_location_env_var_and_setting(tmp_path, monkeypatch, isolated_cache):
    assert FeatureCache().root == isolated_cache / "features"
    geofeat.compute(bumpy(), "hks")
    assert len(FeatureCache().entries()) == 1
    geofeat.set_cache_dir(tmp_path / "elsewhere")
    assert FeatureCache().root == tmp_path / "elsewhere" / "features"
    geofeat.set_cache_dir(None)
    monkeypatch.delenv("GEOFEAT_CACHE_DIR")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert geofeat.cache_dir() == tmp_path / "xdg" / "geofeat"


def test_hit_returns_the_stored_array_without_computing(monkeypatch):
    """A hit reads the entry back and never calls the descriptor's compute (counted, not timed)."""
    calls = []
    real_compute = WKS.compute

    def counted_compute(self, mesh):
        calls.append(mesh.name)
        return real_compute(self, mesh)

    monkeypatch.setattr(WKS, "compute", counted_compute)
    mesh = bumpy(0)
    first = geofeat.compute(mesh, "wks")
    assert calls == [mesh.name]  # a miss computes once
    (entry,) = FeatureCache().entries()
    stored = FeatureCache().get(entry.stem)
    assert np.array_equal(stored, first)

    second = geofeat.compute(mesh, "wks")
    assert calls == [mesh.name]  # the hit did not compute
    assert np.array_equal(first, second) and second.dtype == np.float32

    replaced = stored[::-1] * 2  # a valid entry of other content under the same key
    FeatureCache().put(entry.stem, replaced)
    third = geofeat.compute(mesh, "wks")
    assert calls == [mesh.name] and np.array_equal(third, replaced)  # what the store holds, not a recomputation

    geofeat.compute(mesh, "wks", cache=False)
    assert calls == [mesh.name, mesh.name]  # the count does see a computation


def test_key_separates_params_and_meshes():
    mesh = bumpy(0)
    a = geofeat.compute(mesh, "wks", n_descr=16)
    b = geofeat.compute(mesh, "wks", n_descr=17)
    c = geofeat.compute(bumpy(1), "wks", n_descr=16)
    assert a.shape == (mesh.n_vertices, 16) and b.shape[1] == 17
    assert not np.array_equal(a, c)
    assert len(FeatureCache().entries()) == 3


def test_cache_false_writes_nothing(isolated_cache):
    geofeat.compute(bumpy(), "wks", cache=False)
    assert not isolated_cache.exists()


def test_explicit_cache_directory(tmp_path):
    geofeat.compute(bumpy(), "hks", cache=tmp_path / "mine")
    assert len(FeatureCache(tmp_path / "mine").entries()) == 1


def corrupt(path: Path, how: str) -> None:
    if how == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif how == "garbage":
        path.write_bytes(b"not an hdf5 file at all")
    else:  # flip values inside a valid HDF5 file
        with h5py.File(path, "r+") as fh:
            fh["features"][0, 0] += 1.0


@pytest.mark.parametrize("how", ["truncate", "garbage", "values"])
def test_damaged_entry_is_detected_and_recomputed(how, caplog):
    mesh = bumpy(2)
    good = geofeat.compute(mesh, "wks", n_descr=8)
    (entry,) = FeatureCache().entries()
    corrupt(entry, how)
    again = geofeat.compute(mesh, "wks", n_descr=8)
    assert "damaged" in caplog.text
    assert np.array_equal(again, good)
    assert FeatureCache().get(entry.stem) is not None  # rewritten whole


def test_verify_reports_and_removes_damage():
    for seed in range(3):
        geofeat.compute(bumpy(seed), "hks", n_descr=4)
    entries = FeatureCache().entries()
    corrupt(entries[1], "values")
    n_ok, damaged = FeatureCache().verify(remove=False)
    assert (n_ok, damaged) == (2, [entries[1]])
    n_ok, damaged = FeatureCache().verify()
    assert (n_ok, damaged) == (2, [entries[1]])
    assert len(FeatureCache().entries()) == 2 and not entries[1].exists()


def test_several_processes_writing_at_once(tmp_path):
    root = str(tmp_path / "store")
    with mp.get_context("spawn").Pool(4) as pool:
        done = pool.starmap(write_shared_and_own_keys, [(root, w, 25) for w in range(4)])
    assert done == [25] * 4
    store = FeatureCache(root)
    n_ok, damaged = store.verify(remove=False)
    assert (n_ok, damaged) == (N_SHARED_KEYS + 4 * 25, [])
    assert store.temporary_files() == []
    for i in range(N_SHARED_KEYS):
        assert np.all(store.get(shared_key(i)) == i)


def _compute_worker(root: str, seed: int) -> float:
    return float(geofeat.compute(bumpy(seed % 2), "wks", cache=root, n_descr=8).sum())


def test_several_processes_computing_the_same_features(tmp_path):
    root = str(tmp_path / "store")
    with mp.get_context("spawn").Pool(4) as pool:
        sums = pool.starmap(_compute_worker, [(root, s) for s in range(8)])
    assert len({round(v, 4) for v in sums[0::2]}) == 1 and len({round(v, 4) for v in sums[1::2]}) == 1
    assert FeatureCache(root).verify(remove=False) == (2, [])


KILLED_WRITER = textwrap.dedent(
    """
    import sys, time
    import h5py, numpy as np
    from geofeat import FeatureCache

    root, marker = sys.argv[1], sys.argv[2]
    store = FeatureCache(root)
    real = h5py.Group.create_dataset

    def slow_create(self, *args, **kwargs):
        dataset = real(self, *args, **kwargs)
        open(marker, "w").close()  # half-written: tell the test to kill us now
        time.sleep(60)
        return dataset

    h5py.Group.create_dataset = slow_create
    store.put("b" * 64, np.ones((1000, 16), dtype=np.float32))
    """
)


def test_process_killed_mid_write_leaves_store_readable(tmp_path):
    root = tmp_path / "store"
    store = FeatureCache(root)
    kept = np.arange(12, dtype=np.float32).reshape(4, 3)
    store.put("a" * 64, kept)
    marker = tmp_path / "marker"
    script = tmp_path / "writer.py"
    script.write_text(KILLED_WRITER)
    proc = subprocess.Popen([sys.executable, str(script), str(root), str(marker)], cwd=REPO)
    try:
        deadline = time.time() + 60
        while not marker.exists():
            assert proc.poll() is None, "writer exited before reaching the write"
            assert time.time() < deadline, "writer never reached the write"
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    assert store.get("b" * 64) is None  # the entry is simply absent
    assert np.array_equal(store.get("a" * 64), kept)  # what was there survives
    assert len(store.temporary_files()) == 1 and store.info().entries == 1
    assert store.info().other_paths == ()  # the half-written file counts as temporary, nothing else is left
    assert store.verify() == (1, [])


def test_cli_info_verify_clear(tmp_path, capsys):
    root = tmp_path / "clistore"
    geofeat.compute(bumpy(0), "hks", cache=root / "features")
    geofeat.compute(bumpy(1), "hks", cache=root / "features")
    store = FeatureCache(root / "features")
    assert cli_main(["cache", "info", "--dir", str(store.root)]) == 0
    assert "entries: 2" in capsys.readouterr().out
    corrupt(store.entries()[0], "garbage")
    assert cli_main(["cache", "verify", "--keep", "--dir", str(store.root)]) == 1
    assert "1 entries ok, 1 damaged" in capsys.readouterr().out
    assert cli_main(["cache", "verify", "--dir", str(store.root)]) == 0
    assert cli_main(["cache", "clear", "--dir", str(store.root)]) == 0
    assert "removed 1 entries" in capsys.readouterr().out
    assert store.entries() == []


def test_cli_uses_environment_cache(isolated_cache, capsys):
    geofeat.compute(bumpy(0), "hks")
    result = subprocess.run(
        [sys.executable, "-m", "geofeat.apps.cli", "cache", "info"], capture_output=True, text=True, env=os.environ
    )
    assert result.returncode == 0 and f"cache: {isolated_cache / 'features'}" in result.stdout and "entries: 1" in result.stdout
