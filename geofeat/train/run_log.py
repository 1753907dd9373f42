"""The run log of GeoLoRA training: ``log.csv`` rows and the seconds per phase of a step.

``log.csv`` in the run folder has one row per step (step count, seconds since the start,
loss, number of partial shapes, seconds per phase of `PHASES`) and one per validation (the
step count, the seconds and the validation geodesic error), with the columns `LOG_COLUMNS`.
Under ``torchrun`` only rank 0 writes it.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import time
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import torch

from geofeat.train import checkpoints

log = logging.getLogger(__name__)

__all__ = ["LOG_COLUMNS", "PHASES", "PhaseTimer", "RunLog", "StepRecord", "open_run_log"]

#: Timed phases of a step, in order (the ``t_<phase>`` columns of ``log.csv``, seconds). Without
#: worker processes, ``geodesics`` is the reading of the geodesic matrix from the store and
#: ``partial`` the rotations and partial shapes; with workers, that work is done in the
#: background and ``partial`` is the time this process waited for the worker's samples (0 when
#: they were ready). Both ways ``geodesics`` includes the copy of the matrix (and the ground
#: truth) to the device and its widening to float32.
PHASES = ("geodesics", "partial", "render", "forward", "backproject", "loss", "backward", "optimizer")
#: The columns of ``log.csv``, in order.
LOG_COLUMNS = ("step", "elapsed_s", "loss", "n_partials", "val_geodesic_error", *(f"t_{p}" for p in PHASES))


@dataclass
class StepRecord:
    """What one step did: the step count after it, its loss (NaN when skipped) and seconds per phase."""

    step: int
    loss: float
    n_partials: int
    seconds: dict[str, float] = field(default_factory=dict)


class PhaseTimer:
    """Seconds per phase; on CUDA without waiting on the device.

    On the CPU, the wall seconds of each phase. On CUDA, the seconds the device's stream
    took from the phase's start to its end, from CUDA events read when `seconds` is asked
    for (after the step): the host keeps queuing work, so timing does not slow the step
    down. A phase in which the host works and the device waits (reading samples) counts the
    host's time, since the device reaches the phase's end only when the host has queued it.

    Parameters
    ----------
    device : torch.device
        The device of the timed work.
    """

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self._seconds: dict[str, float] = defaultdict(float)
        self._events: list[tuple[str, torch.cuda.Event, torch.cuda.Event]] = []

    @contextlib.contextmanager
    def __call__(self, phase: str):
        if self.cuda:
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            try:
                yield
            finally:
                end.record()
                self._events.append((phase, start, end))
            return
        start_time = time.perf_counter()
        try:
            yield
        finally:
            self._seconds[phase] += time.perf_counter() - start_time

    @property
    def seconds(self) -> dict[str, float]:
        """Seconds per phase so far (on CUDA this waits for the phases' work to finish)."""
        for phase, start, end in self._events:
            end.synchronize()
            self._seconds[phase] += start.elapsed_time(end) / 1000.0
        self._events.clear()
        return self._seconds


class RunLog:
    """``log.csv`` of a run, open for appending (`open_run_log`).

    Parameters
    ----------
    handle : file object
        ``log.csv`` opened for appending in text mode with ``newline=""``.
    """

    def __init__(self, handle: TextIO):
        self.handle = handle
        self.writer = csv.DictWriter(handle, fieldnames=LOG_COLUMNS)

    def step_row(self, record: StepRecord, elapsed: float) -> None:
        """Write the row of a step that ended ``elapsed`` seconds after training started (`GeoLoraTrainer.fit`)."""
        row = {"step": record.step, "elapsed_s": f"{elapsed:.3f}", "loss": f"{record.loss:.6f}", "n_partials": record.n_partials}
        row["val_geodesic_error"] = ""
        row.update({f"t_{p}": f"{record.seconds.get(p, 0.0):.4f}" for p in PHASES})
        self.writer.writerow(row)

    def validation_row(self, step: int, elapsed: float, error: float | None) -> None:
        """Log and write the validation ``error`` at ``step``; nothing when there is none (no validation set)."""
        if error is not None:
            log.info("step %d: validation geodesic error %.2f", step, error)
            self.writer.writerow({"step": step, "elapsed_s": f"{elapsed:.3f}", "val_geodesic_error": f"{error:.4f}"})

    def flush(self) -> None:
        """Hand the rows written so far to the operating system."""
        self.handle.flush()

    def sync(self) -> None:
        """Put the rows written so far on disk (before a checkpoint that follows them; `checkpoints.sync_log`)."""
        checkpoints.sync_log(self.handle)


@contextlib.contextmanager
def open_run_log(out: Path, main: bool = True) -> Iterator[RunLog | None]:
    """``out / "log.csv"`` opened for appending (its header written when it is new); None when not ``main``.

    Parameters
    ----------
    out : Path
        The run folder.
    main : bool
        Whether this process writes the log (rank 0); the other ranks get None.
    """
    if not main:
        yield None
        return
    log_path = out / "log.csv"
    new_log = not log_path.is_file()
    with open(log_path, "a", newline="") as handle:
        run_log = RunLog(handle)
        if new_log:
            run_log.writer.writeheader()
        yield run_log
