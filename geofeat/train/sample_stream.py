"""The stream of prepared samples a GeoLoRA run trains on, step after step.

With worker processes (``config.workers``), a `geofeat.train.samples.SamplePrefetcher`
prepares the samples of the coming steps in the background while the device computes the
current one; it is started at a step and hands out that step's samples, then the next
step's. Without workers, or past ``config.steps``, the samples are made in this process when
asked for. Both give the same samples (`geofeat.train.samples.prepare_sample`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator

from geofeat.train.config import TrainConfig
from geofeat.train.samples import PreparedSample, SampleDataset, SamplePrefetcher, Timer

__all__ = ["SampleStream"]


class SampleStream:
    """The prepared samples of a run's steps, from worker processes or made here.

    Parameters
    ----------
    config : TrainConfig
        The run's settings: ``steps`` (the workers prepare no step at or past it) and
        ``seed`` (the loader's own generator) are read when the workers start.
    dataset : SampleDataset
        Makes sample ``g`` (`SampleDataset.prepare`).
    sample_indices : callable
        ``sample_indices(step)``: the global sample indices this process trains on at ``step``
        (`geofeat.train.trainer.GeoLoraTrainer.sample_indices`).
    workers : int
        Worker processes; 0 makes every sample in this process.
    pin_memory : bool
        The workers' tensors in page-locked memory (a CUDA trainer).

    Notes
    -----
    The workers run from `start` (or the first `next_samples` that needs them) until
    `close`; `running` stops them however its block ends.
    """

    def __init__(
        self,
        config: TrainConfig,
        dataset: SampleDataset,
        sample_indices: Callable[[int], range],
        workers: int,
        pin_memory: bool = False,
    ):
        self.config = config
        self.dataset = dataset
        self.sample_indices = sample_indices
        self.workers = workers
        self.pin_memory = pin_memory
        self._prefetcher: SamplePrefetcher | None = None

    @property
    def prefetcher(self) -> SamplePrefetcher | None:
        """The running worker processes; None when stopped (or without workers)."""
        return self._prefetcher

    def next_samples(self, step: int, timer: Timer) -> list[PreparedSample]:
        """The prepared samples of ``step`` (``sample_indices(step)``).

        With worker processes: from the running `SamplePrefetcher`, started (or restarted)
        at ``step`` when there is none or it stands at another step (the wait is charged to
        "partial"); made here when the step is past ``config.steps`` (the loader prepares no
        further). Without: made here, charged to "geodesics" and "partial".

        Parameters
        ----------
        step : int
        timer : callable
            ``timer(phase)``: a context manager charging the seconds of its block to ``phase``.

        Returns
        -------
        list of PreparedSample
            One per index of ``sample_indices(step)``, in their order.
        """
        if self.workers > 0 and step < self.config.steps:
            if self._prefetcher is None or self._prefetcher.next_step != step:
                self.start(step)
            with timer("partial"):
                samples = self._prefetcher.take(step)
            if samples is not None:
                return samples
        return [self.dataset.prepare(index, timer) for index in self.sample_indices(step)]

    def start(self, step: int) -> None:
        """(Re)start the worker processes at ``step``, up to ``config.steps``; nothing without workers."""
        self.close()
        if self.workers > 0 and step < self.config.steps:
            self._prefetcher = SamplePrefetcher(
                self.dataset,
                self.sample_indices,
                step,
                self.config.steps,
                self.workers,
                pin_memory=self.pin_memory,
                seed=self.config.seed,
            )

    @contextlib.contextmanager
    def running(self, step: int) -> Iterator[None]:
        """The worker processes run inside the block from ``step`` (none without workers); they are stopped however it ends."""
        self.start(step)
        try:
            yield
        finally:
            self.close()

    def close(self) -> None:
        """Stop the worker processes, if any, and wait for them."""
        prefetcher, self._prefetcher = self._prefetcher, None
        if prefetcher is not None:
            prefetcher.close()
