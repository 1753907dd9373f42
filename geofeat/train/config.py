"""Settings of a GeoLoRA training run: one dataclass, saved as JSON beside the checkpoints.

Defaults are the paper's settings (the released ``train.py`` and ``config/train/*.yaml`` of
vikiehm/geo-lora): DINOv3 ViT-B/16 at 512 x 512, LoRA rank 16 / alpha 32 on query, key and
value, 9 views of the full shape and 4 of each partial shape, two partial shapes per full
shape and step drawn from CUTS / HOLES / RAY, Adam at 1e-4, gradient norm clipped at 1.0,
the geodesic-weighted PointInfoNCE at temperature 0.1, full shapes above 12,000 vertices
decimated, a checkpoint and a validation every 5,000 steps, 50,000 steps in all.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, ClassVar

from geofeat.checks import canonical, is_boolean, is_finite_number, is_integer
from geofeat.errors import TrainingError
from geofeat.geometry.partial import PARTIAL_KINDS
from geofeat.storage.jsonconfig import JsonConfig

__all__ = ["LOSSES", "PARTIAL_GENERATORS", "RESUMABLE_CHANGES", "TrainConfig"]

LOSSES = ("geodesic", "plain")
AMP_MODES = ("auto", "on", "off")
#: Recipes a run can train with (`TrainConfig.recipe`).
TRAIN_RECIPES = ("default", "reference")
#: Partial-shape generators of training: geofeat's (`geofeat.geometry.partial`) or GeoLoRA's own
#: (`geofeat.geometry.partial_reference`, equal draw by draw).
PARTIAL_GENERATORS = ("geofeat", "reference")
#: Fields that may differ between a run and its resumption (they do not change what is learned).
RESUMABLE_CHANGES = frozenset(
    {"steps", "max_minutes", "progress", "device", "workers", "checkpoint_every", "validate_every", "val_pairs", "geodesic_cache"}
)


@dataclass
class TrainConfig(JsonConfig):
    """Every setting of ``geofeat train-geolora``.

    ``config.json`` of a run; a `geofeat.storage.jsonconfig.JsonConfig`, so a key of a settings file
    that names no setting (``wandb_project``, say) is warned about and saved back, not lost.

    Parameters
    ----------
    data : str
        A folder of meshes (``.off``, ``.obj``, ``.ply``; sorted by name), the name of a
        geofeat full-shape dataset (``faust_r``, ``scape_r``), or one of the official
        release's training sets (``faust``, ``becos``, ``becos_without_shrec16``, ``smal``;
        `geofeat.train.shapes.OFFICIAL_TRAINING_SETS`), read from ``data_root``.
    out : str
        Run folder: ``config.json``, ``log.csv``, ``checkpoints/step_NNNNNNN/``.
    data_root : str or None
        Root of the geofeat datasets (``$GEOFEAT_DATA`` when None).
    split : str
        Split of a dataset name (``"train"``: the first 80 FAUST_r shapes).
    first : int or None
        Use only the first N shapes (after sorting).
    max_vertices : int
        Full shapes with more vertices are decimated to this many (quadric decimation).
    weights : str or None
        DINOv3 backbone (see `geofeat.backbones.load_backbone`); None reads ``$GEOFEAT_DINOV3_WEIGHTS``.
    layer : int
        Backbone block whose patch tokens are used (-1: the last).
    rank, alpha : int, float
        LoRA rank and alpha.
    image_size : int
        Render size in pixels (a multiple of the patch size).
    views_full, views_partial : int
        Cameras of the official grid for the full shape and for each partial shape.
    camera_layout : {"official", "uniform"}
    recipe : {"default", "reference"}
        Whose way the run follows: geofeat's, or the official GeoLoRA code's, stage by stage.
        It picks the multi-view feature recipe (`geofeat.multiview.pipeline.RECIPES`);
        ``"reference"`` also gives each block one LoRA ``A`` shared by the query, key and
        value projections, as the official LoRA on the fused ``qkv`` has
        (`geofeat.backbones.LoraSettings.shared_a`), and leaves a whole sample out when one
        of its partial shapes has no loss, as the official loop does. The settings below
        that are None take the recipe's value.
    backproject : {"ball", "face", "ball_last"} or None
        None: the recipe's.
    rope_augmentation : bool or None
        Run DINOv3 in ``train()`` mode during the training steps, which rescales its RoPE
        coordinates at random in every forward pass, as the official training does
        (`geofeat.backbones.DinoBackbone.rope_augmentation`); the draws are seeded by
        ``seed`` and the sample, so a resumed run draws the same. Validation always runs in
        ``eval()`` mode. None: the recipe's (on under ``"reference"``, off under ``"default"``).
    partials_per_shape : int
        Partial shapes cut from the full shape at every step.
    shapes_per_rank : int
        Full shapes each process takes per step (the global batch of a step is
        ``shapes_per_rank`` times the number of ``torchrun`` ranks); the loss is the mean over
        the shapes of the batch of each shape's mean partial loss.
    partial_kinds : tuple of str
        Generators drawn from uniformly (``"cuts"``, ``"holes"``, ``"ray"``).
    partial_generators : {"geofeat", "reference"} or None
        Whose CUTS, HOLES and RAY make the partial shapes (`PARTIAL_GENERATORS`):
        ``"reference"`` makes every sample as GeoLoRA's training loop does (the full shape
        divided by the square root of its area, triangles cut by the plane, the official ray
        caster, nearest-vertex ground truth, a try again below 10 vertices; see
        `geofeat.train.samples`). None: the recipe's (`TrainConfig.generators`).
    loss : {"geodesic", "plain"}
        Geodesic-weighted PointInfoNCE or the plain one (ablation).
    temperature, offset : float
        Loss temperature and the weight offset of the geodesic-weighted loss.
    steps : int
        Total optimisation steps (the run stops there; a resumed run continues up to it).
    max_minutes : float or None
        Stop (with a checkpoint and a validation) once this much wall time has been spent in this process.
    lr, grad_clip : float
        Adam learning rate and the gradient-norm clip.
    amp : {"auto", "on", "off"}
        bfloat16 autocast of the backbone: "auto" = on CUDA only.
    seed : int
        Seeds the LoRA initialisation, the shape order, the rotations and the partial shapes.
    device : str
        ``"auto"``: CUDA when present (under ``torchrun`` the rank's local GPU), else CPU.
    workers : int or "auto"
        Worker processes (per rank) that prepare the coming steps' samples (geodesic
        matrix, rotations, partial shapes) while the device computes the current one; 0:
        this process prepares each at the start of its step. ``"auto"``: 0 on the CPU, on
        CUDA ``min(4, cores - 1)`` (the rank's share of the cores). Does not change what is
        learned.
    checkpoint_every, validate_every : int
        Steps between checkpoints and between validations (0: only at the end).
    val_dataset : str or None
        A geofeat P2F benchmark name (e.g. ``faust_r_cuts``) for validation; None: no validation.
    val_split : str
    val_pairs : int
        Validation pairs (the first N of the benchmark's seeded order).
    geodesic_cache : str or None
        Folder of cached geodesic matrices (None: ``<geofeat cache>/geodesics``).
    progress : bool
        Show progress bars.
    """

    data: str = ""
    out: str = "runs/geolora"
    data_root: str | None = None
    split: str = "train"
    first: int | None = None
    max_vertices: int = 12000
    weights: str | None = None
    layer: int = -1
    rank: int = 16
    alpha: float = 32.0
    image_size: int = 512
    views_full: int = 9
    views_partial: int = 4
    camera_layout: str = "official"
    recipe: str = "default"
    backproject: str | None = None
    rope_augmentation: bool | None = None
    partials_per_shape: int = 2
    shapes_per_rank: int = 1
    partial_kinds: tuple[str, ...] = PARTIAL_KINDS
    partial_generators: str | None = None
    loss: str = "geodesic"
    temperature: float = 0.1
    offset: float = 0.5
    steps: int = 50000
    max_minutes: float | None = None
    lr: float = 1e-4
    grad_clip: float = 1.0
    amp: str = "auto"
    seed: int = 0
    device: str = "auto"
    workers: int | str = "auto"
    checkpoint_every: int = 5000
    validate_every: int = 5000
    val_dataset: str | None = None
    val_split: str = "test"
    val_pairs: int = 20
    geodesic_cache: str | None = None
    progress: bool = True

    error: ClassVar[type[TrainingError]] = TrainingError

    def __post_init__(self) -> None:
        for name in self.field_names():  # NumPy scalars as Python values, for the JSON file
            setattr(self, name, canonical(getattr(self, name)))
        self.partial_kinds = tuple(self.partial_kinds)
        problems = []
        for name in ("data", "out", "split", "camera_layout", "recipe", "loss", "amp", "device", "val_split"):
            if not isinstance(getattr(self, name), str):
                problems.append(f"{name} must be a string, found {type(getattr(self, name)).__name__} {getattr(self, name)!r}")
        for name in ("data_root", "weights", "backproject", "partial_generators", "val_dataset", "geodesic_cache"):
            if getattr(self, name) is not None and not isinstance(getattr(self, name), str):
                problems.append(
                    f"{name} must be a string or None, found {type(getattr(self, name)).__name__} {getattr(self, name)!r}"
                )
        if not is_boolean(self.progress):
            problems.append(f"progress must be true or false, found {self.progress!r}")
        if self.rope_augmentation is not None and not is_boolean(self.rope_augmentation):
            problems.append(f"rope_augmentation must be true, false or None, found {self.rope_augmentation!r}")
        for name in ("seed", "layer"):
            if not is_integer(getattr(self, name)):
                problems.append(f"{name} must be an integer, found {getattr(self, name)!r}")
        if not is_finite_number(self.offset):
            problems.append(f"offset must be a finite number, found {self.offset!r}")
        if problems:  # the checks below assume these types
            raise TrainingError("bad training settings: " + "; ".join(problems) + ".")
        if not self.data:
            problems.append("data is empty: give a folder of meshes or a dataset name (faust_r, scape_r)")
        if self.loss not in LOSSES:
            problems.append(f"loss must be one of {LOSSES}, found {self.loss!r}")
        if self.recipe not in TRAIN_RECIPES:
            problems.append(f"recipe must be one of {TRAIN_RECIPES}, found {self.recipe!r}")
        if self.amp not in AMP_MODES:
            problems.append(f"amp must be one of {AMP_MODES}, found {self.amp!r}")
        unknown_kinds = sorted(set(self.partial_kinds) - set(PARTIAL_KINDS))
        if unknown_kinds or not self.partial_kinds:
            problems.append(f"partial_kinds must be a non-empty subset of {PARTIAL_KINDS}, found {list(self.partial_kinds)}")
        if self.partial_generators is not None and self.partial_generators not in PARTIAL_GENERATORS:
            problems.append(f"partial_generators must be one of {PARTIAL_GENERATORS} or None, found {self.partial_generators!r}")
        positive = ("rank", "image_size", "views_full", "views_partial", "partials_per_shape", "shapes_per_rank")
        for name in (*positive, "max_vertices"):
            if not is_integer(getattr(self, name)) or getattr(self, name) < 1:
                problems.append(f"{name} must be a positive integer, found {getattr(self, name)!r}")
        for name in ("steps", "checkpoint_every", "validate_every", "val_pairs"):
            if not is_integer(getattr(self, name)) or getattr(self, name) < 0:
                problems.append(f"{name} must be an integer >= 0, found {getattr(self, name)!r}")
        if self.first is not None and (not is_integer(self.first) or self.first < 1):
            problems.append(f"first must be a positive integer or None, found {self.first!r}")
        for name in ("lr", "grad_clip", "temperature", "alpha"):
            if not is_finite_number(getattr(self, name)) or getattr(self, name) <= 0:
                problems.append(f"{name} must be a number > 0, found {getattr(self, name)!r}")
        if isinstance(self.workers, str) and self.workers.strip().isdigit():  # a flag's text, "2"
            self.workers = int(self.workers)
        if self.workers != "auto" and (not is_integer(self.workers) or self.workers < 0):
            problems.append(f"workers must be an integer >= 0 or 'auto', found {self.workers!r}")
        if self.max_minutes is not None and (not is_finite_number(self.max_minutes) or self.max_minutes <= 0):
            problems.append(f"max_minutes must be a number > 0 or None, found {self.max_minutes!r}")
        if problems:
            raise TrainingError("bad training settings: " + "; ".join(problems) + ".")

    # -- serialisation (to_dict, from_dict, save, load, unknown: see JsonConfig)

    @classmethod
    def from_file(cls, path: str | os.PathLike, **overrides: Any) -> TrainConfig:
        """Read a ``.json`` or ``.yaml`` / ``.yml`` file; ``overrides`` that are not None win.

        Raises
        ------
        TrainingError
            Missing or unreadable file, or not a mapping.
        """
        return cls.load(path, **overrides)

    def generators(self) -> str:
        """The run's partial-shape generators: ``partial_generators``, or the recipe's (its own name)."""
        if self.partial_generators is not None:
            return self.partial_generators
        return "reference" if self.recipe == "reference" else "geofeat"

    def changes_from(self, other: TrainConfig) -> list[str]:
        """Names of the settings that differ from ``other``."""
        mine, theirs = self.to_dict(), other.to_dict()
        return [name for name in self.field_names() if mine[name] != theirs[name]]
