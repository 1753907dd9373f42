"""Checkpoints and resume safety of GeoLoRA runs: what survives a Ctrl-C, a ``kill -9`` or a power cut.

A run folder (``config.out``) holds ``config.json`` (the `TrainConfig`), ``log.csv`` (one row
per step) and ``checkpoints/step_NNNNNNN/``. A checkpoint is one LoRA folder of
`geofeat.storage.pretrained` (``config.json`` of kind ``"lora"`` + ``weights.safetensors``,
what `geofeat.backbones.lora.load_lora` and the ``geolora`` descriptor load) with one extra
file, ``trainer_state.pt`` (step, sample position, rank count, optimizer state), and for the
``reference`` recipe's LoRA a second one, ``geolora_release.pth``: the LoRA in the
layout of the official release, which the official code loads. It is written
whole into a temporary sibling folder, ``fsync``-ed and renamed (`geofeat.storage.files.atomic_folder`),
so an interruption never leaves a half-written one; the log rows up to a checkpoint's step
are on disk before the checkpoint is.

After a crash a resumed run

* drops the log rows of steps after the checkpoint it resumes from (`truncate_log`; they
  are trained again);
* falls back to the previous checkpoint, with a warning, when the newest one cannot be read
  (`readable_checkpoint`: a truncated ``trainer_state.pt`` or LoRA); the damaged folder is
  renamed ``.step_NNNNNNN.damaged``;
* removes the temporary folders of saves that were killed (`remove_stale_temporary_folders`:
  their process is gone).
"""

from __future__ import annotations

import csv
import logging
import os
import shutil
import signal
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from geofeat.backbones import DinoBackbone
from geofeat.backbones.lora import LORA_KIND, LoraSettings, official_lora_state_dict, save_lora
from geofeat.errors import DamagedCheckpointError, TrainingError
from geofeat.storage.files import atomic_write, remove_dead_temporary_folders
from geofeat.storage.pretrained import CONFIG_FILE, WEIGHTS_FILE, from_pretrained, unread_layout
from geofeat.storage.safe_load import load_torch_file

log = logging.getLogger(__name__)

__all__ = [
    "RELEASE_FILE",
    "STATE_FILE",
    "DeferredInterrupt",
    "checkpoint_folder",
    "complete_checkpoints",
    "latest_checkpoint",
    "read_checkpoint",
    "readable_checkpoint",
    "remove_stale_temporary_folders",
    "sync_log",
    "truncate_log",
    "write_checkpoint",
]

#: The LoRA as a GeoLoRA release checkpoint (fused qkv LoRA), in the checkpoints of a shared-A LoRA.
RELEASE_FILE = "geolora_release.pth"
#: The trainer's state in a checkpoint folder: ``{"step", "samples", "world_size", "optimizer"}``.
STATE_FILE = "trainer_state.pt"


def checkpoint_folder(run: str | os.PathLike, step: int) -> Path:
    """``<run>/checkpoints/step_NNNNNNN`` (seven digits) for ``step``."""
    return Path(run) / "checkpoints" / f"step_{step:07d}"


def complete_checkpoints(run: str | os.PathLike) -> list[Path]:
    """The checkpoint folders of a run folder that hold a state file, oldest first.

    Parameters
    ----------
    run : str or os.PathLike
        A run folder (``config.out``).

    Returns
    -------
    list of pathlib.Path
        ``checkpoints/step_NNNNNNN`` folders with a ``trainer_state.pt``, sorted by step.
    """
    folder = Path(run) / "checkpoints"
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob("step_*") if p.is_dir() and (p / STATE_FILE).is_file())


def latest_checkpoint(run: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run folder, or None."""
    done = complete_checkpoints(run)
    return done[-1] if done else None


def remove_stale_temporary_folders(run: str | os.PathLike) -> list[Path]:
    """Delete the temporary folders of checkpoint saves whose process is gone.

    `geofeat.storage.files.remove_dead_temporary_folders` on ``<run>/checkpoints``: the folders
    ``.step_NNNNNNN.tmp-<pid>-...`` of killed saves (and those of the older trainer,
    ``.step_NNNNNNN.tmp-<pid>``).

    Parameters
    ----------
    run : str or os.PathLike
        A run folder.

    Returns
    -------
    list of pathlib.Path
        The folders removed (a warning names them).
    """
    removed = remove_dead_temporary_folders(Path(run) / "checkpoints")
    if removed:
        log.warning("removed %d unfinished checkpoint folder(s) of killed saves: %s", len(removed), [p.name for p in removed])
    return removed


def write_checkpoint(
    run: str | os.PathLike,
    step: int,
    backbone: DinoBackbone,
    settings: LoraSettings,
    state: Mapping[str, Any],
    extra_info: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``checkpoints/step_NNNNNNN`` (the LoRA and ``trainer_state.pt``) atomically; returns the folder.

    A complete checkpoint of that step already there is kept as it is.

    Parameters
    ----------
    run : str or os.PathLike
        The run folder.
    step : int
        The step count the checkpoint is taken after (the folder's name).
    backbone : DinoBackbone
        Carrying the LoRA.
    settings : LoraSettings
        Stored with the LoRA (its training settings).
    state : Mapping
        The trainer state, saved with ``torch.save`` as ``trainer_state.pt``; its ``"step"`` must be ``step``.
    extra_info : Mapping, optional
        Stored as the LoRA folder's ``info`` besides ``{"step": step}``.

    Returns
    -------
    pathlib.Path

    Notes
    -----
    A LoRA with one ``A`` shared by query, key and value (the ``reference`` recipe's) is
    also written as a release checkpoint, `RELEASE_FILE`, which the official code and
    `geofeat.backbones.load_official_lora` load.
    """
    final = checkpoint_folder(run, step)
    if (final / STATE_FILE).is_file():
        return final
    if int(state["step"]) != step:
        raise TrainingError(f"the trainer state is for step {state['step']}, the checkpoint for step {step}.")
    extra_files = {STATE_FILE: lambda path: torch.save(dict(state), path)}
    if settings.shared_a:  # the fused-qkv layout of the release holds it: also written so
        extra_files[RELEASE_FILE] = lambda path: torch.save(official_lora_state_dict(backbone), path)
    save_lora(backbone, final, settings, extra_info={"step": step, **(extra_info or {})}, extra_files=extra_files)
    log.info("saved checkpoint %s", final)
    return final


def read_checkpoint(folder: str | os.PathLike, device: str | torch.device = "cpu") -> dict:
    """The trainer state of a checkpoint folder, after checking that its LoRA can be read.

    Parameters
    ----------
    folder : str or os.PathLike
        A ``checkpoints/step_NNNNNNN`` folder.
    device : str or torch.device
        Where the optimizer state's tensors go.

    Returns
    -------
    dict
        ``{"step", "optimizer", ...}`` as the trainer saved it.

    Raises
    ------
    DamagedCheckpointError
        A file is truncated or unreadable, or the state does not fit the folder.
    TrainingError
        ``trainer_state.pt`` is a pickle refused for safety, or the folder has a layout this
        geofeat does not read (`geofeat.storage.pretrained.unread_layout`).
    """
    folder = Path(folder)
    found = unread_layout(folder)
    if found is not None:
        raise TrainingError(
            f"the checkpoint {folder} holds {found}, a layout this geofeat does not read; expected {CONFIG_FILE} + "
            f"{WEIGHTS_FILE} + {STATE_FILE} as the trainer writes them. Train again with this version of geofeat, "
            "into a new out folder."
        )
    state = load_torch_file(
        folder / STATE_FILE, TrainingError, damaged_error=DamagedCheckpointError, what="a trainer state", map_location=device
    )
    if not isinstance(state, dict) or not {"step", "optimizer"} <= set(state):
        raise DamagedCheckpointError(f"{folder / STATE_FILE} lacks 'step' or 'optimizer'; it was not written by the trainer.")
    expected = int(folder.name.split("_")[-1])
    if int(state["step"]) != expected:
        raise DamagedCheckpointError(f"{folder / STATE_FILE} is for step {int(state['step'])}, its folder for step {expected}.")
    from_pretrained(folder, LORA_KIND, DamagedCheckpointError).tensors()
    return state


def readable_checkpoint(run: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[Path | None, dict | None]:
    """The newest checkpoint of a run whose files can all be read, with its state; damaged newer ones are set aside.

    A damaged checkpoint (`read_checkpoint` raised `DamagedCheckpointError`) is renamed
    ``.step_NNNNNNN.damaged`` with a warning, and the one before it is tried.

    Returns
    -------
    folder : pathlib.Path or None
        None when the run has no checkpoint.
    state : dict or None

    Raises
    ------
    TrainingError
        Every checkpoint was damaged, or one cannot be used at all (see `read_checkpoint`).
    """
    run = Path(run)
    candidates = complete_checkpoints(run)
    for folder in reversed(candidates):
        try:
            return folder, read_checkpoint(folder, device)
        except DamagedCheckpointError as err:
            aside = folder.with_name(f".{folder.name}.damaged")
            shutil.rmtree(aside, ignore_errors=True)
            os.replace(folder, aside)
            log.warning(
                "checkpoint %s is damaged (%s); moved it to %s and fell back to the previous one", folder, err, aside.name
            )
    if candidates:
        raise TrainingError(
            f"no checkpoint of {run} can be read (all {len(candidates)} were damaged and moved to "
            f"{run / 'checkpoints'}/.step_*.damaged); start again with another out folder."
        )
    return None, None


def truncate_log(run: str | os.PathLike, last_step: int | None, columns: Sequence[str]) -> None:
    """Keep the complete rows of ``<run>/log.csv`` up to ``last_step`` (None: no row), dropping the rest.

    Rows after the checkpoint a run resumes from were written by the killed process and
    are written again by the resumed one; a kill can also leave half a row. The file is
    rewritten atomically.

    Parameters
    ----------
    run : str or os.PathLike
    last_step : int or None
    columns : sequence of str
        The log's columns; a row lacking one is incomplete.
    """
    path = Path(run) / "log.csv"
    if not path.is_file():
        return
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    kept = []
    for row in rows:
        try:
            step = int(row.get("step") or "")
        except ValueError:
            continue
        complete = None not in row and all(row.get(c) is not None for c in columns)
        if last_step is not None and step <= last_step and complete:
            kept.append(row)
    if len(kept) != len(rows) or not rows:

        def write(tmp: Path) -> None:
            with open(tmp, "w", newline="") as out:
                writer = csv.DictWriter(out, fieldnames=list(columns), extrasaction="ignore")
                writer.writeheader()
                writer.writerows(kept)

        atomic_write(path, write)
        where = "a new run" if last_step is None else f"the checkpoint of step {last_step}"
        log.info("log.csv: dropped %d row(s) written after %s", len(rows) - len(kept), where)


def sync_log(handle) -> None:
    """Put the log rows written so far on disk (before a checkpoint that follows them)."""
    handle.flush()
    os.fsync(handle.fileno())


class DeferredInterrupt:
    """Turn the first Ctrl-C into a request to stop after the current step (a second one stops at once).

    A context manager; ``requested`` turns True on the first SIGINT. Only the main thread can
    install the handler; elsewhere Ctrl-C keeps its usual meaning.
    """

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("Ctrl-C: finishing the current step, then saving a checkpoint (press again to stop at once)")

    def __enter__(self) -> DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
