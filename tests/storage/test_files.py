import os
import threading

import pytest

from geofeat.storage.files import atomic_folder, atomic_write, remove_dead_temporary_folders


def test_atomic_write_replaces_and_a_failure_keeps_the_old_file(tmp_path):
    target = tmp_path / "sub" / "a.txt"
    assert atomic_write(target, lambda tmp: tmp.write_text("one")) == target
    assert target.read_text() == "one"

    def fail(tmp):
        tmp.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(target, fail)
    assert target.read_text() == "one"
    assert sorted(p.name for p in target.parent.iterdir()) == ["a.txt"]  # no temporary file left


@pytest.mark.parametrize("durable", [True, False])
def test_atomic_write_syncs_only_when_durable(tmp_path, monkeypatch, durable):
    import os

    synced = []
    real_fsync = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd) or real_fsync(fd))
    target = tmp_path / "b.bin"
    atomic_write(target, lambda tmp: tmp.write_bytes(b"\x00\x01"), durable=durable)
    assert target.read_bytes() == b"\x00\x01"
    assert len(synced) == (2 if durable else 0)  # the file before the rename, the folder after it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.bin"]


def _write_files(**content):
    def write(folder):
        for name, text in content.items():
            (folder / name).write_text(text)

    return write


def test_atomic_folder_writes_and_replaces_whole(tmp_path):
    target = tmp_path / "sub" / "model"
    assert atomic_folder(target, _write_files(a="1", b="2")) == target
    assert {p.name: p.read_text() for p in target.iterdir()} == {"a": "1", "b": "2"}
    atomic_folder(target, _write_files(a="3"))
    assert {p.name: p.read_text() for p in target.iterdir()} == {"a": "3"}  # b of the old folder went with it
    assert sorted(p.name for p in target.parent.iterdir()) == ["model"]


def test_atomic_folder_interrupted_keeps_the_old_folder(tmp_path):
    target = tmp_path / "model"
    atomic_folder(target, _write_files(a="1"))

    def fail(folder):
        (folder / "a").write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_folder(target, fail)
    assert {p.name: p.read_text() for p in target.iterdir()} == {"a": "1"}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model"]


def test_atomic_folder_syncs_the_files_before_the_rename(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: events.append("fsync") or real_fsync(fd))
    monkeypatch.setattr(os, "replace", lambda a, b: events.append("replace") or real_replace(a, b))
    atomic_folder(tmp_path / "m", _write_files(a="1", b="2"))
    # two files and the temporary folder, the rename, then the parent folder
    assert events == ["fsync", "fsync", "fsync", "replace", "fsync"]
    events.clear()
    atomic_folder(tmp_path / "n", _write_files(a="1"), durable=False)
    assert events == ["replace"]


def test_dead_leftovers_are_removed_or_restored_and_live_ones_kept(tmp_path):
    dead, alive = 999_999_999, os.getppid()  # no such process; the parent of this one
    (tmp_path / "kept").mkdir()
    leftovers = {
        f".kept.tmp-{dead}-00aa": "removed",  # a killed write
        f".kept.old-{dead}-00bb": "removed",  # set aside, and the new folder is in place
        f".gone.old-{dead}-00cc": "restored",  # set aside, killed before the new folder was renamed in
        f".step_0000002.tmp-{dead}": "kept",  # no token: not a name atomic_folder writes
        f".kept.tmp-{alive}-00dd": "kept",  # a process still writing
        f".kept.tmp-{os.getpid()}-00ee": "removed",  # this process's id, but no save of it under way: an earlier process's
        "other": "kept",
    }
    for name in leftovers:
        (tmp_path / name).mkdir()
    (tmp_path / f".gone.old-{dead}-00cc" / "a").write_text("old")
    assert remove_dead_temporary_folders(tmp_path, "kept") == sorted(
        tmp_path / n for n in (f".kept.tmp-{dead}-00aa", f".kept.old-{dead}-00bb", f".kept.tmp-{os.getpid()}-00ee")
    )
    removed = remove_dead_temporary_folders(tmp_path)
    assert removed == [tmp_path / f".gone.old-{dead}-00cc"]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ["kept", "gone", f".kept.tmp-{alive}-00dd", f".step_0000002.tmp-{dead}", "other"]
    )
    assert (tmp_path / "gone" / "a").read_text() == "old"
    assert remove_dead_temporary_folders(tmp_path / "missing") == []


def test_a_save_under_way_in_another_thread_is_not_a_leftover(tmp_path):
    started, release = threading.Event(), threading.Event()

    def slow(folder):
        (folder / "a").write_text("1")
        started.set()
        release.wait(30)

    worker = threading.Thread(target=atomic_folder, args=(tmp_path / "m", slow))
    worker.start()
    try:
        assert started.wait(30)
        assert remove_dead_temporary_folders(tmp_path) == []
    finally:
        release.set()
        worker.join(30)
    assert (tmp_path / "m" / "a").read_text() == "1"
