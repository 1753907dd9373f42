"""The GeoLoRA trainer: self-supervised LoRA training of DINOv3 on synthetic partial shapes.

One step (the GeoLoRA recipe):

1. take the next full shape (a seeded permutation per epoch) and its cached geodesics;
2. rotate it about the up axis by a random angle;
3. cut ``partials_per_shape`` partial shapes from it with a generator drawn from CUTS /
   HOLES / RAY, each turned by its own random angle about the up axis (the known vertex
   map is the ground truth);
4. render the full shape from ``views_full`` and every partial shape from ``views_partial``
   cameras of the official grid, run the LoRA backbone with gradients on all these views in
   one call, sample its patch features at the foreground pixels and back-project them to
   each shape, through `geofeat.multiview.pipeline.multiview_features_many`, the path of the
   ``geolora`` descriptor (vertices seen in no view keep zero features);
5. average the (geodesic-weighted) PointInfoNCE of the partial shapes, back-propagate, clip
   the gradient norm and take an Adam step.

The samples (a full shape with its rotation and partial shapes) form one seeded sequence:
sample ``g`` is the full shape at position ``g`` of the per-epoch permutations, with every
random draw from ``numpy.random.default_rng([seed, g])`` (`geofeat.train.samples` states the
rule). One process takes sample ``s`` at step ``s``, so a run resumed from a checkpoint
continues exactly as the uninterrupted run would have.

Steps 1 to 3 are CPU work (`geofeat.train.samples.prepare_sample`: reading the geodesic matrix,
the rotations, the partial shapes); steps 4 and 5 are the device's. With ``config.workers``
worker processes (`geofeat.train.sample_stream.SampleStream`, started by `GeoLoraTrainer.fit` or
by the first `GeoLoraTrainer.train_step`) the CPU work of the coming steps runs in the
background while the device computes the current one; with none it runs in this process at
the start of the step. Both give the same samples, so the same training to the bit.

Several processes (``torchrun``, one rank per GPU; see `GeoLoraTrainer.sample_indices`):
at each step rank ``r`` of ``W`` takes the ``shapes_per_rank`` samples from
``position + r * shapes_per_rank``, where ``position`` counts the samples of the earlier
steps (``s * W * shapes_per_rank`` when the rank count never changed). The LoRA gradients
summed over a rank's samples are all-reduced explicitly (one flattened tensor, not
`torch.nn.parallel.DistributedDataParallel`: the backbone is called several times a step
inside the rendering path, a rank may have no usable partial shape, and the loss is the
mean over the usable samples of all ranks) and divided by the number of usable samples, so
``W`` ranks with ``k`` shapes each compute what one process with ``W * k`` shapes computes.
Rank 0 alone reads and writes the run folder (checkpoints, ``log.csv``, validation) and
hands the state to the others at the start (`geofeat.train.rank_sync`). A checkpoint holds the step and the sample
position, so a run resumes on any number of ranks and continues the sequence without
repeating or skipping a sample (with another rank count, the grouping of samples into
steps differs from the uninterrupted run).

A run folder holds ``config.json``, ``log.csv`` (one row per step: loss, seconds per phase
of `PHASES`, validation error on validation steps; `geofeat.train.run_log`) and
``checkpoints/step_NNNNNNN/`` (a LoRA folder loadable by the ``geolora`` descriptor, with
``trainer_state.pt`` beside it). How checkpoints are written, read back and recovered after
a crash is `geofeat.train.checkpoints`; when a run may be resumed, `geofeat.train.resume`.
"""

from __future__ import annotations

import contextlib
import logging
import time
from pathlib import Path

import numpy as np
import torch

from geofeat.backbones import DinoBackbone, load_backbone
from geofeat.backbones.lora import LoraSettings, add_lora, load_lora
from geofeat.datasets.records import Match
from geofeat.errors import TrainingError
from geofeat.evaluation.protocol import evaluate_pair, summarize
from geofeat.mesh import Mesh
from geofeat.multiview.pipeline import RECIPES, MultiviewFeatures, multiview_features_many
from geofeat.render import make_cameras
from geofeat.runtime import distributed
from geofeat.runtime.progress import progress_bar
from geofeat.storage.files import probe_writable
from geofeat.train import checkpoints, rank_sync, resume
from geofeat.train.checkpoints import DeferredInterrupt
from geofeat.train.config import TrainConfig
from geofeat.train.geodesics import TorchGeodesicStore
from geofeat.train.losses import geodesic_point_info_nce, point_info_nce
from geofeat.train.run_log import LOG_COLUMNS, PHASES, PhaseTimer, StepRecord, open_run_log
from geofeat.train.sample_stream import SampleStream
from geofeat.train.samples import PreparedSample, SampleDataset, Timer, resolve_workers, rotate_about_up
from geofeat.train.shapes import load_training_shapes

log = logging.getLogger(__name__)

__all__ = [
    "PHASES",
    "GeoLoraTrainer",
    "StepRecord",
    "rotate_about_up",
]


class GeoLoraTrainer:
    """Train a LoRA on a frozen DINOv3 with the GeoLoRA recipe.

    Parameters
    ----------
    config : TrainConfig
    backbone : DinoBackbone, optional
        A DINOv3 backbone without LoRA; default: loaded from ``config.weights``.
    shapes : list of Mesh, optional
        Full shapes; default: loaded from ``config.data``.

    Notes
    -----
    ``fit()`` starts a new run in ``config.out`` or, when it already holds checkpoints,
    resumes from the newest one (the saved settings must agree with ``config`` except for
    `RESUMABLE_CHANGES`).

    Under ``torchrun`` (the variables RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR and
    MASTER_PORT set) the constructor starts the process group unless the caller did
    (`geofeat.runtime.distributed.init_process_group`: NCCL on a GPU, gloo on the CPU), ``device="auto"``
    (or ``"cuda"``) is the rank's local GPU, and ``self.ranks`` (a `geofeat.runtime.distributed.RankInfo`)
    says which rank this process is; every rank calls ``fit()``.
    """

    def __init__(self, config: TrainConfig, backbone: DinoBackbone | None = None, shapes: list[Mesh] | None = None):
        self.config = config
        self.device = distributed.local_device(config.device)
        distributed.init_process_group(self.device)  # under torchrun, unless the caller started one
        self.ranks = distributed.group_rank_info()
        self.progress = config.progress and self.ranks.is_main
        self.out = Path(config.out)
        try:  # before hours of loading: a file or a read-only place as the run folder
            probe_writable(self.out, prefix=".geofeat-write-check-")
        except OSError as err:
            raise TrainingError(
                f"cannot write the run folder {self.out}: {err}. Pass a folder you can write to as out."
            ) from None
        self.shapes = (
            shapes
            if shapes is not None
            else load_training_shapes(
                config.data,
                root=config.data_root,
                split=config.split,
                first=config.first,
                max_vertices=config.max_vertices,
                progress=self.progress,
            )
        )
        if not self.shapes:
            raise TrainingError(f"no training shape in {config.data!r}.")
        self.geodesics = TorchGeodesicStore(config.geodesic_cache)
        #: Worker processes that prepare the samples (`geofeat.train.samples.resolve_workers` of ``config.workers``).
        self.workers = resolve_workers(config.workers, self.device)
        #: The prepared samples of the steps (`SampleStream`): from the worker processes, or made when asked for.
        self.sample_stream = SampleStream(
            config,
            SampleDataset(config, self.shapes, self.geodesics.folder),
            self.sample_indices,
            self.workers,
            pin_memory=self.device.type == "cuda",
        )
        self.backbone = (
            backbone
            if backbone is not None
            else load_backbone(config.weights, kind="dinov3", layer=config.layer, device=self.device)
        )
        if self.backbone.kind != "dinov3":
            raise TrainingError(f"GeoLoRA adapts DINOv3; this backbone is {self.backbone.kind}.")
        self.backbone.model.to(self.device)
        if config.image_size % self.backbone.patch_size:
            raise TrainingError(
                f"image_size {config.image_size} is not a multiple of the backbone patch size {self.backbone.patch_size}."
            )
        self.step = 0
        self._origin = (0, 0)  # (step, global sample index of its first shape) of the start or the checkpoint resumed
        self.optimizer: torch.optim.Optimizer | None = None
        self._validation = None

    # ------------------------------------------------------------------ setup and checkpoints

    def _lora_settings(self) -> LoraSettings:
        return LoraSettings(
            rank=self.config.rank,
            alpha=self.config.alpha,
            shared_a=self.config.recipe == "reference",
            training=self.config.to_dict(),
        )

    def _start_or_resume(self) -> bool:
        """Start a new run or resume from the newest readable checkpoint; True when resumed.

        With several ranks, rank 0 alone reads and writes the run folder; it hands the others
        whether it resumed, the step and sample position and the optimizer state, and every
        rank then holds rank 0's LoRA weights (the run folder need not be shared by the nodes).
        """
        if self.ranks.world_size == 1:
            return self._start_or_resume_here()
        outcome = None
        if self.ranks.is_main:
            try:
                resumed = self._start_or_resume_here()
            except Exception as err:
                distributed.broadcast_from_main({"error": f"{type(err).__name__}: {err}"})
                raise
            optimizer = rank_sync.to_cpu(self.optimizer.state_dict()) if resumed else None
            outcome = {"error": None, "resumed": resumed, "origin": self._origin, "optimizer": optimizer}
        outcome = distributed.broadcast_from_main(outcome)
        if not self.ranks.is_main:
            if outcome["error"]:
                raise TrainingError(f"rank 0 could not start or resume the run in {self.out}: {outcome['error']}")
            self._add_lora()
            if outcome["resumed"]:
                self.optimizer.load_state_dict(outcome["optimizer"])  # moved to the parameters' device
            self._origin = tuple(outcome["origin"])
            self.step = self._origin[0]
        # rank 0's LoRA weights everywhere (the same seeded initialisation, or the checkpoint)
        rank_sync.broadcast_parameters(self._lora_parameters())
        return outcome["resumed"]

    def _add_lora(self) -> None:
        torch.manual_seed(self.config.seed)  # LoRA A initialisation
        add_lora(self.backbone, self._lora_settings())
        self._make_optimizer()

    def _lora_parameters(self) -> list[torch.nn.Parameter]:
        """The trained (LoRA) parameters, in the optimizer's order (the same on every rank)."""
        return [p for group in self.optimizer.param_groups for p in group["params"]]

    def _start_or_resume_here(self) -> bool:
        """`_start_or_resume` in the process that owns the run folder."""
        checkpoint, state = resume.checkpoint_to_resume(self.out, self.config, self.shapes, self.device)
        if checkpoint is None:
            self._add_lora()
            self._origin = (0, 0)
            self.out.mkdir(parents=True, exist_ok=True)
            self.config.save(self.out / "config.json")
            return False
        load_lora(self.backbone, checkpoint)
        self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        # checkpoints written before the sample position was saved come from single-process runs
        self._origin = (self.step, int(state.get("samples", self.step * self.config.shapes_per_rank)))
        self.config.save(self.out / "config.json")
        log.info("resumed %s at step %d (sample %d) from %s", self.out, self.step, self._origin[1], checkpoint)
        saved_world = int(state.get("world_size", 1))
        if saved_world != self.ranks.world_size:
            log.info(
                "the checkpoint was written by %d rank(s), this run has %d: the shape sequence continues from sample %d, "
                "%d shape(s) a step",
                saved_world,
                self.ranks.world_size,
                self._origin[1],
                self.ranks.world_size * self.config.shapes_per_rank,
            )
        return True

    def _make_optimizer(self) -> None:
        params = [p for p in self.backbone.model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(params, lr=self.config.lr)

    def save_checkpoint(self, extra: dict | None = None) -> Path:
        """Write ``checkpoints/step_NNNNNNN`` (LoRA + optimizer state) atomically; returns the folder.

        `geofeat.train.checkpoints.write_checkpoint`. Only rank 0 writes; on the other ranks
        this returns the folder without writing.
        """
        if not self.ranks.is_main:
            return checkpoints.checkpoint_folder(self.out, self.step)
        state = {
            "step": self.step,
            "samples": self._sample_position(self.step),
            "world_size": self.ranks.world_size,
            "optimizer": self.optimizer.state_dict(),
            "shapes": resume.shape_records(self.shapes),
        }
        return checkpoints.write_checkpoint(self.out, self.step, self.backbone, self._lora_settings(), state, extra)

    # ------------------------------------------------------------------ features

    def _autocast(self) -> bool:
        """bfloat16 autocast of the backbone: ``config.amp`` "on", or "auto" on CUDA."""
        return self.config.amp == "on" or (self.config.amp == "auto" and self.device.type == "cuda")

    def _rope_augmentation(self) -> bool:
        """Whether the training steps run DINOv3 in ``train()`` mode (``config.rope_augmentation``, or the recipe's)."""
        if self.config.rope_augmentation is not None:
            return self.config.rope_augmentation
        return self.config.recipe == "reference"

    @contextlib.contextmanager
    def _training_mode(self, sample_index: int):
        """The backbone in the training steps' mode for one sample; with RoPE augmentation, its draws seeded by the sample.

        The random RoPE rescaling uses torch's global generator: it is forked and seeded from
        ``(config.seed, sample_index)``, so a sample's draws do not depend on what ran before
        it (a resumed run, worker processes) and the caller's random state is left as it was.
        """
        if not self._rope_augmentation():
            yield
            return
        devices = [self.device] if self.device.type == "cuda" else []
        with torch.random.fork_rng(devices=devices):
            torch.manual_seed(int(np.random.default_rng([self.config.seed, sample_index, 2]).integers(2**63 - 1)))
            self.backbone.rope_augmentation = True
            try:
                yield
            finally:
                self.backbone.rope_augmentation = False

    def mesh_features(
        self, mesh: Mesh, n_views: int, timer: Timer | None = None, fill: str = "zero"
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Multi-view LoRA-DINOv3 features of a mesh, differentiable when gradients are enabled.

        `geofeat.multiview.pipeline.multiview_features` with the run's settings, all views in one batch;
        the ``geolora`` descriptor with the same views, image size, layout, back-projection,
        fill and LoRA gives the same features.

        Parameters
        ----------
        mesh : Mesh
            V vertices.
        n_views : int
            Cameras of ``config.camera_layout`` (not rotated).
        timer : PhaseTimer, optional
            Charged with "render", "forward" and "backproject".
        fill : {"zero", "nearest"}
            Features of vertices seen in no view.

        Returns
        -------
        features : torch.Tensor, shape (V, C), float32
            With an autograd graph to the LoRA parameters when the caller's autograd mode is
            on (`torch.is_grad_enabled`): training steps; validation runs under ``no_grad``.
        seen : torch.Tensor, shape (V,), bool
        """
        return self.meshes_features([mesh], [n_views], timer, fill)[0]

    def meshes_features(
        self, meshes: list[Mesh], n_views: list[int], timer: Timer | None = None, fill: str = "zero"
    ) -> list[MultiviewFeatures]:
        """`mesh_features` of several meshes, their views encoded together in one backbone call.

        `geofeat.multiview.pipeline.multiview_features_many` with the run's settings: a training
        step sends the full shape and its partial shapes at once (9 + 2 x 4 views).

        Parameters
        ----------
        meshes : list of Mesh
        n_views : list of int
            Views of each mesh.
        timer : PhaseTimer, optional
        fill : {"zero", "nearest"}

        Returns
        -------
        list of MultiviewFeatures
            One per mesh, as `mesh_features` returns it.
        """
        config = self.config
        cameras = [
            make_cameras(mesh, views, layout=config.camera_layout, image_size=config.image_size, device=self.device)
            for mesh, views in zip(meshes, n_views, strict=True)
        ]
        return multiview_features_many(
            meshes,
            cameras,
            self.backbone,
            recipe=RECIPES[config.recipe],
            backproject=config.backproject,
            fill=fill,
            grad=torch.is_grad_enabled(),
            autocast=self._autocast(),
            timer=timer,
        )

    # ------------------------------------------------------------------ one step

    def _sample_position(self, step: int) -> int:
        """Global index of the first sample of ``step`` (the samples drawn before it, on all ranks)."""
        origin_step, origin_sample = self._origin
        return origin_sample + (step - origin_step) * self.ranks.world_size * self.config.shapes_per_rank

    def sample_indices(self, step: int | None = None) -> range:
        """Global sample indices this rank trains on at ``step`` (default: the next step).

        Step ``s`` of a run on ``W`` ranks takes the ``W * shapes_per_rank`` samples after those
        of the earlier steps; rank ``r`` takes ``shapes_per_rank`` consecutive ones, from
        ``position(s) + r * shapes_per_rank``, where ``position(s) = s * W * shapes_per_rank`` for a
        run that kept its rank count (a resumed run continues from the position saved in
        its checkpoint). Sample ``g`` is `geofeat.train.samples.prepare_sample` of ``g``: the full shape
        ``geofeat.train.samples.shape_index(seed, n_shapes, g)`` with every draw from
        ``numpy.random.default_rng([seed, g])``: one process (``g = s``) draws as before.
        """
        step = self.step if step is None else step
        first = self._sample_position(step) + self.ranks.rank * self.config.shapes_per_rank
        return range(first, first + self.config.shapes_per_rank)

    def _loss(self, feat_partial, feat_full, gt, dist, seen_partial, seen_full) -> torch.Tensor:
        options = {"seen_partial": seen_partial, "seen_full": seen_full, "temperature": self.config.temperature}
        if self.config.loss == "geodesic":
            return geodesic_point_info_nce(feat_partial, feat_full, gt, dist, offset=self.config.offset, **options)
        return point_info_nce(feat_partial, feat_full, gt, **options)

    def sample_features(self, full: Mesh, partials: list[Mesh], timer: Timer) -> list[MultiviewFeatures]:
        """Features of the shapes of one sample: the full shape first, then each partial shape.

        Parameters
        ----------
        full : Mesh
            The turned full shape, V vertices; rendered from ``config.views_full`` cameras.
        partials : list of Mesh
            The turned partial shapes; each rendered from ``config.views_partial`` cameras.
        timer : PhaseTimer
            Charged with "render", "forward" and "backproject".

        Returns
        -------
        list of MultiviewFeatures
            ``1 + len(partials)`` pairs of `mesh_features`: features (n, C) float32 with their
            autograd graph, and ``seen`` (n,) bool. All views go through the backbone in one call
            (`meshes_features`).
        """
        config = self.config
        views = [config.views_full] + [config.views_partial] * len(partials)
        return self.meshes_features([full, *partials], views, timer)

    def _sample_loss(self, sample: PreparedSample, timer: Timer) -> tuple[torch.Tensor | None, int]:
        """The mean loss of the partial shapes of a prepared sample and their number (None, 0: none usable).

        A partial shape without a loss (no vertex seen on both shapes) is left out; under
        ``recipe="reference"`` it leaves the whole sample out, as the official loop skips a
        step whose loss is NaN.

        The sample's CPU tensors go to the device here (asynchronously when pinned), the
        geodesic matrix widened there from float16 to float32.
        """
        with timer("geodesics"):
            dist = sample.geodesics.to(self.device, non_blocking=True).float()
            gts = [gt.to(self.device, non_blocking=True) for _, gt in sample.partials]
        with self._training_mode(sample.index):
            features = self.sample_features(sample.full, [mesh for mesh, _ in sample.partials], timer)
        feat_full, seen_full = features[0]
        losses = []
        for (feat_partial, seen_partial), gt in zip(features[1:], gts, strict=True):
            with timer("loss"):
                try:
                    losses.append(self._loss(feat_partial, feat_full, gt, dist, seen_partial, seen_full))
                except TrainingError as err:  # e.g. no partial vertex seen
                    if self.config.recipe == "reference":  # the official loop skips the step (its loss is NaN)
                        log.warning("step %d: skipped sample %d of %s: %s", self.step, sample.index, sample.full.name, err)
                        return None, 0
                    log.warning(
                        "step %d, sample %d: skipped a partial shape of %s: %s", self.step, sample.index, sample.full.name, err
                    )
        if not losses:
            return None, 0
        return torch.stack(losses).mean(), len(losses)

    def close(self) -> None:
        """Stop the worker processes that prepare samples, if any, and wait for them.

        `fit` does it before it returns or raises; call it after running `train_step`
        yourself with ``workers`` (a later `train_step` starts them again).
        """
        self.sample_stream.close()

    def train_step(self) -> StepRecord:
        """One optimisation step (see the module notes and `sample_indices`); skipped (loss NaN) when no partial shape is usable.

        The loss is the mean, over the usable samples of the step on all ranks, of each
        sample's mean partial loss; each sample is back-propagated on its own and the summed
        gradients are all-reduced and divided by the number of usable samples, so ``W``
        ranks with ``shapes_per_rank=k`` train exactly as one process with ``shapes_per_rank=W*k``.
        """
        config = self.config
        timer = PhaseTimer(self.device)
        self.backbone.model.eval()
        self.optimizer.zero_grad(set_to_none=True)
        loss_sum, n_shapes, n_partials = 0.0, 0, 0
        for sample in self.sample_stream.next_samples(self.step, timer):
            loss, count = self._sample_loss(sample, timer)
            if loss is None:
                continue
            with timer("backward"):
                loss.backward()
            loss_sum, n_shapes, n_partials = loss_sum + float(loss.detach()), n_shapes + 1, n_partials + count
        if self.ranks.world_size > 1:
            with timer("optimizer"):
                totals = torch.tensor([loss_sum, n_shapes, n_partials], dtype=torch.float64, device=self.device)
                totals = distributed.all_reduce_sum(totals).tolist()
            loss_sum, n_shapes, n_partials = totals[0], round(totals[1]), round(totals[2])
        if n_shapes == 0:
            self.step += 1
            return StepRecord(self.step, float("nan"), 0, dict(timer.seconds))
        with timer("optimizer"):
            rank_sync.average_gradients(self._lora_parameters(), n_shapes, self.ranks.world_size)
            torch.nn.utils.clip_grad_norm_(self._lora_parameters(), max_norm=config.grad_clip)
            self.optimizer.step()
        self.step += 1
        return StepRecord(self.step, loss_sum / n_shapes, n_partials, dict(timer.seconds))

    # ------------------------------------------------------------------ validation

    @torch.no_grad()
    def validate(self) -> float | None:
        """Mean nearest-neighbour P2F geodesic error (x100) on ``config.val_pairs`` pairs of ``config.val_dataset``.

        Features use the training view counts (``views_full`` for the full shape,
        ``views_partial`` for the partial one), unseen vertices filled from the nearest seen
        one; the protocol of `geofeat.evaluation.protocol` (``"vertices"``), with the distances of the
        trainer's float16 geodesic store (about three significant digits). None when no
        validation set.
        """
        config = self.config
        if not config.val_dataset or config.val_pairs == 0:
            return None
        if self._validation is None:
            from geofeat.datasets import load_dataset

            self._validation = load_dataset(config.val_dataset, root=config.data_root, split=config.val_split)
        dataset = self._validation
        timer = PhaseTimer(self.device)
        records = []
        n_pairs = min(config.val_pairs, len(dataset))
        for i in progress_bar(range(n_pairs), desc="validation", unit="pair", leave=False, show=config.progress):
            pair = dataset[i]
            feat_x, _ = self.mesh_features(pair.x, config.views_full, timer, fill="nearest")
            feat_y, _ = self.mesh_features(pair.y, config.views_partial, timer, fill="nearest")
            predicted = torch.cdist(feat_y, feat_x).argmin(dim=1).cpu().numpy()
            match = Match(predicted, np.ones(pair.y.n_vertices, dtype=bool))
            records.append(evaluate_pair(pair, match, "vertices", distances=self.geodesics.load(pair.x).numpy()))
        return summarize(records).geodesic_error

    # ------------------------------------------------------------------ the loop

    def fit(self) -> Path:
        """Train until ``config.steps`` (or ``config.max_minutes``); returns the last checkpoint folder.

        Validates at the start of a new run, every ``validate_every`` steps and at the end;
        checkpoints every ``checkpoint_every`` steps and at the end. The first Ctrl-C finishes
        the current step, saves a checkpoint and raises ``KeyboardInterrupt``. The sample
        workers (``config.workers``) start before the first validation and are stopped (and
        waited for) before this returns or raises.

        Under ``torchrun`` every rank calls this; rank 0 alone writes ``log.csv``, validates
        and saves checkpoints, while the others go on to the next step's all-reduce (which
        waits for rank 0). A stop (Ctrl-C on any rank, the time budget on any rank) is agreed
        on by all ranks before each step, so they stop after the same step; all ranks return
        once the last checkpoint is on disk.
        """
        config, main, world = self.config, self.ranks.is_main, self.ranks.world_size
        self.close()  # workers started by earlier train_step calls stand at the position before resuming
        resumed = self._start_or_resume()
        if main:
            checkpoints.truncate_log(self.out, self.step if resumed else None, LOG_COLUMNS)
        mine = distributed.shard(self.shapes, self.ranks)  # the one-off Dijkstra, shared out among the ranks
        for mesh in progress_bar(mine, desc="geodesics", unit="shape", show=self.progress):
            self.geodesics.ensure(mesh)
        distributed.barrier()  # (a rank that does not see the shared store computes what it lacks on first use)
        start = time.perf_counter()
        # the deferred Ctrl-C is in place before the sample workers are forked: a Ctrl-C during their start (in
        # logging's at-fork hook, say) is a request to stop like any other, never an exception swallowed there
        with (
            DeferredInterrupt() as interrupt,
            self.sample_stream.running(self.step),
            open_run_log(self.out, main) as run_log,
        ):
            if not resumed and main:
                run_log.validation_row(self.step, 0.0, self.validate())
                run_log.sync()
                self.save_checkpoint()
            bar = progress_bar(total=config.steps, initial=self.step, desc="GeoLoRA", unit="step", show=self.progress)
            while self.step < config.steps and not rank_sync.any_rank(interrupt.requested, world, self.device):
                record = self.train_step()
                elapsed = time.perf_counter() - start
                if main:
                    run_log.step_row(record, elapsed)
                bar.update(1)
                bar.set_postfix(loss=f"{record.loss:.4f}")
                over_budget = config.max_minutes is not None and elapsed > 60.0 * config.max_minutes
                out_of_time = rank_sync.any_rank(over_budget, world, self.device)
                if main and config.validate_every and self.step % config.validate_every == 0 and self.step < config.steps:
                    if not out_of_time:
                        run_log.validation_row(self.step, elapsed, self.validate())
                if main and config.checkpoint_every and self.step % config.checkpoint_every == 0:
                    run_log.sync()
                    self.save_checkpoint()
                if main:
                    run_log.flush()
                if out_of_time:
                    log.info("time budget of %.1f minutes spent at step %d", config.max_minutes, self.step)
                    break
            interrupted = rank_sync.any_rank(interrupt.requested, world, self.device)
            bar.close()
            if interrupted:
                if main:
                    run_log.sync()
                checkpoint = self.save_checkpoint()
                distributed.barrier()
                log.warning("interrupted: stopped after step %d; resume with the same out folder (%s)", self.step, checkpoint)
                raise KeyboardInterrupt
            if main:
                run_log.validation_row(self.step, time.perf_counter() - start, self.validate())
                run_log.sync()
            final = self.save_checkpoint()
        distributed.barrier()  # the other ranks return once rank 0 has written the last checkpoint
        return final
