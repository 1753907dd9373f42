"""`geofeat.storage.entry_folder` through the feature cache: the temporary files of `files.atomic_write` are seen and swept."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest

from geofeat.descriptors.cache import FeatureCache
from geofeat.errors import CacheError, StoreError
from geofeat.geometry.geodesic_store import GeodesicStore
from geofeat.storage.entry_folder import STALE_TMP_SECONDS, array_crc32

KEY = "ab" + "0" * 62


def test_put_writes_through_atomic_write_and_leaves_no_temporary_file(tmp_path, monkeypatch):
    store = FeatureCache(tmp_path)
    replaced = []
    real_replace = os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: replaced.append(os.path.basename(a)) or real_replace(a, b))
    path = store.put(KEY, np.ones((3, 2), dtype=np.float32))
    assert path == tmp_path / "ab" / f"{KEY}.h5"
    assert len(replaced) == 1 and replaced[0].startswith(f".{KEY}.h5.") and replaced[0].endswith(".tmp")
    assert store.temporary_files() == [] and store.info().entries == 1 and store.other_paths() == []


def test_a_failed_put_leaves_nothing_and_keeps_the_old_entry(tmp_path, monkeypatch):
    store = FeatureCache(tmp_path)
    store.put(KEY, np.zeros((2, 2), dtype=np.float32))

    def broken(self, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(h5py.Group, "create_dataset", broken)
    with pytest.raises(CacheError, match="cannot write the cache entry"):
        store.put(KEY, np.ones((2, 2), dtype=np.float32))
    assert sorted(p.name for p in (tmp_path / "ab").iterdir()) == [f"{KEY}.h5"]
    assert np.array_equal(store.get(KEY), np.zeros((2, 2), dtype=np.float32))


def test_leftover_temporary_files_are_counted_and_swept(tmp_path):
    store = FeatureCache(tmp_path)
    store.put(KEY, np.ones((2, 2), dtype=np.float32))
    killed = tmp_path / "ab" / f".{KEY}.h5.k1ll3d.tmp"  # what atomic_write leaves when its process is killed
    older = tmp_path / "ab" / ".tmp-123-abc.h5"  # an older geofeat's temporary file
    running = tmp_path / "ab" / f".{KEY}.h5.wr1t1ng.tmp"
    for path in (killed, older, running):
        path.write_bytes(b"half")
    old = os.path.getmtime(killed) - 2 * STALE_TMP_SECONDS
    os.utime(killed, (old, old))
    os.utime(older, (old, old))
    assert store.temporary_files() == sorted([killed, older, running]) and store.other_paths() == []
    assert store.verify() == (1, [])
    assert store.temporary_files() == [running]  # too recent to belong to no running writer
    assert store.clear() == 1 and store.temporary_files() == []


def test_array_crc32_covers_dtype_shape_and_bytes():
    a = np.arange(6, dtype=np.float32)
    assert array_crc32(a) == array_crc32(a.copy())
    assert len({array_crc32(a), array_crc32(a.reshape(2, 3)), array_crc32(a.astype(np.float64))}) == 3


@pytest.mark.parametrize("store_type", [FeatureCache, GeodesicStore])
def test_a_store_path_that_is_a_file_is_refused_not_reported_empty(tmp_path, store_type):
    path = tmp_path / "a-file"
    path.write_text("not a store")
    store = store_type(path)
    for read in (store.info, store.verify, store.clear, store.entries):
        with pytest.raises(StoreError, match="is a file, not a folder"):
            read()
    assert path.read_text() == "not a store"
    assert store_type(tmp_path / "not-yet").info().entries == 0  # a folder still to be created is an empty store
