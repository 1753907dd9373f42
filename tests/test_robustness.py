"""Robustness table: odd, bad or hostile inputs and what each must give.

Every row is one input and its expected outcome: an error type (a `GeofeatError`, with a
message that says what was expected and how to fix it; or argparse's exit) or equality with
a reference result computed the ordinary way. Rows cover bad mesh files, parameters at the
boundary, non-finite features, read-only and odd cache stores, small point clouds, mesh-like
inputs, damaged and pickle-only weights, concurrent cache writers and killed training runs (a cache
writer killed in the middle of an entry: tests/descriptors/test_cache.py), and faults that would
otherwise go unnoticed: features of a mesh no view sees, or moved far from the origin; loads
racing a save; resumes on changed data; Ctrl-C and kill -9 reaching worker processes; command
lines that must end in one line, not a traceback; messages that must give the right advice.

A read-only store is simulated (`read_only`): every call that would create, rename or delete
something below the store raises ``OSError(EROFS)``, as a read-only mount does.
"""

from __future__ import annotations

import csv
import errno
import json
import logging
import multiprocessing as mp
import os
import re
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
import torch
import trimesh
from cache_writers import N_SHARED_KEYS, write_shared_and_own_keys
from shapes import REPO, bumpy, sphere

import geofeat
import geofeat.storage.pretrained
from geofeat import FeatureCache, Mesh
from geofeat.apps.cli import main as cli_main
from geofeat.backbones import load_backbone
from geofeat.checks import canonical, check_boolean, check_integer, check_number
from geofeat.descriptors import registry
from geofeat.descriptors.base import Descriptor
from geofeat.errors import BackboneError, CacheError, DescriptorError, GeofeatError, MeshError, TrainingError
from geofeat.geometry.geodesic_store import GeodesicStore

TESTS = Path(__file__).resolve().parent


@dataclass
class Ctx:
    """What a row's action gets: a fresh folder, pytest's monkeypatch and log capture, the isolated cache."""

    tmp: Path
    monkeypatch: pytest.MonkeyPatch
    caplog: pytest.LogCaptureFixture
    cache: Path


@dataclass(frozen=True)
class Row:
    """One input and its expected outcome.

    ``run(ctx)`` is the input. Either it raises ``raises`` (message matching ``match``), or it
    returns a result equal to ``reference(ctx)`` (arrays: exactly; None: no reference). ``check``
    then looks at the error or result and the side effects (cache entries, log, files).
    """

    id: str
    run: Callable[[Ctx], Any]
    raises: type[BaseException] | None = None
    match: str | None = None
    reference: Callable[[Ctx], Any] | None = None
    check: Callable[[Ctx, Any], None] | None = None


@dataclass(frozen=True)
class Close:
    """A reference that is met to a relative tolerance (training losses: float32 sums in another order)."""

    values: list[float]
    rtol: float = 1e-5


def assert_same(result, expected) -> None:
    if isinstance(expected, Close):
        np.testing.assert_allclose(result, expected.values, rtol=expected.rtol)
    elif isinstance(expected, np.ndarray):
        assert isinstance(result, np.ndarray) and result.dtype == expected.dtype
        np.testing.assert_array_equal(result, expected)
    elif isinstance(expected, (list, tuple)) and expected and isinstance(expected[0], np.ndarray):
        assert len(result) == len(expected)
        for a, b in zip(result, expected, strict=True):
            assert_same(a, b)
    else:
        assert result == expected


# ----------------------------------------------------------------------------- helpers


def read_only(ctx: Ctx, root: Path) -> None:
    """Make every write below ``root`` fail with EROFS, as on a read-only mount (reads still work)."""
    root = Path(root).resolve()

    def inside(path) -> bool:
        try:
            return Path(os.fspath(path)).resolve().is_relative_to(root)
        except (TypeError, ValueError):
            return False

    def refuse(path):
        raise OSError(errno.EROFS, "Read-only file system", os.fspath(path))

    def guard(real, n_paths=1):
        def wrapped(*args, **kwargs):
            if any(inside(a) for a in args[:n_paths]):
                refuse(args[0])
            return real(*args, **kwargs)

        return wrapped

    write_flags = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_TRUNC | os.O_APPEND
    real_open = os.open

    def os_open(path, flags, *args, **kwargs):
        if flags & write_flags and inside(path):
            refuse(path)
        return real_open(path, flags, *args, **kwargs)

    patch = ctx.monkeypatch
    patch.setattr(os, "open", os_open)
    for name in ("mkdir", "unlink", "remove", "rmdir"):
        patch.setattr(os, name, guard(getattr(os, name)))
    for name in ("replace", "rename"):
        patch.setattr(os, name, guard(getattr(os, name), n_paths=2))
    real_file = h5py.File

    def h5_file(name, mode="r", *args, **kwargs):
        if mode != "r" and inside(name):
            refuse(name)
        return real_file(name, mode, *args, **kwargs)

    patch.setattr(h5py, "File", h5_file)  # the cache imports h5py on first use: patch the module itself


def store_with_entries(ctx: Ctx, n: int = 2) -> FeatureCache:
    store = FeatureCache(ctx.tmp / "store")
    for seed in range(n):
        geofeat.compute(bumpy(seed, 2), "hks", cache=store, n_eig=8, n_descr=4)
    assert len(store.entries()) == n
    return store


def cli(args: list[str]) -> tuple[int, str, str]:
    """Run ``geofeat`` in this process; returns (exit code, stdout, stderr)."""
    import contextlib
    import io

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli_main(args)
    return code, out.getvalue(), err.getvalue()


def write_off(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


TRIANGLE = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TETRA_FACES = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]])


def truncated_ply(ctx: Ctx) -> Path:
    data = trimesh.exchange.ply.export_ply(trimesh.Trimesh(TRIANGLE, TETRA_FACES, process=False))
    (ctx.tmp / "t.ply").write_bytes(data[:-20])
    return ctx.tmp / "t.ply"


def tetra_off() -> str:
    rows = [" ".join(map(str, v)) for v in TRIANGLE]
    return "OFF\n4 4 0\n" + "\n".join(rows) + "\n" + "\n".join("3 " + " ".join(map(str, f)) for f in TETRA_FACES) + "\n"


class NaNDescriptor(Descriptor):
    """A descriptor whose output is NaN on half the vertices (a stand-in for a numerical failure)."""

    name = "nan_for_tests"

    def __init__(self, *, dim: int = 3):
        self.dim = dim

    def compute(self, mesh: Mesh) -> np.ndarray:
        out = np.ones((mesh.n_vertices, self.dim))
        out[::2] = np.nan
        return out


def register_nan_descriptor(ctx: Ctx) -> None:
    ctx.monkeypatch.setattr(registry, "_REGISTRY", registry._REGISTRY.copy())
    registry.register(registry.RegistryEntry("nan_for_tests", "test_robustness:NaNDescriptor"))


def no_entries(ctx: Ctx, _=None) -> None:
    assert FeatureCache().entries() == [] and FeatureCache(ctx.tmp / "store").entries() == []


# ---- backbones and pickles


def tiny_folder(ctx: Ctx) -> Path:
    from tiny_models import tiny_dinov3

    folder = ctx.tmp / "v3"
    tiny_dinov3().save_pretrained(folder)
    return folder


def truncated_safetensors(ctx: Ctx) -> Path:
    folder = tiny_folder(ctx)
    weights = folder / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(data[: len(data) // 2])
    return folder


class Planted:
    """Unpickling this (weights_only=False) would create a marker file: proof that a pickle ran code."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def pickle_only_folder(ctx: Ctx) -> Path:
    from safetensors.torch import load_file

    folder = tiny_folder(ctx)
    state = load_file(folder / "model.safetensors")
    (folder / "model.safetensors").unlink()
    state["planted"] = Planted(ctx.tmp / "ran")
    torch.save(state, folder / "pytorch_model.bin")
    return folder


def malicious_pth(ctx: Ctx) -> Path:
    path = ctx.tmp / "dinov3_vits16.pth"
    torch.save({"blocks.0.attn.qkv.weight": torch.zeros(3, 3), "x": Planted(ctx.tmp / "ran")}, path)
    return path


def nothing_ran(ctx: Ctx, _=None) -> None:
    assert not (ctx.tmp / "ran").exists()


# ---- training runs


def train_config(ctx: Ctx, **overrides):
    from geofeat.train.config import TrainConfig

    settings = dict(
        data="unused",
        out=str(ctx.tmp / "run"),
        image_size=32,
        backproject="face",
        steps=4,
        checkpoint_every=2,
        validate_every=0,
        geodesic_cache=str(ctx.tmp / "geodesics"),
        progress=False,
        device="cpu",
    )
    settings.update(overrides)
    return TrainConfig(**settings)


def trainer(ctx: Ctx, **overrides):
    from tiny_models import tiny_dinov3

    from geofeat.backbones import DinoBackbone
    from geofeat.train.trainer import GeoLoraTrainer

    return GeoLoraTrainer(
        train_config(ctx, **overrides), backbone=DinoBackbone(tiny_dinov3(), kind="dinov3"), shapes=[bumpy(s, 2) for s in (0, 1)]
    )


def logged_steps(run: Path) -> list[int]:
    with open(run / "log.csv", newline="") as handle:
        return [int(r["step"]) for r in csv.DictReader(handle) if r["loss"]]


def logged_losses(run: Path) -> list[float]:
    with open(run / "log.csv", newline="") as handle:
        return [float(r["loss"]) for r in csv.DictReader(handle) if r["loss"]]


def straight_losses(ctx: Ctx, steps: int) -> Close:
    """The losses of the same run without interruption."""
    reference = Ctx(ctx.tmp / "reference", ctx.monkeypatch, ctx.caplog, ctx.cache)
    trainer(reference, steps=steps).fit()
    return Close(logged_losses(reference.tmp / "run"))


def crash_after_step(ctx: Ctx, crash_step: int, steps: int) -> None:
    """Run until ``crash_step`` is logged, then die without any clean-up (an exception the trainer does not handle)."""
    first = trainer(ctx, steps=steps)
    step = first.train_step

    def dying_step():
        if first.step == crash_step:
            raise SystemExit("killed")  # not KeyboardInterrupt: no checkpoint is saved on the way out
        return step()

    first.train_step = dying_step
    with pytest.raises(SystemExit):
        first.fit()


def resume_after_crash(ctx: Ctx) -> list[float]:
    crash_after_step(ctx, crash_step=3, steps=4)  # checkpoints 0 and 2; rows of steps 1..3 written
    assert logged_steps(ctx.tmp / "run") == [1, 2, 3]
    trainer(ctx, steps=4).fit()
    assert logged_steps(ctx.tmp / "run") == [1, 2, 3, 4]  # step 3 once, not twice
    return logged_losses(ctx.tmp / "run")


def resume_from_truncated_state(ctx: Ctx) -> list[float]:
    trainer(ctx, steps=4).fit()  # checkpoints 0, 2, 4
    state = ctx.tmp / "run" / "checkpoints" / "step_0000004" / "trainer_state.pt"
    state.write_bytes(state.read_bytes()[:100])
    crash_free = trainer(ctx, steps=4)
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        final = crash_free.fit()
    assert "step_0000004" in ctx.caplog.text and "damaged" in ctx.caplog.text
    assert final.name == "step_0000004" and (ctx.tmp / "run" / "checkpoints" / ".step_0000004.damaged").is_dir()
    assert logged_steps(ctx.tmp / "run") == [1, 2, 3, 4]
    return logged_losses(ctx.tmp / "run")


KILLED_SAVE = textwrap.dedent(
    """
    import json, os, signal, sys
    sys.path.insert(0, sys.argv[2])
    import torch
    from shapes import bumpy
    from tiny_models import tiny_dinov3
    from geofeat.backbones import DinoBackbone
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    real = torch.save

    def save(obj, f, *args, **kwargs):
        if isinstance(obj, dict) and obj.get("step") == 2:
            os.kill(os.getpid(), signal.SIGKILL)  # kill -9 half-way through writing checkpoint 2
        return real(obj, f, *args, **kwargs)

    torch.save = save
    config = TrainConfig(**json.loads(sys.argv[1]))
    GeoLoraTrainer(config, backbone=DinoBackbone(tiny_dinov3(), kind="dinov3"), shapes=[bumpy(s, 2) for s in (0, 1)]).fit()
    """
)


def resume_after_kill_during_save(ctx: Ctx) -> list[float]:
    import json

    script = ctx.tmp / "train.py"
    script.write_text(KILLED_SAVE)
    config = train_config(ctx, steps=4).to_dict()
    proc = subprocess.run(
        [sys.executable, str(script), json.dumps(config), str(TESTS)], cwd=REPO, capture_output=True, timeout=300
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    folder = ctx.tmp / "run" / "checkpoints"
    stale = [p.name for p in folder.iterdir() if ".tmp-" in p.name]
    assert len(stale) == 1 and stale[0].startswith(".step_0000002.tmp-"), stale  # what the kill left
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        trainer(ctx, steps=4).fit()
    assert "unfinished checkpoint" in ctx.caplog.text
    assert sorted(p.name for p in folder.iterdir()) == ["step_0000000", "step_0000002", "step_0000004"]
    assert logged_steps(ctx.tmp / "run") == [1, 2, 3, 4]
    return logged_losses(ctx.tmp / "run")


def pickle_only_trainer_state(ctx: Ctx):
    trainer(ctx, steps=2).fit()
    state = ctx.tmp / "run" / "checkpoints" / "step_0000002" / "trainer_state.pt"
    saved = torch.load(state, weights_only=True)
    saved["planted"] = Planted(ctx.tmp / "ran")
    torch.save(saved, state)
    trainer(ctx, steps=4).fit()


# ---- fsync before rename


def fsync_log(ctx: Ctx) -> list[tuple[str, str]]:
    """Record ``("fsync", path)`` and ``("replace", source)`` in call order."""
    if not Path("/proc/self/fd").is_dir():
        pytest.skip("needs /proc/self/fd to name synced files")
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        return real_fsync(fd)

    def replace(src, dst, *args, **kwargs):
        events.append(("replace", os.fspath(src)))
        return real_replace(src, dst, *args, **kwargs)

    ctx.monkeypatch.setattr(os, "fsync", fsync)
    ctx.monkeypatch.setattr(os, "replace", replace)
    return events


def synced_before_renamed(events, source: Path, parent: Path) -> set[Path]:
    """The paths synced before the (last) rename of ``source``; checks that ``parent`` is synced after it."""
    renames = [i for i, (kind, path) in enumerate(events) if kind == "replace" and Path(path) == Path(source)]
    assert renames, f"{source} was not renamed: {events}"
    after = {Path(p) for kind, p in events[renames[-1] :] if kind == "fsync"}
    assert Path(os.path.realpath(parent)) in after, f"{parent} not synced after the rename: {events}"
    return {Path(p) for kind, p in events[: renames[-1]] if kind == "fsync"}


def checkpoint_is_synced(ctx: Ctx) -> bool:
    t = trainer(ctx, steps=1)
    t._start_or_resume()
    events = fsync_log(ctx)
    t.step = 7
    final = t.save_checkpoint()
    prefix = f".{final.name}.tmp-{os.getpid()}-"
    tmp = next(Path(p) for kind, p in events if kind == "replace" and Path(p).name.startswith(prefix))
    before = synced_before_renamed(events, tmp, final.parent)
    real_tmp = Path(os.path.realpath(final.parent)) / tmp.name
    wanted = {real_tmp / "weights.safetensors", real_tmp / "config.json", real_tmp / "trainer_state.pt", real_tmp}
    assert wanted <= before, (wanted, before)
    return True


def cache_entry_is_synced(ctx: Ctx) -> bool:
    store = FeatureCache(ctx.tmp / "store")
    events = fsync_log(ctx)
    path = store.put("c" * 64, np.ones((3, 2), dtype=np.float32))
    renamed = next(Path(p) for kind, p in events if kind == "replace")
    assert Path(os.path.realpath(renamed)) in synced_before_renamed(events, renamed, path.parent)
    return True


def atomic_write_is_synced(ctx: Ctx) -> bool:
    from geofeat.storage.files import atomic_write

    events = fsync_log(ctx)
    target = atomic_write(ctx.tmp / "sub" / "a.txt", lambda p: p.write_text("content"))
    renamed = next(Path(p) for kind, p in events if kind == "replace")
    assert Path(os.path.realpath(renamed)) in synced_before_renamed(events, renamed, target.parent)
    return target.read_text() == "content"


# ---- cache stores


def default_store_read_only(ctx: Ctx):
    mesh = bumpy(0, 2)
    read_only(ctx, ctx.cache)
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        first = geofeat.compute(mesh, "hks", n_eig=8, n_descr=4)
        second = geofeat.compute(bumpy(1, 2), "hks", n_eig=8, n_descr=4)
    warnings = [r for r in ctx.caplog.records if "computed without caching" in r.getMessage()]
    assert len(warnings) == 1, ctx.caplog.text  # warned once
    assert "Read-only file system" in ctx.caplog.text and second.shape[1] == 4
    return first


def warm_store_read_only(ctx: Ctx):
    mesh = bumpy(0, 2)
    geofeat.compute(mesh, "hks", n_eig=8, n_descr=4)  # written while writable
    read_only(ctx, ctx.cache)
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        hit = geofeat.compute(mesh, "hks", n_eig=8, n_descr=4)
    assert "without caching" not in ctx.caplog.text
    return hit


def explicit_store_read_only(ctx: Ctx):
    (ctx.tmp / "store").mkdir()
    read_only(ctx, ctx.tmp / "store")
    geofeat.compute(bumpy(0, 2), "hks", cache=ctx.tmp / "store", n_eig=8, n_descr=4)


def cli_clear_read_only(ctx: Ctx):
    """``geofeat cache clear`` on a read-only store: (exit code, lines on stderr, the line names the store)."""
    store = store_with_entries(ctx)
    read_only(ctx, store.root)
    code, out, err = cli(["cache", "clear", "--dir", str(store.root)])
    assert len(store.entries()) == 2
    return code, err.count("\n"), err.startswith("geofeat: error: cannot clear the feature cache")


def cli_clear_read_only_geodesic_store(ctx: Ctx):
    """As `cli_clear_read_only`, for a geodesic store."""
    store = GeodesicStore(ctx.tmp / "geodesics")
    store.load(bumpy(0, 2))
    read_only(ctx, store.root)
    code, out, err = cli(["cache", "clear", "--geodesic-dir", str(store.root)])
    assert len(store.entries()) == 1
    return code, err.count("\n"), err.startswith("geofeat: error: cannot clear the geodesic store")


def cli_verify_read_only(ctx: Ctx):
    store = store_with_entries(ctx)
    store.entries()[0].write_bytes(b"garbage")
    read_only(ctx, store.root)
    code, out, err = cli(["cache", "verify", "--dir", str(store.root)])
    return code, out.splitlines()[0]


def odd_store(ctx: Ctx) -> FeatureCache:
    store = store_with_entries(ctx, 3)
    key = "ab" + "0" * 62
    (store.root / "ab" / f"{key}.h5").mkdir(parents=True)  # a folder with an entry's name
    (store.root / "ab" / f"{key}.h5" / "inside").write_text("x")
    (store.root / "zz").mkdir()
    (store.root / "zz" / "notes.h5").write_text("not an entry")  # a file that is not an entry
    return store


def odd_store_info_verify_clear(ctx: Ctx):
    store = odd_store(ctx)
    info = store.info()
    n_ok, damaged = store.verify()
    code, out, err = cli(["cache", "clear", "--dir", str(store.root)])
    assert "not an entry" in out and err == ""
    left = sorted(p.relative_to(store.root).as_posix() for p in store.root.rglob("*") if p.is_file())
    return info.entries, len(info.other_paths), n_ok, damaged, code, left


def concurrent_writers(ctx: Ctx):
    """Three processes write the same four keys (and their own ones) at once (`cache_writers.write_shared_and_own_keys`)."""
    root = str(ctx.tmp / "s")
    with mp.get_context("spawn").Pool(3) as pool:
        done = pool.starmap(write_shared_and_own_keys, [(root, w, 6) for w in range(3)])
    return done, FeatureCache(root).verify(remove=False), FeatureCache(root).temporary_files()


# ---- the table

MESH_FILES = [
    Row("off-empty", lambda c: geofeat.load_mesh(write_off(c.tmp / "e.off", "")), MeshError, "empty OFF file"),
    Row(
        "off-truncated",
        lambda c: geofeat.load_mesh(write_off(c.tmp / "t.off", tetra_off()[:-12])),
        MeshError,
        "file ends after",
    ),
    Row(
        "off-nan",
        lambda c: geofeat.load_mesh(write_off(c.tmp / "n.off", tetra_off().replace("1.0 0.0 0.0", "nan 0.0 0.0"))),
        MeshError,
        "NaN or infinite",
    ),
    Row(
        "off-1-based",
        lambda c: geofeat.load_mesh(write_off(c.tmp / "o.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 1 2 3\n")),
        MeshError,
        "1-based indices",
    ),
    Row(
        "off-polygon",
        lambda c: geofeat.load_mesh(write_off(c.tmp / "q.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n")),
        MeshError,
        "only triangles",
    ),
    Row(
        "obj-1-based-equals-arrays",
        lambda c: geofeat.load_mesh(write_off(c.tmp / "t.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n")).faces,
        reference=lambda c: np.array([[0, 1, 2], [0, 1, 3]], dtype=np.int64),
    ),
    Row("obj-empty", lambda c: geofeat.load_mesh(write_off(c.tmp / "e.obj", "")), MeshError, "empty"),
    Row("ply-truncated", lambda c: geofeat.load_mesh(truncated_ply(c)), MeshError, "malformed PLY"),
]

NON_FINITE = [
    Row(
        "wks-empty-energy-range",
        lambda c: geofeat.compute(sphere(2), "wks", n_eig=3, n_descr=4),
        DescriptorError,
        "all equal to .*raise n_eig",
        check=no_entries,
    ),
    Row(
        "nan-features-refused-not-cached",
        lambda c: register_nan_descriptor(c) or geofeat.compute(bumpy(0, 2), "nan_for_tests"),
        DescriptorError,
        r"non-finite features on mesh 'bumpy0': 243 NaN and 0 infinite value\(s\) in 81 of 162 vertices",
        check=no_entries,
    ),
]

PARAMETERS = [
    Row(
        "normalize-string",
        lambda c: geofeat.compute(bumpy(), "wks", normalize="false"),
        DescriptorError,
        "normalize must be True or False; found 'false' \\(str\\)",
    ),
    Row(
        "normalize-int",
        lambda c: geofeat.compute(bumpy(), "hks", normalize=0),
        DescriptorError,
        "normalize must be True or False",
    ),
    Row(
        "n-descr-float",
        lambda c: geofeat.compute(bumpy(), "wks", n_descr=8.0),
        DescriptorError,
        "n_descr must be an integer >= 1",
    ),
    Row("n-eig-bool", lambda c: geofeat.compute(bumpy(), "wks", n_eig=True), DescriptorError, "n_eig must be an integer"),
    Row(
        "numpy-int-equals-int-one-cache-entry",
        lambda c: [geofeat.compute(bumpy(0, 2), "wks", n_descr=np.int64(8), n_eig=np.int32(16)), len(FeatureCache().entries())],
        reference=lambda c: [geofeat.compute(bumpy(0, 2), "wks", n_descr=8, n_eig=16), 1],
    ),
    Row(
        "numpy-bool-equals-bool",
        lambda c: geofeat.compute(bumpy(0, 2), "hks", normalize=np.bool_(False), laplacian=np.str_("cotan")),
        reference=lambda c: geofeat.compute(bumpy(0, 2), "hks", normalize=False, laplacian="cotan", cache=False),
    ),
    Row(
        "numpy-scalars-canonical",
        lambda c: [
            (v, type(v).__name__)
            for v in (
                check_integer(np.int64(8), "n"),
                check_number(np.float32(0.5), "x"),
                check_boolean(np.bool_(True), "b"),
                *canonical([np.float32(0.25), np.str_("a"), Path("p")]),
            )
        ],
        reference=lambda c: [(8, "int"), (0.5, "float"), (True, "bool"), (0.25, "float"), ("a", "str"), ("p", "str")],
    ),
    Row(
        "dino-numpy-params-same-key",
        lambda c: registry.make_descriptor(
            "dinov3",
            views=np.int64(4),
            batch_size=np.int8(2),
            random_rotation=np.bool_(True),
            seed=np.uint16(3),
            weights=Path("w"),
        ).params_json(),
        reference=lambda c: registry.make_descriptor(
            "dinov3", views=4, batch_size=2, random_rotation=True, seed=3, weights="w"
        ).params_json(),
    ),
    Row(
        "dino-rotation-string",
        lambda c: registry.make_descriptor("dinov3", random_rotation="no"),
        DescriptorError,
        "random_rotation must be True or False",
    ),
]

CACHE = [
    Row(
        "default-store-read-only-computes-and-warns-once",
        default_store_read_only,
        reference=lambda c: geofeat.compute(bumpy(0, 2), "hks", n_eig=8, n_descr=4, cache=False),
        check=no_entries,
    ),
    Row(
        "read-only-store-still-serves-hits",
        warm_store_read_only,
        reference=lambda c: geofeat.compute(bumpy(0, 2), "hks", n_eig=8, n_descr=4, cache=False),
    ),
    Row(
        "explicit-store-read-only",
        explicit_store_read_only,
        CacheError,
        "is not writable: .*Read-only file system.*cache=False",
    ),
    Row("cli-clear-read-only", cli_clear_read_only, reference=lambda c: (2, 1, True)),
    Row("cli-clear-read-only-geodesic-store", cli_clear_read_only_geodesic_store, reference=lambda c: (2, 1, True)),
    Row(
        "cli-verify-read-only",
        cli_verify_read_only,
        reference=lambda c: (0, "1 entries ok, 1 damaged (0 removed, 1 could not be)"),
    ),
    Row(
        "folder-named-h5-skipped",
        odd_store_info_verify_clear,
        reference=lambda c: (3, 2, 3, [], 0, ["ab/ab" + "0" * 62 + ".h5/inside", "zz/notes.h5"]),
    ),
    Row(
        "concurrent-writers",
        concurrent_writers,
        reference=lambda c: ([6, 6, 6], (N_SHARED_KEYS + 3 * 6, []), []),
    ),
]

POINT_CLOUDS = [
    Row(
        "point-cloud-30-points",
        lambda c: geofeat.compute(Mesh(np.random.default_rng(0).standard_normal((30, 3))), "hks", n_eig=3, n_descr=4),
        MeshError,
        "has 30 points; .* needs at least 31 points",
    ),
    Row(
        "point-cloud-coincident",
        lambda c: geofeat.compute(Mesh(np.ones((40, 3))), "hks", n_eig=3, n_descr=4),
        MeshError,
        "has 40 points, of which 1 distinct and not isolated; .* needs at least 31 points",
    ),
    Row(
        "point-cloud-31-points-works",
        lambda c: np.isfinite(
            geofeat.compute(Mesh(np.random.default_rng(0).standard_normal((31, 3))), "hks", n_eig=3, n_descr=4)
        ).all(),
        reference=lambda c: True,
    ),
]

MESH_LIKE_INPUTS = [
    Row(
        "bare-array",
        lambda c: geofeat.compute(np.zeros((10, 3)), "hks"),
        MeshError,
        r"cannot use a numpy array of shape \(10, 3\) as a mesh; expected a geofeat.Mesh",
    ),
    Row(
        "verts-faces-pair",
        lambda c: geofeat.compute((bumpy(0, 2).verts, bumpy(0, 2).faces), "wks", n_descr=8),
        reference=lambda c: geofeat.compute(bumpy(0, 2), "wks", n_descr=8, cache=False),
    ),
    Row(
        "trimesh-mesh",
        lambda c: geofeat.compute(trimesh.Trimesh(bumpy(0, 2).verts, bumpy(0, 2).faces, process=False), "wks", n_descr=8),
        reference=lambda c: geofeat.compute(bumpy(0, 2), "wks", n_descr=8, cache=False),
    ),
    Row("trimesh-scene", lambda c: geofeat.compute(trimesh.Scene(), "hks"), MeshError, "trimesh.Scene"),
]

UNSAFE_WEIGHTS = [
    Row(
        "hf-truncated-safetensors",
        lambda c: load_backbone(truncated_safetensors(c), kind="dinov3", device="cpu"),
        BackboneError,
        "model.safetensors .*truncated or damaged",
    ),
    Row(
        "hf-pickle-only-bin",
        lambda c: load_backbone(pickle_only_folder(c), kind="dinov3", device="cpu"),
        BackboneError,
        "pytorch_model.bin was refused for safety.*safetensors",
        check=nothing_ran,
    ),
    Row(
        "malicious-official-pth",
        lambda c: load_backbone(malicious_pth(c), kind="dinov3", device="cpu"),
        BackboneError,
        "refused for safety",
        check=nothing_ran,
    ),
    Row(
        "trainer-state-pickle-only",
        pickle_only_trainer_state,
        TrainingError,
        "trainer_state.pt was refused for safety",
        check=nothing_ran,
    ),
]

RUN_PY_LIMIT = [
    Row("run-limit-0", lambda c: run_py().parse_args(["--limit", "0"]), SystemExit, "2"),
    Row("run-limit-negative", lambda c: run_py().parse_args(["--limit", "-1"]), SystemExit, "2"),
    Row("run-limit-positive", lambda c: run_py().parse_args(["--limit", "3"]).limit, reference=lambda c: 3),
]

KILLS = [
    Row("resume-after-crash-no-repeated-rows", resume_after_crash, reference=lambda c: straight_losses(c, 4)),
    Row("resume-falls-back-from-truncated-state", resume_from_truncated_state, reference=lambda c: straight_losses(c, 4)),
    Row("kill-9-during-save-stale-folder-removed", resume_after_kill_during_save, reference=lambda c: straight_losses(c, 4)),
    Row("checkpoint-fsynced-before-rename", checkpoint_is_synced, reference=lambda c: True),
    Row("cache-entry-fsynced-before-rename", cache_entry_is_synced, reference=lambda c: True),
    Row("atomic-write-fsynced-before-rename", atomic_write_is_synced, reference=lambda c: True),
]


def repeated_face_off(ctx: Ctx, repeats: int) -> Path:
    """A 3-vertex OFF whose one triangle is written ``repeats`` times, plus one face naming a vertex twice."""
    faces = "3 0 1 2\n" * repeats + "3 0 0 1\n"
    return write_off(ctx.tmp / "repeated.off", f"OFF\n3 {repeats + 1} 0\n0 0 0\n1 0 0\n0 1 0\n{faces}")


def repeated_faces_hks(ctx: Ctx) -> np.ndarray:
    """HKS of a bumpy sphere whose faces are all written twice (the second time reversed), one of them 200,000 times."""
    mesh = bumpy(0, 2)
    faces = np.concatenate([mesh.faces, mesh.faces[:, ::-1], np.repeat(mesh.faces[:1], 200_000, axis=0)])
    return geofeat.compute(Mesh(mesh.verts, faces), "hks", cache=False, n_eig=8, n_descr=4)


def dropped_faces_logged(ctx: Ctx, result) -> None:
    assert "dropped" in ctx.caplog.text and "repeated face(s)" in ctx.caplog.text


# repeated faces are dropped: the robust Laplacian's time grows with the square of the faces per edge
REPEATED_FACES = [
    Row(
        "repeated-faces-dropped-with-a-count",
        lambda c: len(geofeat.load_mesh(repeated_face_off(c, 1_000_000)).faces),
        reference=lambda c: 1,
        check=lambda c, r: (
            ("dropped 999999 repeated face(s)" in c.caplog.text and "dropped 1 face(s) that name" in c.caplog.text)
            or pytest.fail(c.caplog.text[-500:])
        ),
    ),
    Row(
        "repeated-faces-hks-equals-clean-mesh",
        repeated_faces_hks,
        reference=lambda c: geofeat.compute(bumpy(0, 2), "hks", cache=False, n_eig=8, n_descr=4),
        check=dropped_faces_logged,
    ),
    Row(
        "only-collapsed-faces",
        lambda c: Mesh(TRIANGLE, np.array([[0, 0, 1], [2, 3, 3]])),
        MeshError,
        "every face names one vertex twice",
    ),
]

SECRET = "root:x:0:0:secret-token"


def mesh_error_of(text: str):
    def run(ctx: Ctx):
        return geofeat.load_mesh(write_off(ctx.tmp / "looks-like-a-mesh.off", text))

    return run


def content_not_quoted(ctx: Ctx, error) -> None:
    assert "secret" not in str(error) and "root:x" not in str(error), str(error)


UNQUOTED_FILE_CONTENT = [
    Row(
        "mesh-error-first-line-not-quoted",
        mesh_error_of(SECRET + "\n"),
        MeshError,
        "does not start with 'OFF'",
        check=content_not_quoted,
    ),
    Row(
        "mesh-error-value-not-quoted",
        mesh_error_of("OFF\n3 1 0\n" + SECRET + " 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"),
        MeshError,
        "expected ASCII numbers",
        check=content_not_quoted,
    ),
    Row(
        "mesh-error-variant-not-quoted",
        mesh_error_of(SECRET + "OFF 3 1 0\n"),
        MeshError,
        "an OFF variant",
        check=content_not_quoted,
    ),
]


def plain_pickle_checkpoint(ctx: Ctx) -> Path:
    """What ``pickle.dump`` (not torch.save) writes: a whole pickle that names a callable."""
    import pickle

    path = ctx.tmp / "plain.pth"
    with open(path, "wb") as fh:
        pickle.dump({"weights": np.zeros(2), "hook": os.getcwd}, fh, protocol=4)
    return path


def release_head(checkpoint):
    from geofeat.adapters.heads import load_head

    return load_head("ulrssm", checkpoint=checkpoint)


RELEASE_CHECKPOINTS = [
    Row(
        "plain-pickle-refused-not-truncated",
        lambda c: release_head(plain_pickle_checkpoint(c)),
        GeofeatError,
        "refused for safety",
    ),
    Row(
        "release-checkpoint-is-a-folder",
        lambda c: release_head(c.tmp),
        GeofeatError,
        "is a folder; expected the authors' .pth",
    ),
]


def training_config(text: str):
    def run(ctx: Ctx):
        from geofeat.train.config import TrainConfig

        path = ctx.tmp / "train.yaml"
        path.write_text("data: faust_r\n" + text)
        return TrainConfig.from_file(path)

    return run


TRAINING_CONFIG = [
    Row("train-config-out-list", training_config("out: [a, b]\n"), TrainingError, "out must be a string, found list"),
    Row("train-config-seed-text", training_config("seed: abc\n"), TrainingError, "seed must be an integer, found 'abc'"),
    Row("train-config-progress-no", training_config('progress: "no"\n'), TrainingError, "progress must be true or false"),
    Row("train-config-progress-false", lambda c: training_config("progress: false\n")(c).progress, reference=lambda c: False),
]


def saved_head(ctx: Ctx, damage: str) -> Path:
    """A small ULRSSM head with untrained weights saved into a folder, then damaged as ``damage`` says."""
    from geofeat.adapters.heads import make_head

    head = make_head("ulrssm", descriptor="xyz", width=8, width_out=8, n_blocks=1, n_eig=8, n_fmap=4, diffusion_eig=8)
    head.in_channels, head.model = 3, head.build_model(3)
    folder = ctx.tmp / "head"
    head.save(folder)
    weights, config = folder / "weights.safetensors", folder / "config.json"
    if damage == "truncated":
        weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    elif damage == "missing":
        weights.unlink()
    elif damage == "config-list":
        payload = json.loads(config.read_text())
        config.write_text(json.dumps(payload | {"config": list(payload["config"].items())}))
    elif damage.startswith("format-"):
        version = {"format-string": "1", "format-true": True, "format-negative": -5}[damage]
        config.write_text(json.dumps(json.loads(config.read_text()) | {"format_version": version}))
    elif damage in ("int64", "bool", "nan"):
        from safetensors import safe_open
        from safetensors.torch import save_file

        with safe_open(weights, "pt") as handle:
            metadata = handle.metadata()
            state = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118 - safe_open is no mapping
        key = next(k for k, v in sorted(state.items()) if v.is_floating_point() and v.numel() > 1)
        state[key] = {"int64": state[key].long(), "bool": state[key] > 0, "nan": state[key].clone().fill_(float("nan"))}[damage]
        save_file(state, weights, metadata=metadata)
    return folder


def load_saved_head(damage: str):
    def run(ctx: Ctx):
        from geofeat.adapters.heads import load_head

        return type(load_head(saved_head(ctx, damage))).__name__

    return run


SAVED_HEADS = [
    Row("head-folder-sound", load_saved_head("none"), reference=lambda c: "ULRSSMHead"),
    Row("head-folder-weights-truncated", load_saved_head("truncated"), GeofeatError, "as safetensors"),
    Row("head-folder-weights-missing", load_saved_head("missing"), GeofeatError, "holds no weights.safetensors"),
    Row("head-folder-config-list", load_saved_head("config-list"), GeofeatError, "must be JSON objects"),
]


def forged_hit(kind: str):
    """Replace the cached HKS of a mesh by a well-formed entry (valid checksum) of the wrong content, then compute again."""

    def run(ctx: Ctx):
        from geofeat.descriptors.cache import _checksum

        mesh = bumpy(0, 2)
        store = FeatureCache(ctx.tmp / "store")
        good = geofeat.compute(mesh, "hks", cache=store, n_eig=8, n_descr=4)
        (path,) = store.entries()
        bad = {
            "rows": good[:-1],
            "float64": good.astype(np.float64),
            "nan": np.where(np.arange(len(good))[:, None] == 0, np.nan, good).astype(np.float32),
            "strings": np.array([b"x"] * len(good)),
        }[kind]
        with h5py.File(path, "r+") as fh:
            del fh["features"]
            fh.create_dataset("features", data=bad)
            fh.attrs["checksum"] = _checksum(bad) if kind != "strings" else "crc32:00000000"
        again = geofeat.compute(mesh, "hks", cache=store, n_eig=8, n_descr=4)
        assert "is damaged" in ctx.caplog.text, ctx.caplog.text
        assert store.get(path.stem, n_rows=mesh.n_vertices) is not None  # recomputed and stored again
        return again

    return run


FORGED_CACHE_HITS = [
    Row(
        f"cache-hit-{kind}-recomputed",
        forged_hit(kind),
        reference=lambda c: geofeat.compute(bumpy(0, 2), "hks", cache=False, n_eig=8, n_descr=4),
    )
    for kind in ("rows", "float64", "nan", "strings")
]


def geodesic_pairs(n_targets: int = 1):
    """Pairs (a CUTS partial of a bumpy sphere against the sphere) and a fixed prediction with unmatched vertices."""
    from geofeat.datasets.records import Match, ShapePair
    from geofeat.geometry.partial import make_partial

    pairs, matches = [], []
    for seed in range(n_targets):
        x = bumpy(seed, 3)
        partial = make_partial(x, "cuts", seed=0)
        rng = np.random.default_rng(seed)
        pred = rng.integers(0, x.n_vertices, partial.mesh.n_vertices)
        pred[::11] = -1
        sym = rng.permutation(x.n_vertices)[partial.vertex_map]
        pairs.append(ShapePair(x=x, y=partial.mesh, map_yx=partial.vertex_map, map_yx_sym=sym))
        matches.append(Match(map_yx=pred, overlap_y=np.ones(partial.mesh.n_vertices, dtype=bool)))
    return pairs, matches


def evaluated(ctx: Ctx, store=None, n_targets: int = 1, **options):
    """Errors and chirality of `geodesic_pairs` through `evaluate_dataset`."""
    from geofeat.evaluation.protocol import evaluate_dataset

    pairs, matches = geodesic_pairs(n_targets)
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        records, _ = evaluate_dataset(pairs, lambda i, p: matches[i], store=store, progress=False, **options)
    return [a for r in records for a in (r.errors, np.array([r.chirality_accuracy]))]


def evaluated_reference(ctx: Ctx, n_targets: int = 1):
    from geofeat.evaluation.metrics import chirality_accuracy, geodesic_errors
    from geofeat.geometry.geodesic import geodesic_matrix

    pairs, matches = geodesic_pairs(n_targets)
    out = []
    for pair, match in zip(pairs, matches, strict=True):
        dist = geodesic_matrix(pair.x, "dijkstra", normalize=True, cache=False)
        out += [
            geodesic_errors(match.map_yx, pair.map_yx, dist),
            np.array([chirality_accuracy(match.map_yx, pair.map_yx, pair.map_yx_sym, dist)]),
        ]
    return out


def bound_forced_low(ctx: Ctx):
    store = GeodesicStore(ctx.tmp / "geodesics")
    result = evaluated(ctx, store, memory="1M")
    assert (
        "Computing only the distances the evaluation reads" in ctx.caplog.text and "above the bound of 1.0 MB" in ctx.caplog.text
    )
    assert store.entries() == []  # streamed entries are never stored
    return result


def bound_shared_by_workers(ctx: Ctx):
    """Two targets, two forked workers: each worker's bound is half the one given (written to a file by each worker)."""
    import geofeat.evaluation.protocol as evaluation

    seen = ctx.tmp / "bounds.txt"
    real = evaluation.evaluation_distances

    def recording(mesh, store=None, limit=None, *, limit_source=None):
        with open(seen, "a") as fh:
            fh.write(f"{limit}|{limit_source}\n")
        return real(mesh, store, limit, limit_source=limit_source)

    ctx.monkeypatch.setattr(evaluation, "evaluation_distances", recording)
    result = evaluated(ctx, n_targets=2, workers=2, memory="2M")
    lines = seen.read_text().splitlines()
    assert lines == [f"{1 << 20}|memory_limit, shared by 2 worker processes"] * 2, lines
    return result


def matrix_out_of_memory(ctx: Ctx):
    from geofeat.geometry import geodesic

    def no_memory(*args, **kwargs):
        raise MemoryError("Unable to allocate 23.8 GiB for an array with shape (80000, 80000) and data type float32")

    ctx.monkeypatch.setattr(geodesic, "_all_pairs_dijkstra", no_memory)
    geodesic.geodesic_matrix(bumpy(0, 3), cache=False)


def store_over_its_limit(ctx: Ctx):
    store = GeodesicStore(ctx.tmp / "geodesics", limit=2 * GeodesicStore(ctx.tmp).entry_bytes(162))
    for seed in range(4):
        store.load(bumpy(seed, 2))
        assert store.info().bytes <= store.limit
    return len(store.entries())


def default_geodesic_store(ctx: Ctx, fault: str):
    """Evaluate with the default geodesic store after breaking it as ``fault`` says."""
    import errno

    from geofeat.geometry import geodesic_store

    ctx.monkeypatch.setattr(geodesic_store, "_UNWRITABLE_WARNED", set(), raising=False)  # warned once per process
    if fault == "cache-dir-is-a-file":
        (ctx.tmp / "a file").write_text("not a folder")
        ctx.monkeypatch.setenv("GEOFEAT_CACHE_DIR", str(ctx.tmp / "a file"))
    elif fault == "read-only":
        ctx.cache.mkdir(parents=True, exist_ok=True)
        read_only(ctx, ctx.cache)
    elif fault == "disk-full":

        def full(*args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device")

        ctx.monkeypatch.setattr(geodesic_store.np, "save", full)
    result = evaluated(ctx, GeodesicStore())
    assert ctx.caplog.text.count("geodesic matrices are computed in memory and not kept") == 1, ctx.caplog.text
    return result


def named_geodesic_store_read_only(ctx: Ctx):
    (ctx.tmp / "geodesics").mkdir()
    read_only(ctx, ctx.tmp / "geodesics")
    GeodesicStore(ctx.tmp / "geodesics").load(bumpy(0, 2))


GEODESICS = [
    Row("geodesic-bound-forced-low", bound_forced_low, reference=evaluated_reference),
    Row("geodesic-bound-shared-by-workers", bound_shared_by_workers, reference=lambda c: evaluated_reference(c, 2)),
    Row("geodesic-matrix-out-of-memory", matrix_out_of_memory, GeofeatError, "642 vertices: its all-pairs geodesic matrix"),
    Row("geodesic-store-limit-evicts", store_over_its_limit, reference=lambda c: 2),
    *[
        Row(f"geodesic-store-{fault}", lambda c, f=fault: default_geodesic_store(c, f), reference=evaluated_reference)
        for fault in ("cache-dir-is-a-file", "read-only", "disk-full")
    ],
    Row(
        "geodesic-store-named-read-only",
        named_geodesic_store_read_only,
        GeofeatError,
        "the geodesic store .* cannot be written",
    ),
]


def mesh_tree(ctx: Ctx, relatives: list[str]) -> Path:
    """A data folder holding a small mesh at each relative path."""
    root = ctx.tmp / "data"
    for i, relative in enumerate(relatives):
        path = root / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        mesh = bumpy(i, 1)
        trimesh.Trimesh(mesh.verts, mesh.faces, process=False).export(path)
    return root


def extract_tree(relatives: list[str], export: tuple | None, read_only_place: str | None = None, manifest: str | None = None):
    """`geofeat.apps.extract.extract` HKS over a mesh tree; ``read_only_place`` ("data", "export") is made read-only first."""

    def run(ctx: Ctx):
        from geofeat.apps.extract import ExportSpec, extract, folder_shapes

        root = mesh_tree(ctx, relatives)
        spec = None
        if export is not None:
            fmt, layout, to = export
            spec = ExportSpec(fmt, layout, None if to is None else ctx.tmp / to)
        if read_only_place == "data":
            read_only(ctx, root)
        elif read_only_place == "export":
            (ctx.tmp / "ro").mkdir()
            read_only(ctx, ctx.tmp / "ro")
        store = FeatureCache(ctx.tmp / "store")
        try:
            return extract(
                folder_shapes(root),
                "hks",
                {"n_eig": 8, "n_descr": 4},
                store=store,
                export=spec,
                device="cpu",
                progress=False,
                manifest=None if manifest is None else ctx.tmp / manifest,
            )
        finally:
            ctx.store_entries = len(store.entries())

    return run


def nothing_computed(ctx: Ctx, error) -> None:
    assert ctx.store_entries == 0, "the check must come before the work"


EXPORTS = [
    Row(
        "export-beside-two-shapes-one-file",
        extract_tree(["a/b.off", "b/deep/b.off"], ("npy", "beside", "D")),
        GeofeatError,
        "'a/b' and 'b/deep/b' would both be exported to",
        check=nothing_computed,
    ),
    Row(
        "export-h5-shape-and-its-folder",
        extract_tree(["a.off", "a/b.off"], ("h5", "mirror", "out.h5")),
        GeofeatError,
        "cannot hold both shape 'a' and shape 'a/b'",
        check=nothing_computed,
    ),
    Row(
        "export-beside-read-only-data",
        extract_tree(["shapes/off/a.off"], ("npy", "beside", None), read_only_place="data"),
        GeofeatError,
        "cannot export into .*Read-only file system",
        check=nothing_computed,
    ),
    Row(
        "export-h5-read-only-folder",
        extract_tree(["a.off"], ("h5", "mirror", "ro/out.h5"), read_only_place="export"),
        GeofeatError,
        "cannot export into .*Read-only file system",
        check=nothing_computed,
    ),
    Row(
        "manifest-read-only-folder",
        extract_tree(["a.off"], None, read_only_place="export", manifest="ro/m.manifest.json"),
        GeofeatError,
        "cannot write the manifest .*Read-only file system",
        check=nothing_computed,
    ),
]


def extract_into_read_only_out(ctx: Ctx) -> tuple[int, bool, bool]:
    """`geofeat extract --out` a read-only folder: (exit code, the advice names --out, the advice names cache=False)."""
    root = mesh_tree(ctx, ["a.off"])
    (ctx.tmp / "ro").mkdir()
    read_only(ctx, ctx.tmp / "ro")
    code, _, err = cli(
        [
            "extract",
            "--descriptor",
            "hks",
            "--param",
            "n_eig=8",
            "--data",
            str(root),
            "--out",
            str(ctx.tmp / "ro"),
            "--no-progress",
        ]
    )
    return code, "--out" in err, "cache=False" in err


CACHE += [
    Row("extract-out-read-only-suggests-out", extract_into_read_only_out, reference=lambda c: (2, True, False)),
]

# ----------------------------------------------------------------------------- faults that would go unnoticed


def dino_blob(ctx: Ctx, mesh: Mesh | None = None, **params) -> np.ndarray:
    """DINOv3 features (a tiny random model) of the 162-vertex blob, or of ``mesh``, cached in ``ctx.tmp/store``."""
    from geofeat.apps.demo import blob

    settings = dict(weights=tiny_folder(ctx), views=4, device="cpu", image_size=64, cache=FeatureCache(ctx.tmp / "store"))
    return geofeat.compute(blob(2, 0, "b") if mesh is None else mesh, "dinov3", **(settings | params))


def zeros_with_warning(ctx: Ctx) -> tuple[bool, bool]:
    """fill="zero" where no vertex is seen: (the features are all zeros, a warning says so)."""
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        features = dino_blob(ctx, image_size=16, fill="zero")
    return bool(np.all(features == 0)), "no vertex of 'b' was seen" in ctx.caplog.text


def moved_features_agree(ctx: Ctx) -> list[float]:
    """Largest difference between the features of the blob and of the same blob moved by 1e6 or scaled by 1e-6 and 1e6."""
    from geofeat.apps.demo import blob

    mesh = blob(2, 0, "b")
    base = dino_blob(ctx, cache=False)
    moved = [
        Mesh(mesh.verts + 1e6, mesh.faces, "moved"),
        Mesh(mesh.verts * 1e-6, mesh.faces, "small"),
        Mesh(mesh.verts * 1e6, mesh.faces, "large"),
    ]
    return [float(np.abs(dino_blob(ctx, m, cache=False) - base).max()) < 1e-4 for m in moved]


def store_entries(ctx: Ctx, _=None) -> None:
    assert FeatureCache(ctx.tmp / "store").entries() == [], "nothing may be cached"


DINO_VIEWS = [
    Row(
        "dino-no-vertex-seen-refused",
        lambda c: dino_blob(c, image_size=16),
        geofeat.RenderError,
        "no vertex of 'b' .* received a pixel in any of its 4 views",
        check=store_entries,
    ),
    Row("dino-no-vertex-seen-fill-zero-warns", zeros_with_warning, reference=lambda c: (True, True)),
    Row("dino-features-ignore-offset-and-scale", moved_features_agree, reference=lambda c: [True, True, True]),
]


def save_times(folder: Path, n: int) -> None:
    for value in range(1, n + 1):
        geofeat.storage.pretrained.save_pretrained(
            folder, "toy", {"value": value}, {"w": torch.full((64,), float(value))}, durable=False
        )


def torn_loads(ctx: Ctx) -> int:
    """Loads whose config and weights came from different saves, while another process saves the folder 60 times."""
    from geofeat.storage.pretrained import from_pretrained, save_pretrained

    folder = save_pretrained(ctx.tmp / "m", "toy", {"value": 0}, {"w": torch.zeros(64)})
    writer = mp.get_context("fork").Process(target=save_times, args=(folder, 60))
    writer.start()
    torn = 0
    try:
        while writer.is_alive():
            try:
                saved = from_pretrained(folder, "toy", geofeat.HeadError)
            except geofeat.HeadError as err:  # replaced too often while read: refused, never mixed
                assert "replaced" in str(err), err
                continue
            torn += int(saved.tensors()["w"][0].item() != saved.config["value"])
    finally:
        writer.join(60)
    assert writer.exitcode == 0 and from_pretrained(folder, "toy", geofeat.HeadError).config["value"] == 60
    return torn


def resume_on_changed_shapes(ctx: Ctx):
    """A run of two shapes resumed with the second shape's content edited."""
    from tiny_models import tiny_dinov3

    from geofeat.backbones import DinoBackbone
    from geofeat.train.trainer import GeoLoraTrainer

    trainer(ctx, steps=2).fit()
    edited = bumpy(1, 2)
    shapes = [bumpy(0, 2), Mesh(edited.verts * 1.01, edited.faces, edited.name)]
    GeoLoraTrainer(train_config(ctx, steps=4), backbone=DinoBackbone(tiny_dinov3(), kind="dinov3"), shapes=shapes).fit()


#: One Ctrl-C to this process from inside the next fork's at-fork hook (a hook cannot be removed: it stays, disarmed).
CTRL_C_AT_NEXT_FORK = {"armed": False}


def ctrl_c_in_fork_hook() -> None:
    if CTRL_C_AT_NEXT_FORK["armed"]:
        CTRL_C_AT_NEXT_FORK["armed"] = False
        os.kill(os.getpid(), signal.SIGINT)


os.register_at_fork(before=ctrl_c_in_fork_hook)


def ctrl_c_while_workers_start(ctx: Ctx) -> str:
    """A Ctrl-C landing in an at-fork hook while the sample workers start: the run stops before its first step."""
    from geofeat.train.checkpoints import latest_checkpoint

    run = trainer(ctx, steps=30, checkpoint_every=0, workers=2)
    CTRL_C_AT_NEXT_FORK["armed"] = True
    try:
        with pytest.raises(KeyboardInterrupt):
            run.fit()
    finally:
        CTRL_C_AT_NEXT_FORK["armed"] = False
    return latest_checkpoint(ctx.tmp / "run").name


#: Loads of a folder that another process is saving, or whose save was killed.
CONCURRENT_SAVES = [
    Row("load-during-60-saves-never-torn", torn_loads, reference=lambda c: 0),
]

TRAINING_RUNS = [
    Row("resume-refuses-changed-shape", resume_on_changed_shapes, TrainingError, re.escape("1 changed in content (bumpy1)")),
    Row("ctrl-c-at-worker-start-stops", ctrl_c_while_workers_start, reference=lambda c: "step_0000000"),
]

#: Starts a pool whose workers stay busy, prints their process ids, then waits to be killed.
POOL_SCRIPT = textwrap.dedent(
    """
    import sys, threading, time
    sys.path.insert(0, sys.argv[2])
    import psutil

    def slow(task):
        time.sleep(600)

    def start(which):
        if which == "samples":
            from shapes import bumpy
            from geofeat.train.config import TrainConfig
            from geofeat.train.samples import SampleDataset, SamplePrefetcher
            config = TrainConfig(data="unused", out=sys.argv[3] + "/run", device="cpu", progress=False)
            dataset = SampleDataset(config, [bumpy(s, 3) for s in (0, 1)], sys.argv[3] + "/geodesics")
            return SamplePrefetcher(dataset, lambda step: range(step, step + 1), 0, 100, workers=2)
        if which == "evaluation":
            from geofeat.evaluation.protocol import map_forked
            results = map_forked(slow, list(range(8)), workers=2)
            threading.Thread(target=lambda: list(results), daemon=True).start()
        if which == "compute":
            from shapes import bumpy
            from geofeat.descriptors.collection import compute_many
            meshes = [bumpy(s, 4) for s in range(200)]
            threading.Thread(target=lambda: compute_many(meshes, "hks", n_jobs=2, cache=False), daemon=True).start()

    if __name__ == "__main__":
        pool = start(sys.argv[1])
        while len(psutil.Process().children()) < 2:
            time.sleep(0.1)
        time.sleep(3)  # the workers have started and hold their pipes
        print(" ".join(str(child.pid) for child in psutil.Process().children(recursive=True)), flush=True)
        time.sleep(600)
    """
)


def workers_left_after_kill(which: str):
    """Kill -9 a process running a pool of geofeat: the ids of its workers still running 30 s later."""

    def run(ctx: Ctx) -> list[int]:
        import psutil

        script = ctx.tmp / "pool.py"
        script.write_text(POOL_SCRIPT)
        parent = subprocess.Popen(
            [sys.executable, str(script), which, str(TESTS), str(ctx.tmp)], cwd=REPO, stdout=subprocess.PIPE, text=True
        )
        try:
            workers = [psutil.Process(int(pid)) for pid in parent.stdout.readline().split()]
        finally:
            parent.kill()
            parent.wait()
        assert workers, "the pool started no worker"
        _, alive = psutil.wait_procs(workers, timeout=30)
        for process in alive:  # do not leave them behind this test
            process.kill()
        return [p.pid for p in alive]

    return run


WORKER_PROCESSES = [
    Row("sample-workers-end-with-trainer", workers_left_after_kill("samples"), reference=lambda c: []),
    Row("evaluation-workers-end-with-parent", workers_left_after_kill("evaluation"), reference=lambda c: []),
    Row("compute-workers-end-with-parent", workers_left_after_kill("compute"), reference=lambda c: []),
]


def one_line_exit(run: Callable[[Ctx], tuple[int, str]], expected: str):
    """(exit code, the error is one line holding ``expected``, no traceback) of a command line."""

    def check(ctx: Ctx) -> tuple[int, bool]:
        code, err = run(ctx)
        lines = err.strip().splitlines()
        return code, len(lines) == 1 and expected in lines[0] and "Traceback" not in err

    return check


def train_into_file(ctx: Ctx) -> tuple[int, str]:
    (ctx.tmp / "FILE").write_text("")
    root = mesh_tree(ctx, ["a.off"])
    code, _, err = cli(["train-geolora", "--data", str(root), "--out", str(ctx.tmp / "FILE"), "--weights", str(tiny_folder(ctx))])
    return code, err


def fake_generator(ctx: Ctx) -> Path:
    """A folder that looks like the BeCoS generator (main.py, a configuration naming its setting)."""
    generator = ctx.tmp / "generator"
    (generator / "config").mkdir(parents=True)
    (generator / "main.py").write_text("")
    (generator / "config" / "demo_config.yaml").write_text("setting: partial_full\n")
    return generator


def prepare_becos(*extra: str):
    def run(ctx: Ctx) -> tuple[int, str]:
        (ctx.tmp / "FILE").write_text("")
        given = [arg.format(tmp=ctx.tmp) for arg in extra]
        code, _, err = cli(["data", "prepare", "becos", "--generator", str(fake_generator(ctx)), *given])
        return code, err

    return run


def run_py_pairs_on_derived(ctx: Ctx) -> tuple[int, str]:
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = run_py().main(["--dataset", "synthetic_cuts", "--pairs", "combinations", "--out", str(ctx.tmp / "out")])
    return code, err.getvalue()


def extract_interrupted(ctx: Ctx) -> tuple[int, str]:
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    ctx.monkeypatch.setattr("geofeat.apps.extract.extract", interrupted)
    code, _, err = cli(["extract", "--descriptor", "hks", "--data", str(mesh_tree(ctx, ["a.off"])), "--no-progress"])
    return code, err


COMMAND_LINES = [
    Row("train-out-is-a-file", one_line_exit(train_into_file, "cannot write the run folder"), reference=lambda c: (2, True)),
    Row(
        "prepare-out-is-a-file",
        one_line_exit(prepare_becos("--out", "{tmp}/FILE"), "cannot write into"),
        reference=lambda c: (2, True),
    ),
    Row(
        "prepare-python-missing",
        one_line_exit(prepare_becos("--out", "{tmp}/out", "--python", "/nonexistent/python"), "cannot run '/nonexistent/python'"),
        reference=lambda c: (2, True),
    ),
    Row(
        "run-py-option-a-derived-benchmark-lacks",
        one_line_exit(run_py_pairs_on_derived, "unknown option(s) ['pairs']"),
        reference=lambda c: (2, True),
    ),
    Row("extract-ctrl-c", one_line_exit(extract_interrupted, "interrupted"), reference=lambda c: (130, True)),
]


def cache_cleared_while_writing(ctx: Ctx) -> tuple[bool, bool]:
    """The store's folder removed while an entry is written (a cache clear): (the entry is kept, a warning says so)."""
    import shutil

    store, real = FeatureCache(ctx.tmp / "store"), h5py.File
    calls = []

    def clear_first(path, *args, **kwargs):
        if not calls:
            calls.append(path)
            shutil.rmtree(ctx.tmp / "store")
        return real(path, *args, **kwargs)

    ctx.monkeypatch.setattr(h5py, "File", clear_first)
    with ctx.caplog.at_level(logging.WARNING, logger="geofeat"):
        store.put("a" * 64, np.ones((3, 2), np.float32))
    ctx.monkeypatch.undo()
    return bool(np.array_equal(store.get("a" * 64), np.ones((3, 2)))), "was removed while" in ctx.caplog.text


def failing_sample_worker(ctx: Ctx):
    """A sample that a worker process cannot prepare: the trainer raises the worker's error with its own message."""
    from geofeat.train import samples

    def no_partial(*args, **kwargs):
        raise geofeat.MeshError("no partial shape in 20 tries")

    ctx.monkeypatch.setattr(samples, "make_partial", no_partial)  # the workers are forked: they see it too
    trainer(ctx, steps=2, workers=2).fit()


def run_folder_as_checkpoint(ctx: Ctx):
    """A training run folder (its settings as config.json, checkpoints/step_N) given as a GeoLoRA checkpoint."""
    run = ctx.tmp / "run"
    (run / "checkpoints" / "step_0000002").mkdir(parents=True)
    train_config(ctx).save(run / "config.json")
    geofeat.compute(bumpy(0, 1), "geolora", checkpoint=run, weights=tiny_folder(ctx), device="cpu", cache=False)


def swap_killed_between_renames(ctx: Ctx) -> int:
    """A folder a killed save left set aside (its new content not yet in place): a load restores and reads it."""
    from geofeat.storage.pretrained import from_pretrained, save_pretrained

    folder = save_pretrained(ctx.tmp / "m", "toy", {"value": 7}, {"w": torch.full((4,), 7.0)})
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    folder.rename(folder.parent / f".m.old-{int(dead.stdout)}-0123abcd")
    return from_pretrained(folder, "toy", geofeat.HeadError).config["value"]


CACHE += [
    Row("cache-cleared-while-writing", cache_cleared_while_writing, reference=lambda c: (True, True)),
]

SAVED_HEADS += [
    Row("head-format-version-string", load_saved_head("format-string"), GeofeatError, "must be a whole number from 1"),
    Row("head-format-version-true", load_saved_head("format-true"), GeofeatError, "must be a whole number from 1"),
    Row("head-format-version-negative", load_saved_head("format-negative"), GeofeatError, "must be a whole number"),
    Row("head-weights-int64", load_saved_head("int64"), GeofeatError, "of another kind of number .*int64 instead of"),
    Row("head-weights-bool", load_saved_head("bool"), GeofeatError, "of another kind of number .*bool instead of"),
    Row("head-weights-nan", load_saved_head("nan"), GeofeatError, "holding NaN or infinite values"),
]

WORKER_PROCESSES += [
    Row("sample-worker-error-message", failing_sample_worker, geofeat.MeshError, "^no partial shape in 20 tries$"),
]

TRAINING_RUNS += [
    Row("run-folder-as-checkpoint", run_folder_as_checkpoint, GeofeatError, "is a training run folder.*step_0000002"),
]

CONCURRENT_SAVES += [
    Row("swap-killed-between-renames", swap_killed_between_renames, reference=lambda c: 7),
]

COMMAND_LINES += [
    Row(
        "data-check-unknown-split-exit-2",
        one_line_exit(lambda c: cli(["data", "check", "synthetic_cuts", "--split", "bogus"])[::2], "split must be one of"),
        reference=lambda c: (2, True),
    ),
]

ROWS = (
    MESH_FILES
    + NON_FINITE
    + PARAMETERS
    + CACHE
    + POINT_CLOUDS
    + MESH_LIKE_INPUTS
    + UNSAFE_WEIGHTS
    + RUN_PY_LIMIT
    + KILLS
    + REPEATED_FACES
    + UNQUOTED_FILE_CONTENT
    + RELEASE_CHECKPOINTS
    + TRAINING_CONFIG
    + SAVED_HEADS
    + FORGED_CACHE_HITS
    + GEODESICS
    + EXPORTS
    + DINO_VIEWS
    + CONCURRENT_SAVES
    + TRAINING_RUNS
    + WORKER_PROCESSES
    + COMMAND_LINES
)


def run_py():
    """The command behind ``benchmarks/run.py``."""
    from geofeat.apps import benchmark

    return benchmark


@pytest.mark.parametrize("row", ROWS, ids=[r.id for r in ROWS])
def test_input(row: Row, tmp_path, monkeypatch, caplog, isolated_cache, capsys):
    ctx = Ctx(tmp_path, monkeypatch, caplog, isolated_cache)
    if row.raises is not None:
        with pytest.raises(row.raises, match=row.match) as info:
            row.run(ctx)
        if row.raises is SystemExit:
            assert "error: argument --limit: expected a positive number of pairs" in capsys.readouterr().err
        else:
            assert isinstance(info.value, GeofeatError), type(info.value).__mro__
        outcome = info.value
    else:
        outcome = row.run(ctx)
        assert_same(outcome, row.reference(ctx))
    if row.check is not None:
        row.check(ctx, outcome)


def test_every_table_is_run_and_ids_are_unique():
    """Every module-level list of rows is part of ROWS, and no two rows share an id."""
    tables = {name: v for name, v in globals().items() if isinstance(v, list) and v and all(isinstance(r, Row) for r in v)}
    in_rows = {id(r) for r in ROWS}
    assert [name for name, table in tables.items() if any(id(r) not in in_rows for r in table)] == []
    assert len({r.id for r in ROWS}) == len(ROWS)
