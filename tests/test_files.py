import pytest

from geofeat.files import atomic_write


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
