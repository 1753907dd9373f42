"""The GeoLoRA trainer: self-supervised LoRA training of DINOv3 on synthetic partial shapes.

One step (the GeoLoRA recipe):

1. take the next full shape (a seeded permutation per epoch) and its cached geodesics;
2. rotate it about the up axis by a random angle;
3. cut ``partials_per_shape`` partial shapes from it with a generator drawn from CUTS /
   HOLES / RAY, each turned by its own random angle about the up axis (the known vertex
   map is the ground truth);
4. render the full shape from ``views_full`` and every partial shape from ``views_partial``
   cameras of the official grid, run the LoRA backbone with gradients, sample its patch
   features at the foreground pixels and back-project them, through
   `geofeat.render.multiview_features`, the path of the ``geolora`` descriptor (vertices seen
   in no view keep zero features);
5. average the (geodesic-weighted) PointInfoNCE of the partial shapes, back-propagate, clip
   the gradient norm and take an Adam step.

Every random draw of step ``s`` comes from ``numpy.random.default_rng([seed, s])``, so a
run resumed from a checkpoint continues exactly as the uninterrupted run would have.

A run folder holds ``config.json``, ``log.csv`` (one row per step: loss, seconds per phase,
validation error on validation steps) and ``checkpoints/step_NNNNNNN/`` (the adapter as
``adapter.safetensors`` + ``adapter_config.json``, loadable by the ``geolora`` descriptor,
and ``trainer_state.pt`` with the optimizer state). Checkpoints are written to a temporary
folder ``.step_NNNNNNN.tmp-PID``, every file and the folder ``fsync``-ed, then renamed, so an
interruption never leaves a half-written one; the log rows up to a checkpoint's step are on
disk before the checkpoint is.

After a crash (``kill -9``, power cut) a resumed run

* drops the log rows of steps after the checkpoint it resumes from (they are trained again);
* falls back to the previous checkpoint, with a warning, when the newest one cannot be read
  (a truncated ``trainer_state.pt`` or adapter); the damaged folder is renamed
  ``.step_NNNNNNN.damaged``;
* removes the temporary folders of saves that were killed (their process is gone).
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import re
import shutil
import signal
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from geofeat.backbones import DinoBackbone, load_backbone
from geofeat.backbones.lora import LoraSettings, add_lora, load_adapter, save_adapter
from geofeat.datasets.records import Match
from geofeat.devices import resolve_device
from geofeat.evaluation import evaluate_pair, summarize
from geofeat.files import atomic_write, fsync_folder, fsync_tree, load_torch_file
from geofeat.geometry.partial import make_partial
from geofeat.mesh import Mesh
from geofeat.render import make_cameras, multiview_features
from geofeat.train.config import RESUMABLE_CHANGES, TrainConfig
from geofeat.train.errors import TrainingError
from geofeat.train.losses import geodesic_point_info_nce, point_info_nce
from geofeat.train.shapes import GeodesicStore, load_training_shapes

log = logging.getLogger(__name__)

__all__ = [
    "PHASES",
    "GeoLoraTrainer",
    "StepRecord",
    "complete_checkpoints",
    "latest_checkpoint",
    "remove_stale_temporary_folders",
    "rotate_about_up",
]

#: Timed phases of a step, in order.
PHASES = ("geodesics", "partial", "render", "forward", "backproject", "loss", "backward", "optimizer")
_STATE_FILE = "trainer_state.pt"
_LOG_COLUMNS = ("step", "elapsed_s", "loss", "n_partials", "val_geodesic_error", *(f"t_{p}" for p in PHASES))
_TMP_FOLDER = re.compile(r"\.step_\d+\.tmp-(\d+)")


class _DamagedCheckpoint(TrainingError):
    """A checkpoint file that cannot be read (truncated, not written by torch.save); resuming falls back."""


def rotate_about_up(mesh: Mesh, angle_degrees: float) -> Mesh:
    """The mesh turned about the y (up) axis through the origin; same vertex order.

    Parameters
    ----------
    mesh : Mesh
    angle_degrees : float

    Returns
    -------
    Mesh
    """
    a = math.radians(angle_degrees)
    rotation = np.array([[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]])
    return Mesh(mesh.verts @ rotation.T, mesh.faces, mesh.name)


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
    return sorted(p for p in folder.glob("step_*") if p.is_dir() and (p / _STATE_FILE).is_file())


def latest_checkpoint(run: str | os.PathLike) -> Path | None:
    """The newest complete checkpoint folder of a run folder, or None."""
    done = complete_checkpoints(run)
    return done[-1] if done else None


def _process_alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # a save of this process is never under way when this is asked
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    except OSError:
        return False
    return True


def remove_stale_temporary_folders(run: str | os.PathLike) -> list[Path]:
    """Delete the ``.step_NNNNNNN.tmp-PID`` folders of checkpoint saves whose process is gone.

    Parameters
    ----------
    run : str or os.PathLike
        A run folder.

    Returns
    -------
    list of pathlib.Path
        The folders removed (a warning names them).
    """
    folder = Path(run) / "checkpoints"
    removed = []
    if not folder.is_dir():
        return removed
    for path in sorted(folder.iterdir()):
        match = _TMP_FOLDER.fullmatch(path.name)
        if match and path.is_dir() and not _process_alive(int(match.group(1))):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    if removed:
        log.warning("removed %d unfinished checkpoint folder(s) of killed saves: %s", len(removed), [p.name for p in removed])
    return removed


@dataclass
class StepRecord:
    """What one step did: the step count after it, its loss (NaN when skipped) and seconds per phase."""

    step: int
    loss: float
    n_partials: int
    seconds: dict[str, float] = field(default_factory=dict)


class _Timer:
    """Adds wall seconds per phase, synchronising CUDA so GPU work is charged to its phase."""

    def __init__(self, device: torch.device):
        self.cuda = device.type == "cuda"
        self.seconds: dict[str, float] = defaultdict(float)

    @contextlib.contextmanager
    def __call__(self, phase: str):
        if self.cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        try:
            yield
        finally:
            if self.cuda:
                torch.cuda.synchronize()
            self.seconds[phase] += time.perf_counter() - start


class _DeferredInterrupt:
    """Turn the first Ctrl-C into a request to stop after the current step (a second one stops at once)."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        log.warning("Ctrl-C: finishing the current step, then saving a checkpoint (press again to stop at once)")

    def __enter__(self) -> _DeferredInterrupt:
        if threading.current_thread() is threading.main_thread():
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)


class GeoLoraTrainer:
    """Train a LoRA adapter on a frozen DINOv3 with the GeoLoRA recipe.

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
    """

    def __init__(self, config: TrainConfig, backbone: DinoBackbone | None = None, shapes: list[Mesh] | None = None):
        self.config = config
        self.device = resolve_device(config.device)
        self.out = Path(config.out)
        self.shapes = shapes if shapes is not None else load_training_shapes(
            config.data, root=config.data_root, split=config.split, first=config.first,
            max_vertices=config.max_vertices, progress=config.progress,
        )  # fmt: skip
        if not self.shapes:
            raise TrainingError(f"no training shape in {config.data!r}.")
        self.geodesics = GeodesicStore(config.geodesic_cache)
        self.backbone = backbone if backbone is not None else load_backbone(config.weights, kind="dinov3", layer=config.layer)
        if self.backbone.kind != "dinov3":
            raise TrainingError(f"GeoLoRA adapts DINOv3; this backbone is {self.backbone.kind}.")
        self.backbone.model.to(self.device)
        if config.image_size % self.backbone.patch_size:
            raise TrainingError(
                f"image_size {config.image_size} is not a multiple of the backbone patch size {self.backbone.patch_size}."
            )
        self.step = 0
        self.optimizer: torch.optim.Optimizer | None = None
        self._validation = None

    # ------------------------------------------------------------------ setup and checkpoints

    def _lora_settings(self) -> LoraSettings:
        return LoraSettings(rank=self.config.rank, alpha=self.config.alpha, training=self.config.to_dict())

    def _start_or_resume(self) -> bool:
        """Start a new run or resume from the newest readable checkpoint; True when resumed."""
        remove_stale_temporary_folders(self.out)
        checkpoint, state = self._readable_checkpoint()
        if checkpoint is None:
            torch.manual_seed(self.config.seed)  # LoRA A initialisation
            add_lora(self.backbone, self._lora_settings())
            self._make_optimizer()
            self.out.mkdir(parents=True, exist_ok=True)
            self.config.save(self.out / "config.json")
            return False
        saved = TrainConfig.from_file(self.out / "config.json")
        changed = sorted(set(self.config.changes_from(saved)) - RESUMABLE_CHANGES - {"out"})
        if changed:
            raise TrainingError(
                f"{self.out} holds a run with other settings ({', '.join(f'{n}={getattr(saved, n)!r}' for n in changed)}); "
                "resume it with the same settings or choose another out folder."
            )
        load_adapter(self.backbone, checkpoint)
        self._make_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.step = int(state["step"])
        self.config.save(self.out / "config.json")
        log.info("resumed %s at step %d from %s", self.out, self.step, checkpoint)
        return True

    def _read_checkpoint(self, folder: Path) -> dict:
        """The trainer state of a checkpoint folder, after checking that its adapter files can be read.

        Raises
        ------
        _DamagedCheckpoint
            A file is truncated or unreadable, or the state does not fit the folder.
        TrainingError
            ``trainer_state.pt`` is a pickle refused for safety.
        """
        state = load_torch_file(
            folder / _STATE_FILE, TrainingError, damaged_error=_DamagedCheckpoint, what="a trainer state",
            map_location=self.device,
        )  # fmt: skip
        if not isinstance(state, dict) or not {"step", "optimizer"} <= set(state):
            raise _DamagedCheckpoint(f"{folder / _STATE_FILE} lacks 'step' or 'optimizer'; it was not written by the trainer.")
        expected = int(folder.name.split("_")[-1])
        if int(state["step"]) != expected:
            raise _DamagedCheckpoint(f"{folder / _STATE_FILE} is for step {int(state['step'])}, its folder for step {expected}.")
        try:
            import safetensors.torch

            safetensors.torch.load_file(str(folder / "adapter.safetensors"))
            json.loads((folder / "adapter_config.json").read_text())
        except Exception as exc:  # SafetensorError, OSError, JSONDecodeError have no common base class
            raise _DamagedCheckpoint(f"the adapter in {folder} cannot be read ({type(exc).__name__}: {exc}).") from exc
        return state

    def _readable_checkpoint(self) -> tuple[Path | None, dict | None]:
        """The newest checkpoint whose files can all be read, with its state; damaged newer ones are set aside."""
        candidates = complete_checkpoints(self.out)
        for folder in reversed(candidates):
            try:
                return folder, self._read_checkpoint(folder)
            except _DamagedCheckpoint as err:
                aside = folder.with_name(f".{folder.name}.damaged")
                shutil.rmtree(aside, ignore_errors=True)
                os.replace(folder, aside)
                log.warning(
                    "checkpoint %s is damaged (%s); moved it to %s and fell back to the previous one", folder, err, aside.name
                )
        if candidates:
            raise TrainingError(
                f"no checkpoint of {self.out} can be read (all {len(candidates)} were damaged and moved to "
                f"{self.out / 'checkpoints'}/.step_*.damaged); start again with another out folder."
            )
        return None, None

    def _make_optimizer(self) -> None:
        params = [p for p in self.backbone.model.parameters() if p.requires_grad]
        self.optimizer = torch.optim.Adam(params, lr=self.config.lr)

    def save_checkpoint(self, extra: dict | None = None) -> Path:
        """Write ``checkpoints/step_NNNNNNN`` (adapter + optimizer state) atomically; returns the folder."""
        final = self.out / "checkpoints" / f"step_{self.step:07d}"
        if (final / _STATE_FILE).is_file():
            return final
        tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        try:
            save_adapter(self.backbone, tmp, self._lora_settings(), extra_info={"step": self.step, **(extra or {})})
            torch.save({"step": self.step, "optimizer": self.optimizer.state_dict()}, tmp / _STATE_FILE)
            fsync_tree(tmp)  # the files and the folder are on disk before the rename makes them the checkpoint
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        shutil.rmtree(final, ignore_errors=True)  # an incomplete one (no state file) from a crash
        os.replace(tmp, final)
        fsync_folder(final.parent)
        log.info("saved checkpoint %s", final)
        return final

    def _truncate_log(self, last_step: int | None) -> None:
        """Keep the complete rows of ``log.csv`` up to ``last_step`` (None: no row), dropping the rest.

        Rows after the checkpoint a run resumes from were written by the killed process and
        are written again by the resumed one; a kill can also leave half a row.
        """
        path = self.out / "log.csv"
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
            complete = None not in row and all(row.get(c) is not None for c in _LOG_COLUMNS)
            if last_step is not None and step <= last_step and complete:
                kept.append(row)
        if len(kept) != len(rows) or not rows:

            def write(tmp: Path) -> None:
                with open(tmp, "w", newline="") as out:
                    writer = csv.DictWriter(out, fieldnames=_LOG_COLUMNS, extrasaction="ignore")
                    writer.writeheader()
                    writer.writerows(kept)

            atomic_write(path, write)
            where = "a new run" if last_step is None else f"the checkpoint of step {last_step}"
            log.info("log.csv: dropped %d row(s) written after %s", len(rows) - len(kept), where)

    @staticmethod
    def _sync_log(handle) -> None:
        """Put the log rows written so far on disk (before a checkpoint that follows them)."""
        handle.flush()
        os.fsync(handle.fileno())

    # ------------------------------------------------------------------ features

    def _autocast(self) -> bool:
        """bfloat16 autocast of the backbone: ``config.amp`` "on", or "auto" on CUDA."""
        return self.config.amp == "on" or (self.config.amp == "auto" and self.device.type == "cuda")

    def shape_features(
        self, mesh: Mesh, n_views: int, timer: _Timer | None = None, fill: str = "zero"
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Multi-view LoRA-DINOv3 features of a mesh, differentiable when gradients are enabled.

        `geofeat.render.multiview_features` with the run's settings, all views in one batch;
        the ``geolora`` descriptor with the same views, image size, layout, back-projection,
        fill and adapter gives the same features.

        Parameters
        ----------
        mesh : Mesh
            V vertices.
        n_views : int
            Cameras of ``config.camera_layout`` (not rotated).
        timer : _Timer, optional
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
        cameras = make_cameras(
            mesh, n_views, layout=self.config.camera_layout, image_size=self.config.image_size, device=self.device
        )
        return multiview_features(
            mesh, cameras, self.backbone, backproject=self.config.backproject, fill=fill,
            grad=torch.is_grad_enabled(), autocast=self._autocast(), timer=timer,
        )  # fmt: skip

    # ------------------------------------------------------------------ one step

    def _shape_index(self, step: int) -> int:
        n = len(self.shapes)
        order = np.random.default_rng([self.config.seed, step // n, 1]).permutation(n)
        return int(order[step % n])

    def _loss(self, feat_partial, feat_full, gt, dist, seen_partial, seen_full) -> torch.Tensor:
        options = {"seen_partial": seen_partial, "seen_full": seen_full, "temperature": self.config.temperature}
        if self.config.loss == "geodesic":
            return geodesic_point_info_nce(feat_partial, feat_full, gt, dist, offset=self.config.offset, **options)
        return point_info_nce(feat_partial, feat_full, gt, **options)

    def train_step(self) -> StepRecord:
        """One optimisation step (see the module notes); skipped (loss NaN) when no partial shape is usable."""
        config, step = self.config, self.step
        timer = _Timer(self.device)
        rng = np.random.default_rng([config.seed, step])
        mesh = self.shapes[self._shape_index(step)]
        with timer("geodesics"):
            dist = self.geodesics.load(mesh, self.device)
        with timer("partial"):
            full = rotate_about_up(mesh, rng.uniform(0.0, 360.0))
            partials = []
            for _ in range(config.partials_per_shape):
                kind = config.partial_kinds[rng.integers(len(config.partial_kinds))]
                partial = make_partial(full, kind, seed=int(rng.integers(2**63 - 1)))
                turned = rotate_about_up(partial.mesh, rng.uniform(0.0, 360.0))
                gt = torch.tensor(partial.vertex_map, dtype=torch.int64, device=self.device)
                partials.append((turned, gt))
        self.backbone.model.eval()
        feat_full, seen_full = self.shape_features(full, config.views_full, timer)
        losses = []
        for turned, gt in partials:
            feat_partial, seen_partial = self.shape_features(turned, config.views_partial, timer)
            with timer("loss"):
                try:
                    losses.append(self._loss(feat_partial, feat_full, gt, dist, seen_partial, seen_full))
                except TrainingError as err:  # e.g. no partial vertex seen: as the release, skip
                    log.warning("step %d: skipped a partial shape of %s: %s", step, mesh.name, err)
        self.optimizer.zero_grad(set_to_none=True)
        if not losses:
            self.step += 1
            return StepRecord(self.step, float("nan"), 0, dict(timer.seconds))
        loss = torch.stack(losses).mean()
        with timer("backward"):
            loss.backward()
        with timer("optimizer"):
            params = [p for group in self.optimizer.param_groups for p in group["params"]]
            torch.nn.utils.clip_grad_norm_(params, max_norm=config.grad_clip)
            self.optimizer.step()
        self.step += 1
        return StepRecord(self.step, float(loss.detach()), len(losses), dict(timer.seconds))

    # ------------------------------------------------------------------ validation

    @torch.no_grad()
    def validate(self) -> float | None:
        """Mean nearest-neighbour P2F geodesic error (x100) on ``config.val_pairs`` pairs of ``config.val_dataset``.

        Features use the training view counts (``views_full`` for the full shape,
        ``views_partial`` for the partial one), unseen vertices filled from the nearest seen
        one; the protocol of `geofeat.evaluation` (``"vertices"``), with the distances of the
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
        timer = _Timer(self.device)
        records = []
        n_pairs = min(config.val_pairs, len(dataset))
        for i in tqdm(range(n_pairs), desc="validation", unit="pair", leave=False, disable=not config.progress):
            pair = dataset[i]
            feat_x, _ = self.shape_features(pair.x, config.views_full, timer, fill="nearest")
            feat_y, _ = self.shape_features(pair.y, config.views_partial, timer, fill="nearest")
            predicted = torch.cdist(feat_y, feat_x).argmin(dim=1).cpu().numpy()
            match = Match(predicted, np.ones(pair.y.n_vertices, dtype=bool))
            records.append(evaluate_pair(pair, match, "vertices", distances=self.geodesics.load(pair.x).numpy()))
        return summarize(records).geodesic_error

    # ------------------------------------------------------------------ the loop

    def _log_row(self, writer, record: StepRecord, elapsed: float, val_error: float | None) -> None:
        row = {"step": record.step, "elapsed_s": f"{elapsed:.3f}", "loss": f"{record.loss:.6f}", "n_partials": record.n_partials}
        row["val_geodesic_error"] = "" if val_error is None else f"{val_error:.4f}"
        row.update({f"t_{p}": f"{record.seconds.get(p, 0.0):.4f}" for p in PHASES})
        writer.writerow(row)

    def _validation_row(self, writer, elapsed: float) -> float | None:
        error = self.validate()
        if error is not None:
            log.info("step %d: validation geodesic error %.2f", self.step, error)
            writer.writerow({"step": self.step, "elapsed_s": f"{elapsed:.3f}", "val_geodesic_error": f"{error:.4f}"})
        return error

    def fit(self) -> Path:
        """Train until ``config.steps`` (or ``config.max_minutes``); returns the last checkpoint folder.

        Validates at the start of a new run, every ``validate_every`` steps and at the end;
        checkpoints every ``checkpoint_every`` steps and at the end. The first Ctrl-C finishes
        the current step, saves a checkpoint and raises ``KeyboardInterrupt``.
        """
        config = self.config
        resumed = self._start_or_resume()
        self._truncate_log(self.step if resumed else None)
        for mesh in tqdm(self.shapes, desc="geodesics", unit="shape", disable=not config.progress):
            self.geodesics.ensure(mesh)
        log_path = self.out / "log.csv"
        new_log = not log_path.is_file()
        start = time.perf_counter()
        with open(log_path, "a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=_LOG_COLUMNS)
            if new_log:
                writer.writeheader()
            if not resumed:
                self._validation_row(writer, 0.0)
                self._sync_log(handle)
                self.save_checkpoint()
            bar = tqdm(total=config.steps, initial=self.step, desc="GeoLoRA", unit="step", disable=not config.progress)
            with _DeferredInterrupt() as interrupt:
                while self.step < config.steps and not interrupt.requested:
                    record = self.train_step()
                    elapsed = time.perf_counter() - start
                    self._log_row(writer, record, elapsed, None)
                    bar.update(1)
                    bar.set_postfix(loss=f"{record.loss:.4f}")
                    out_of_time = config.max_minutes is not None and elapsed > 60.0 * config.max_minutes
                    if config.validate_every and self.step % config.validate_every == 0 and self.step < config.steps:
                        if not out_of_time:
                            self._validation_row(writer, elapsed)
                    if config.checkpoint_every and self.step % config.checkpoint_every == 0:
                        self._sync_log(handle)
                        self.save_checkpoint()
                    handle.flush()
                    if out_of_time:
                        log.info("time budget of %.1f minutes spent at step %d", config.max_minutes, self.step)
                        break
            bar.close()
            if interrupt.requested:
                self._sync_log(handle)
                checkpoint = self.save_checkpoint()
                log.warning("interrupted: stopped after step %d; resume with the same out folder (%s)", self.step, checkpoint)
                raise KeyboardInterrupt
            self._validation_row(writer, time.perf_counter() - start)
            self._sync_log(handle)
            return self.save_checkpoint()
