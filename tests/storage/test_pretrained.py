"""`geofeat.storage.pretrained`: one folder of config.json + weights.safetensors, written in one piece."""

from __future__ import annotations

import json
import os

import pytest
import torch

from geofeat._version import __version__
from geofeat.errors import HeadError, MissingDependencyError, StoreError
from geofeat.storage import files
from geofeat.storage.pretrained import CONFIG_FILE, WEIGHTS_FILE, Pretrained, from_pretrained, save_pretrained, unread_layout


def _tensors() -> dict[str, torch.Tensor]:
    return {"a.weight": torch.arange(6, dtype=torch.float32).reshape(2, 3), "b.bias": torch.tensor([1, 2], dtype=torch.int64)}


def test_round_trip(tmp_path):
    extra = {"state.txt": lambda path: path.write_text("hello")}
    folder = save_pretrained(
        tmp_path / "m", "toy", {"rank": 4, "targets": ["q"]}, _tensors(), info={"step": 3}, extra_files=extra
    )
    assert folder == tmp_path / "m"
    assert sorted(p.name for p in folder.iterdir()) == [CONFIG_FILE, "state.txt", WEIGHTS_FILE]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]  # no temporary folder left
    envelope = json.loads((folder / CONFIG_FILE).read_text())
    save_id = envelope.pop("save_id")  # the save's token, in the weights' metadata too
    assert envelope == {
        "kind": "toy",
        "format_version": 1,
        "geofeat_version": __version__,
        "has_weights": True,
        "config": {"rank": 4, "targets": ["q"]},
        "info": {"step": 3},
    }
    assert (
        len(save_id) == 32
        and save_id != json.loads((save_pretrained(tmp_path / "n", "toy", {}) / CONFIG_FILE).read_text())["save_id"]
    )
    saved = from_pretrained(folder, "toy", HeadError)
    assert isinstance(saved, Pretrained)
    assert (saved.folder, saved.kind, saved.config, saved.info, saved.geofeat_version) == (
        folder,
        "toy",
        {"rank": 4, "targets": ["q"]},
        {"step": 3},
        __version__,
    )
    assert saved.has_weights()
    loaded = saved.tensors()
    assert sorted(loaded) == ["a.weight", "b.bias"]
    for name, value in _tensors().items():
        assert torch.equal(loaded[name], value) and loaded[name].dtype == value.dtype
    assert (folder / "state.txt").read_text() == "hello"


def test_tensors_are_stored_contiguous_from_views(tmp_path):
    base = torch.arange(12, dtype=torch.float32).reshape(3, 4)
    save_pretrained(tmp_path / "m", "toy", {}, {"t": base.t()})
    assert torch.equal(from_pretrained(tmp_path / "m", "toy", StoreError).tensors()["t"], base.t())


def test_no_tensors_no_weights_file(tmp_path):
    save_pretrained(tmp_path / "m", "toy", {"x": 1})
    saved = from_pretrained(tmp_path / "m", ("other", "toy"), HeadError)
    assert not saved.has_weights()
    with pytest.raises(HeadError, match="holds no weights.safetensors"):
        saved.tensors()


def test_weights_removed_after_a_save_with_weights_fail_the_load(tmp_path):
    folder = save_pretrained(tmp_path / "m", "toy", {"x": 1}, _tensors())
    (folder / WEIGHTS_FILE).unlink()  # a reader between the swap's renames sees the same
    with pytest.raises(HeadError, match="holds no weights.safetensors, though its config.json says it was saved with"):
        from_pretrained(folder, "toy", HeadError)


def test_kind_mismatch_names_both_kinds(tmp_path):
    save_pretrained(tmp_path / "m", "head", {})
    with pytest.raises(HeadError, match=r"holds a 'head', not a 'lora'"):
        from_pretrained(tmp_path / "m", "lora", HeadError)


def test_a_folder_of_a_kind_this_geofeat_does_not_read_says_what_it_holds_and_to_save_again(tmp_path):
    save_pretrained(tmp_path / "m", "lora_adapter", {})
    assert unread_layout(tmp_path / "m") == "a LoRA or trainer checkpoint of kind 'lora_adapter'"
    with pytest.raises(
        HeadError,
        match=r"holds a LoRA or trainer checkpoint of kind 'lora_adapter', a layout this geofeat does not read; expected "
        r"a 'lora' as config.json \+ weights.safetensors written by save_pretrained. Save it again",
    ):
        from_pretrained(tmp_path / "m", "lora", HeadError)
    save_pretrained(tmp_path / "m", "lora", {})
    assert unread_layout(tmp_path / "m") is None


def test_missing_folder_missing_or_damaged_config(tmp_path):
    with pytest.raises(StoreError, match="does not exist"):
        from_pretrained(tmp_path / "nowhere", "toy", StoreError)
    (tmp_path / "empty").mkdir()
    with pytest.raises(StoreError, match="has no config.json"):
        from_pretrained(tmp_path / "empty", "toy", StoreError)
    save_pretrained(tmp_path / "m", "toy", {})
    (tmp_path / "m" / CONFIG_FILE).write_text('{"kind": "to')
    with pytest.raises(StoreError, match="could not read .* as JSON"):
        from_pretrained(tmp_path / "m", "toy", StoreError)
    (tmp_path / "m" / CONFIG_FILE).write_text('{"rank": 4}')
    with pytest.raises(StoreError, match="expected the keys"):
        from_pretrained(tmp_path / "m", "toy", StoreError)


@pytest.mark.parametrize(
    ("files", "found"),
    [
        (("adapter_config.json", "adapter.safetensors"), "a LoRA or trainer checkpoint as adapter_config.json"),
        (("head_config.json", "weights.safetensors"), "a head as head_config.json"),
    ],
)
def test_a_folder_of_another_layout_says_what_it_holds_and_to_save_again(tmp_path, files, found):
    other = tmp_path / "other"
    other.mkdir()
    for name in files:
        (other / name).write_bytes(b"{}")
    assert unread_layout(other).startswith(found)
    with pytest.raises(
        HeadError,
        match=rf"holds {found} .*, a layout this geofeat does not read; expected a 'head' as config.json \+ "
        r"weights.safetensors written by save_pretrained. Save it again with this version of geofeat, into a new folder.",
    ):
        from_pretrained(other, "head", HeadError)
    save_pretrained(tmp_path / "m", "toy", {})
    assert unread_layout(tmp_path / "m") is None and unread_layout(tmp_path) is None


def test_a_later_layout_version_is_refused(tmp_path):
    save_pretrained(tmp_path / "m", "toy", {})
    envelope = json.loads((tmp_path / "m" / CONFIG_FILE).read_text())
    (tmp_path / "m" / CONFIG_FILE).write_text(json.dumps(envelope | {"format_version": 2}))
    with pytest.raises(StoreError, match="layout version 2 .* upgrade geofeat"):
        from_pretrained(tmp_path / "m", "toy", StoreError)


def test_an_existing_pretrained_folder_is_replaced_whole(tmp_path):
    save_pretrained(tmp_path / "m", "toy", {"v": 1}, _tensors(), extra_files={"old.txt": lambda p: p.write_text("x")})
    save_pretrained(tmp_path / "m", "toy", {"v": 2})
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == [CONFIG_FILE]  # the old weights and extra file went
    assert from_pretrained(tmp_path / "m", "toy", StoreError).config == {"v": 2}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]


def test_an_empty_existing_folder_is_used(tmp_path):
    (tmp_path / "m").mkdir()
    save_pretrained(tmp_path / "m", "toy", {"v": 1})
    assert from_pretrained(tmp_path / "m", "toy", StoreError).config == {"v": 1}


def test_a_foreign_folder_or_a_file_is_refused(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(HeadError, match="not written by save_pretrained.*never overwritten"):
        save_pretrained(tmp_path / "mine", "toy", {}, error=HeadError)
    assert sorted(p.name for p in (tmp_path / "mine").iterdir()) == ["notes.txt"]
    (tmp_path / "file").write_text("x")
    with pytest.raises(StoreError, match="is a file"):
        save_pretrained(tmp_path / "file", "toy", {})
    assert (tmp_path / "file").read_text() == "x"


@pytest.mark.parametrize("bad", [{"path": object()}, {"nan": float("nan")}, {1: "int key", "a": 2}])
def test_non_json_config_or_info_is_refused_and_nothing_is_written(tmp_path, bad):
    with pytest.raises(HeadError, match="must hold only JSON values"):
        save_pretrained(tmp_path / "m", "toy", bad, error=HeadError)
    with pytest.raises(HeadError, match="must hold only JSON values"):
        save_pretrained(tmp_path / "m", "toy", {}, info=bad, error=HeadError)
    assert list(tmp_path.iterdir()) == []


def test_bad_tensor_and_extra_file_names_are_refused(tmp_path):
    with pytest.raises(StoreError, match="map names"):
        save_pretrained(tmp_path / "m", "toy", {}, {"a": [1, 2]})
    for name in (CONFIG_FILE, WEIGHTS_FILE, "sub/x.pt", ".."):
        with pytest.raises(StoreError, match="plain file name"):
            save_pretrained(tmp_path / "m", "toy", {}, extra_files={name: lambda p: None})
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("interruption", [RuntimeError, KeyboardInterrupt])
def test_an_interrupted_save_leaves_the_old_folder_and_no_temporary_folder(tmp_path, interruption):
    save_pretrained(tmp_path / "m", "toy", {"v": 1}, _tensors())
    before = {p.name: p.read_bytes() for p in (tmp_path / "m").iterdir()}

    def fail(path):
        path.write_text("half")
        raise interruption("stopped")

    with pytest.raises(interruption):
        save_pretrained(tmp_path / "m", "toy", {"v": 2}, {"x": torch.zeros(2)}, extra_files={"state.pt": fail})
    assert {p.name: p.read_bytes() for p in (tmp_path / "m").iterdir()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]


def test_a_save_killed_between_the_two_renames_is_put_back(tmp_path):
    """A kill between setting the old folder aside and renaming the new one in: the next save or cleanup restores it."""
    save_pretrained(tmp_path / "m", "toy", {"v": 1})
    aside = tmp_path / ".m.old-999999999-0a1b2c3d"  # a process id that does not exist
    os.rename(tmp_path / "m", aside)
    (tmp_path / ".m.tmp-999999999-0a1b2c3d").mkdir()  # its half-written temporary folder
    assert files.remove_dead_temporary_folders(tmp_path) == sorted([aside, tmp_path / ".m.tmp-999999999-0a1b2c3d"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"]
    assert from_pretrained(tmp_path / "m", "toy", StoreError).config == {"v": 1}


def test_damaged_or_missing_weights_raise_the_given_error(tmp_path):
    save_pretrained(tmp_path / "m", "toy", {}, _tensors())
    weights = tmp_path / "m" / WEIGHTS_FILE
    weights.write_bytes(weights.read_bytes()[:40])
    saved = from_pretrained(tmp_path / "m", "toy", HeadError)
    with pytest.raises(HeadError, match="truncated or damaged"):
        saved.tensors()
    weights.write_bytes(b"garbage, not safetensors")
    with pytest.raises(HeadError, match="could not read"):
        saved.tensors()


def test_missing_safetensors_is_named(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "safetensors.torch", None)
    with pytest.raises(MissingDependencyError, match="safetensors"):
        save_pretrained(tmp_path / "m", "toy", {}, _tensors())
    assert list(tmp_path.iterdir()) == []


def test_the_core_module_does_not_import_torch():
    import subprocess
    import sys

    code = "import sys, geofeat.storage.pretrained; print('torch' in sys.modules)"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "False"
