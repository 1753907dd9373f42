"""GeodesicStore: geodesic matrices on disk by mesh content, checked on every read."""

from __future__ import annotations

import errno
import os

import numpy as np
import pytest
from shapes import bumpy

import geofeat
from geofeat.errors import MeshError
from geofeat.geometry import geodesic_store
from geofeat.geometry.geodesic import geodesic_matrix
from geofeat.geometry.geodesic_store import GeodesicStore


@pytest.fixture
def computations(monkeypatch):
    """Counts the matrices the store computes."""
    calls = []
    original = geodesic_store.geodesic_matrix

    def counting(mesh, *args, **kwargs):
        calls.append(mesh.name)
        return original(mesh, *args, **kwargs)

    monkeypatch.setattr(geodesic_store, "geodesic_matrix", counting)
    return calls


def test_miss_computes_and_stores_then_hit_reads_back(tmp_path, computations):
    store = GeodesicStore(tmp_path / "g")
    mesh = bumpy(0, 2)
    assert store.path(mesh) is None
    first = store.load(mesh)
    path = store.path(mesh)
    assert computations == [mesh.name] and path.parent == tmp_path / "g"
    assert path.name.startswith(f"{mesh.hash}-float32-v{geodesic_store.STORE_VERSION}-") and path.suffix == ".npy"
    again = GeodesicStore(tmp_path / "g").load(mesh)  # a new store (another process) finds the entry
    assert computations == [mesh.name]
    np.testing.assert_array_equal(again, first)
    np.testing.assert_array_equal(again, geodesic_matrix(mesh, normalize=True))  # float32: exactly the matrix
    assert again.dtype == np.float32 and not again.flags.writeable
    assert store.ensure(mesh) == path and computations == [mesh.name]
    assert [p.name for p in (tmp_path / "g").iterdir()] == [path.name]  # no temporary file left


def test_key_is_the_mesh_content_not_its_name(tmp_path, computations):
    store = GeodesicStore(tmp_path)
    mesh = bumpy(0, 2)
    store.load(mesh)
    store.load(mesh.renamed("another name"))
    assert len(computations) == 1
    other = bumpy(1, 2)  # same connectivity, other vertices
    store.load(other)
    assert len(computations) == 2 and store.path(other) != store.path(mesh)
    half = GeodesicStore(tmp_path, dtype="float16")  # another precision is another entry
    half.load(mesh)
    assert len(computations) == 3 and np.load(half.path(mesh)).dtype == np.float16


@pytest.mark.parametrize(
    "damage",
    ["garbage", "truncated", "flipped byte", "wrong shape"],
)
def test_damaged_entry_is_detected_and_recomputed_never_returned(tmp_path, computations, caplog, damage):
    store = GeodesicStore(tmp_path)
    mesh = bumpy(0, 2)
    good = store.load(mesh)
    path = store.path(mesh)
    data = bytearray(path.read_bytes())
    if damage == "garbage":
        path.write_bytes(b"not a numpy file")
    elif damage == "truncated":
        path.write_bytes(bytes(data[: len(data) // 2]))
    elif damage == "flipped byte":  # same size, valid header: only the checksum sees it
        data[-7] ^= 0x10
        path.write_bytes(bytes(data))
    else:
        with open(path, "wb") as handle:
            np.save(handle, np.zeros((3, 3), dtype=np.float32))
    again = store.load(mesh)
    np.testing.assert_array_equal(again, good)
    assert computations == [mesh.name, mesh.name]
    assert "recomputing" in caplog.text and str(path) in caplog.text
    np.testing.assert_array_equal(np.load(store.path(mesh)), good)  # repaired on disk


def test_float16_store_rounds_and_connected_store_refuses_pieces(tmp_path):
    mesh = bumpy(0, 2)
    half = GeodesicStore(tmp_path, dtype="float16").load(mesh)
    np.testing.assert_allclose(half, geodesic_matrix(mesh), rtol=2e-3, atol=1e-4)
    assert half.dtype == np.float32
    two = geofeat.Mesh(
        np.concatenate([mesh.verts, mesh.verts + 10.0]), np.concatenate([mesh.faces, mesh.faces + mesh.n_vertices]), "two"
    )
    assert np.isinf(GeodesicStore(tmp_path).load(two)).any()  # evaluation accepts pieces
    with pytest.raises(MeshError, match="not connected"):
        GeodesicStore(tmp_path / "c", connected=True).load(two)
    with pytest.raises(MeshError, match="float32"):
        GeodesicStore(tmp_path, dtype="float64")


def test_default_folder_follows_the_cache_setting(tmp_path, isolated_cache):
    assert GeodesicStore().folder == isolated_cache / "geodesics"
    geofeat.set_cache_dir(tmp_path / "elsewhere")
    assert GeodesicStore().folder == tmp_path / "elsewhere" / "geodesics"


def test_read_back_is_the_checked_file_mapped_read_only_and_outlives_its_replacement(tmp_path, computations, monkeypatch):
    import os

    store = GeodesicStore(tmp_path)
    mesh = bumpy(0, 2)
    synced = []
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd))
    first = store.load(mesh)
    assert synced == []  # not fsync-ed: a torn entry fails its checksum on read instead
    path = store.path(mesh)
    again = GeodesicStore(tmp_path).load(mesh)
    assert type(again) is np.ndarray and isinstance(again.base, np.memmap)  # no copy of the file
    assert not again.flags.writeable
    with pytest.raises(ValueError):
        again[0, 1] = 1.0
    np.testing.assert_array_equal(again, first)
    path.unlink()  # the store only deletes entries or renames new ones over them: the mapping keeps its pages
    replaced = np.full_like(first, 7.0)
    with open(path, "wb") as handle:
        np.save(handle, replaced)
    np.testing.assert_array_equal(again, first)
    assert computations == [mesh.name]


def test_info_verify_and_clear_see_every_entry_and_leave_other_files(tmp_path):
    import os
    import time

    folder = tmp_path / "g"
    single, half = GeodesicStore(folder), GeodesicStore(folder, dtype="float16")
    meshes = [bumpy(0, 2), bumpy(1, 2)]
    for mesh in meshes:
        single.load(mesh)
    half.load(meshes[0])  # another precision in the same folder: the folder's entries, whatever the store's dtype
    name = single.path(meshes[0]).name
    stale, fresh = folder / f".{name}.x1y2.tmp", folder / f".{name}.z3w4.tmp"  # atomic_write's temporary names
    for tmp in (stale, fresh):
        tmp.write_bytes(b"partial")
    os.utime(stale, (time.time() - 7200, time.time() - 7200))
    (folder / "notes.txt").write_text("mine")
    (folder / ".notes.tmp").write_text("mine too")  # a hidden file of the user's, not a temporary of the store
    info = single.info()
    others = (folder / ".notes.tmp", folder / "notes.txt")
    assert (info.root, info.entries, info.temporary_files, info.other_paths) == (folder, 3, 2, others)
    assert info.bytes == sum(p.stat().st_size for p in single.entries())
    assert single.verify(remove=False) == (3, [])
    damaged = single.path(meshes[1])
    raw = bytearray(damaged.read_bytes())
    raw[-3] ^= 0x10  # one bit of the matrix
    damaged.write_bytes(bytes(raw))
    assert half.verify(remove=False) == (2, [damaged]) and damaged.exists()
    assert half.verify() == (2, [damaged]) and not damaged.exists()
    assert not stale.exists() and fresh.exists()  # only leftovers older than an hour are swept
    assert single.clear() == 2
    assert sorted(p.name for p in folder.iterdir()) == [".notes.tmp", "notes.txt"]


def test_cache_command_manages_both_stores_and_only_the_folders_named(isolated_cache, capsys):
    from geofeat.apps.cli import main as cli_main

    mesh = bumpy(0, 2)
    geofeat.compute(mesh, "hks", n_eig=8, n_descr=4)
    GeodesicStore().load(mesh)
    features, geodesics = isolated_cache / "features", isolated_cache / "geodesics"
    assert cli_main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert f"cache: {features}\nentries: 1\n" in out and f"geodesic store: {geodesics}\nentries: 1\n" in out
    assert cli_main(["cache", "clear", "--dir", str(features)]) == 0  # the feature folder only
    assert capsys.readouterr().out == f"removed 1 entries from {features}\n"
    assert len(GeodesicStore().entries()) == 1
    assert cli_main(["cache", "clear", "--geodesic-dir", str(geodesics)]) == 0
    assert capsys.readouterr().out == f"removed 1 entries from {geodesics}\n" and GeodesicStore().entries() == []
    GeodesicStore().load(mesh)
    geofeat.compute(mesh, "hks", n_eig=8, n_descr=4)
    assert cli_main(["cache", "clear"]) == 0  # both by default
    assert GeodesicStore().entries() == [] and geofeat.FeatureCache().entries() == []


def test_the_store_keeps_under_its_limit_evicting_the_least_recently_used(tmp_path, computations):
    meshes = [bumpy(seed, 2) for seed in range(3)]  # 162 vertices: 105,104 bytes an entry
    store = GeodesicStore(tmp_path, limit=2 * GeodesicStore(tmp_path).entry_bytes(162) + 10)
    store.load(meshes[0])
    store.load(meshes[1])
    os.utime(store.path(meshes[0]), (1, 1))  # an old entry ...
    os.utime(store.path(meshes[1]), (2, 2))
    store.load(meshes[0])  # ... read again: now the most recently used
    store.load(meshes[2])  # no room for three: meshes[1] goes
    assert store.path(meshes[1]) is None and store.path(meshes[0]) and store.path(meshes[2])
    assert store.info().bytes <= store.limit and len(computations) == 3


def test_an_entry_larger_than_the_limit_is_computed_in_memory(tmp_path, caplog, monkeypatch):
    mesh = bumpy(0, 2)
    store = GeodesicStore(tmp_path / "g", limit="100k")
    with caplog.at_level("WARNING", logger="geofeat"):
        dist = store.load(mesh)
    np.testing.assert_array_equal(dist, geodesic_matrix(mesh))
    assert store.entries() == [] and "larger than the store's limit of 102.4 kB" in caplog.text
    assert store.ensure(mesh) is None
    monkeypatch.setenv("GEOFEAT_GEODESIC_STORE_LIMIT", "big")
    with pytest.raises(geofeat.errors.StoreError, match="GEOFEAT_GEODESIC_STORE_LIMIT must be a size"):
        GeodesicStore(tmp_path)


def test_an_unwritable_default_store_warns_once_and_computes_in_memory(tmp_path, monkeypatch, caplog):
    blocker = tmp_path / "a file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("GEOFEAT_CACHE_DIR", str(blocker))
    monkeypatch.setattr(geodesic_store, "_UNWRITABLE_WARNED", set())
    with caplog.at_level("WARNING", logger="geofeat"):
        first = GeodesicStore().load(bumpy(0, 2))
        GeodesicStore().load(bumpy(1, 2))
    np.testing.assert_array_equal(first, geodesic_matrix(bumpy(0, 2)))
    assert caplog.text.count("computed in memory and not kept") == 1 and "cannot be written" in caplog.text
    with pytest.raises(geofeat.errors.StoreError, match="cannot be written"):  # a folder the caller named
        GeodesicStore(blocker / "geodesics").load(bumpy(2, 2))


def test_a_full_disk_gives_a_store_error_or_a_warning(tmp_path, monkeypatch, caplog, computations):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(geodesic_store.np, "save", full)
    monkeypatch.setattr(geodesic_store, "_UNWRITABLE_WARNED", set())
    with pytest.raises(geofeat.errors.StoreError, match="No space left on device"):
        GeodesicStore(tmp_path / "named").load(bumpy(0, 2))
    assert GeodesicStore(tmp_path / "named").temporary_files() == []
    monkeypatch.setattr(geodesic_store, "cache_dir", lambda: tmp_path / "default")
    with caplog.at_level("WARNING", logger="geofeat"):
        dist = GeodesicStore().load(bumpy(0, 2))
    assert dist.shape == (162, 162) and "No space left on device" in caplog.text
