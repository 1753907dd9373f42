"""Resuming a GeoLoRA run: the checkpoint to resume from, checked against the run being started.

A run folder that already holds checkpoints is resumed from the newest readable one
(`geofeat.train.checkpoints.readable_checkpoint`) when the settings saved in its
``config.json`` agree with the new ones (up to `geofeat.train.config.RESUMABLE_CHANGES`) and
the training shapes are those the checkpoint recorded (names and content hashes, in order).
"""

from __future__ import annotations

from pathlib import Path

import torch

from geofeat.errors import TrainingError
from geofeat.mesh import Mesh
from geofeat.train import checkpoints
from geofeat.train.config import RESUMABLE_CHANGES, TrainConfig

__all__ = ["check_same_shapes", "checkpoint_to_resume", "shape_records"]


def checkpoint_to_resume(
    out: Path, config: TrainConfig, shapes: list[Mesh], device: torch.device
) -> tuple[Path | None, dict | None]:
    """The newest readable checkpoint of the run in ``out`` and its trainer state; ``(None, None)`` for a new run.

    The temporary folders of saves that were killed are removed first.

    Parameters
    ----------
    out : Path
        The run folder.
    config : TrainConfig
        The settings of the run being started.
    shapes : list of Mesh
        Its training shapes, in order.
    device : torch.device
        Where the optimizer state is loaded.

    Returns
    -------
    checkpoint : Path or None
    state : dict or None
        ``trainer_state.pt`` of the checkpoint (`geofeat.train.checkpoints.read_checkpoint`).

    Raises
    ------
    TrainingError
        The saved settings differ from ``config`` beyond `RESUMABLE_CHANGES`, or the run was
        trained on other shapes (`check_same_shapes`).
    """
    checkpoints.remove_stale_temporary_folders(out)
    checkpoint, state = checkpoints.readable_checkpoint(out, device)
    if checkpoint is None:
        return None, None
    saved = TrainConfig.from_file(out / "config.json")
    changed = sorted(set(config.changes_from(saved)) - RESUMABLE_CHANGES - {"out"})
    if changed:
        raise TrainingError(
            f"{out} holds a run with other settings ({', '.join(f'{n}={getattr(saved, n)!r}' for n in changed)}); "
            "resume it with the same settings or choose another out folder."
        )
    check_same_shapes(state.get("shapes"), shape_records(shapes), checkpoint, out, config.data)
    return checkpoint, state


def shape_records(shapes: list[Mesh]) -> list[list[str]]:
    """``[name, content hash]`` of every training shape, in the run's order (saved with each checkpoint)."""
    return [[mesh.name, mesh.hash] for mesh in shapes]


def check_same_shapes(saved: list | None, mine: list[list[str]], checkpoint: Path, out: Path, data: str) -> None:
    """Refuse to resume on other training shapes than the checkpoint's run (names and contents compared).

    Parameters
    ----------
    saved : list or None
        The checkpoint's `shape_records`; None for a checkpoint that records none (refused).
    mine : list of [str, str]
        `shape_records` of the shapes of the run being started.
    checkpoint : Path
        The checkpoint folder (named in the messages).
    out : Path
        The run folder.
    data : str
        ``config.data`` (named in the messages).

    Raises
    ------
    TrainingError
        Shapes added, removed, reordered or changed since the checkpoint, named; or no
        shapes recorded.
    """
    if saved is None:
        raise TrainingError(
            f"{checkpoint} records no training shapes, so resuming cannot check that {data!r} holds the same ones; "
            f"every checkpoint this trainer writes records them. Train again into a new out folder."
        )
    if [list(r) for r in saved] == mine:
        return
    before, now = dict((n, h) for n, h in saved), dict(mine)
    changes = (
        [f"{len(set(now) - set(before))} added ({', '.join(sorted(set(now) - set(before))[:3])})"]
        if set(now) - set(before)
        else []
    )
    if set(before) - set(now):
        changes.append(f"{len(set(before) - set(now))} removed ({', '.join(sorted(set(before) - set(now))[:3])})")
    edited = sorted(n for n in set(now) & set(before) if now[n] != before[n])
    if edited:
        changes.append(f"{len(edited)} changed in content ({', '.join(edited[:3])})")
    raise TrainingError(
        f"{out} was trained on other shapes than {data!r} holds now: "
        + ("; ".join(changes) or "the same shapes in another order")
        + f" (checkpoint {checkpoint.name}). Resume with the run's data, or start a new run in another out folder."
    )
