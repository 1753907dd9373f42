"""LoRA (GeoLoRA) on the attention projections of a frozen DINO backbone, through `peft`.

>>> backbone = load_backbone("/models/dinov3-vitb16", kind="dinov3")        # doctest: +SKIP
>>> add_lora(backbone)                   # rank 16, alpha 32 on q/k/v; base frozen   # doctest: +SKIP
>>> save_lora(backbone, "runs/faust/lora", LoraSettings(training={"lr": 1e-4}))  # doctest: +SKIP
>>> load_lora(load_backbone("/models/dinov3-vitb16", kind="dinov3"), "runs/faust/lora")  # doctest: +SKIP
>>> load_official_lora(load_backbone(..., kind="dinov3"), "saved_models/becos.pth")  # doctest: +SKIP

One LoRA (peft's adapter ``"default"``) serves full and partial shapes alike (siamese training).
The low-rank update of a projection ``W`` (out, in) is ``W + (alpha / rank) * B @ A`` with
``A`` (rank, in) and ``B`` (out, rank).

LoRA folders are written by `geofeat.storage.pretrained.save_pretrained` (kind ``"lora"``,
the layout of heads and trainer checkpoints too):

``weights.safetensors``
    Tensors keyed ``layer.<i>.<target>.lora_A.weight`` (rank, in) and
    ``layer.<i>.<target>.lora_B.weight`` (out, rank), ``<i>`` the block index, ``<target>`` the
    projection's leaf name (``q_proj``, ``k_proj``, ``v_proj`` for DINOv3).
``config.json``
    ``{"kind": "lora", "format_version", "geofeat_version", "config", "info"}``:
    ``config`` holds the backbone's kind, source and weights digest, its number of blocks,
    rank, alpha, dropout, targets, ``shared_a`` and the free-form training settings;
    ``info`` the extra information (step, loss).

The GeoLoRA release checkpoints (``saved_models/*.pth`` of the authors' repository) adapt the
fused ``blocks.<i>.attn.qkv`` projection of the official DINOv3 (peft ``r=16``,
``lora_alpha=32``, ``target_modules=["qkv"]``, ``bias="none"``). Their update ``B @ A`` splits
exactly into per-projection LoRA updates sharing ``A``, with ``B`` cut into three row blocks
(query, key, value); `load_official_lora` does that conversion.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

from geofeat.backbones.dino import DinoBackbone, state_dict_digest
from geofeat.checks import check_integer, check_number
from geofeat.errors import BackboneError, MissingDependencyError
from geofeat.storage.jsonconfig import JsonConfig
from geofeat.storage.pretrained import Pretrained, from_pretrained, save_pretrained
from geofeat.storage.safe_load import load_torch_file

logger = logging.getLogger(__name__)

__all__ = [
    "LORA_KIND",
    "OFFICIAL_ALPHA",
    "LoraSettings",
    "add_lora",
    "convert_official_lora",
    "has_lora",
    "load_lora",
    "load_official_lora",
    "loaded_lora_digest",
    "lora_digest",
    "lora_state_dict",
    "official_lora_state_dict",
    "save_lora",
    "save_official_lora",
]

#: The `geofeat.storage.pretrained` kind of LoRA folders (trainer checkpoints included).
LORA_KIND = "lora"
_BACKBONE_KEYS = ("backbone_kind", "backbone_digest", "backbone_source", "num_layers")
_PEFT_ADAPTER = "default"
_REQUIRED_KEYS = ("backbone_kind", "backbone_digest", "rank", "alpha", "targets")
_CANONICAL_KEY = re.compile(r"^layer\.(\d+)\.([A-Za-z0-9_]+)\.lora_([AB])\.weight$")
# the release checkpoints: peft-wrapped official DINOv3, fused qkv (the prefix and peft's adapter name are optional)
_OFFICIAL_KEY = re.compile(r"^(?:module\.)?(?:base_model\.model\.)?blocks\.(\d+)\.attn\.qkv\.lora_([AB])(?:\.default)?\.weight$")
_OFFICIAL_EXAMPLE = "base_model.model.blocks.<i>.attn.qkv.lora_A.default.weight (rank, D) and ...lora_B.default.weight (3D, rank)"
OFFICIAL_ALPHA = 32.0


def _require_peft() -> Any:
    try:
        import peft
    except ImportError as exc:
        raise MissingDependencyError(
            "LoRA needs the optional dependency 'peft', which is not installed; install it with: pip install 'geofeat[dino]'"
        ) from exc
    return peft


# ----------------------------------------------------------------------------- settings


@dataclass
class LoraSettings(JsonConfig):
    """LoRA hyper-parameters, plus free-form training settings stored with the LoRA.

    A `geofeat.storage.jsonconfig.JsonConfig`: `JsonConfig.save` / `JsonConfig.load` write and read it as a JSON file.

    Parameters
    ----------
    rank : int
        Rank ``r`` of the update (GeoLoRA: 16).
    alpha : float
        Scale numerator: the update is multiplied by ``alpha / rank`` (GeoLoRA: 32, i.e. 2).
    dropout : float
        Dropout on the LoRA input during training, in [0, 1) (GeoLoRA: 0).
    targets : tuple of str, optional
        Leaf names of the adapted modules; None means the backbone's query/key/value
        projections (`DinoBackbone.attention_projections`).
    shared_a : bool
        Within each block, all targets share one ``A`` (one parameter, trained once), as the
        GeoLoRA release's LoRA on the fused ``qkv`` projection does: its ``A`` multiplies the
        input of all three, and its ``B`` splits into one per projection. False: each target
        has its own ``A``.
    training : dict
        JSON-serialisable training settings (learning rate, views, data, ...), stored as given.
    """

    rank: int = 16
    alpha: float = 32.0
    dropout: float = 0.0
    targets: tuple[str, ...] | None = None
    shared_a: bool = False
    training: dict[str, Any] = field(default_factory=dict)

    error: ClassVar[type[BackboneError]] = BackboneError

    def __post_init__(self) -> None:
        self.rank = check_integer(self.rank, "rank", owner="LoRA", low=1, error=BackboneError, expected="a positive integer")
        self.alpha = check_number(self.alpha, "alpha", owner="LoRA", low=0, low_open=True, error=BackboneError)
        self.dropout = check_number(self.dropout, "dropout", owner="LoRA", low=0, high=1, high_open=True, error=BackboneError)
        if self.targets is not None:
            if isinstance(self.targets, str) or not all(isinstance(t, str) and t for t in self.targets) or not self.targets:
                raise BackboneError(f"LoRA targets must be a non-empty sequence of module names, found {self.targets!r}")
            self.targets = tuple(self.targets)
        if not isinstance(self.shared_a, bool):
            raise BackboneError(f"shared_a must be True or False, found {self.shared_a!r}")
        if not isinstance(self.training, dict):
            raise BackboneError(f"training settings must be a dict, found {type(self.training).__name__}")
        try:
            json.dumps(self.training)
        except (TypeError, ValueError) as exc:
            raise BackboneError(f"training settings must be JSON-serialisable: {exc}") from exc

    @property
    def scaling(self) -> float:
        """``alpha / rank``, the factor applied to ``B @ A``."""
        return self.alpha / self.rank


# ----------------------------------------------------------------------------- adding LoRA


def has_lora(backbone: DinoBackbone) -> bool:
    """Whether ``backbone.model`` already carries peft LoRA layers."""
    peft = _require_peft()
    return any(isinstance(m, peft.tuners.lora.LoraLayer) for m in backbone.model.modules())


def _resolve_targets(backbone: DinoBackbone, settings: LoraSettings) -> tuple[str, ...]:
    targets = settings.targets if settings.targets is not None else backbone.attention_projections
    leaves = {name.rsplit(".", 1)[-1] for name, _ in backbone.model.named_modules()}
    missing = sorted(set(targets) - leaves)
    if missing:
        raise BackboneError(
            f"LoRA targets {missing} are not modules of this {backbone.kind} model; its attention projections are "
            f"{backbone.attention_projections}"
        )
    return tuple(targets)


def add_lora(backbone: DinoBackbone, config: LoraSettings | None = None) -> DinoBackbone:
    """Wrap the backbone's model with a trainable LoRA; every base weight is frozen.

    The model is modified in place (``backbone.model`` becomes a ``peft.PeftModel``) and the same
    backbone is returned; its `weights_digest` stays the digest of the base weights.
    `DinoBackbone.patch_features` is then differentiable with respect to the LoRA parameters
    (the only ones with ``requires_grad``). A new LoRA starts as the identity (``B = 0``).

    Parameters
    ----------
    backbone : DinoBackbone
        A backbone without LoRA.
    config : LoraSettings, optional
        Defaults to ``LoraSettings()`` (rank 16, alpha 32, no dropout, query/key/value).

    Returns
    -------
    DinoBackbone
        ``backbone`` itself, with ``rank * (in + out)`` trainable LoRA parameters per target and block.

    Raises
    ------
    BackboneError
        The backbone already has LoRA layers, or a target is not a module of the model.
    """
    peft = _require_peft()
    settings = config if config is not None else LoraSettings()
    if not isinstance(settings, LoraSettings):
        raise BackboneError(f"config must be a LoraSettings, found {type(settings).__name__}")
    if has_lora(backbone):
        raise BackboneError("this backbone already has a LoRA; load a fresh backbone to add another")
    targets = _resolve_targets(backbone, settings)
    lora_config = peft.LoraConfig(
        r=settings.rank, lora_alpha=settings.alpha, lora_dropout=settings.dropout, target_modules=list(targets), bias="none"
    )
    model = peft.get_peft_model(backbone.model, lora_config)
    for name, param in model.named_parameters():
        param.requires_grad_("lora_" in name)
    model.eval()
    backbone.model = model
    if settings.shared_a:
        _share_a(backbone, targets)
    logger.info(
        "added LoRA (rank %d, alpha %g, targets %s) to %s: %d trainable parameters",
        settings.rank,
        settings.alpha,
        list(targets),
        backbone.kind,
        sum(p.numel() for p in model.parameters() if p.requires_grad),
    )
    return backbone


def _active_settings(backbone: DinoBackbone) -> LoraSettings:
    """Rank, alpha, dropout, targets and A sharing of the backbone's LoRA (its peft config)."""
    if not has_lora(backbone):
        raise BackboneError("this backbone has no LoRA; call add_lora(backbone) or load_lora(backbone, folder) first")
    peft_config = getattr(backbone.model, "peft_config", None)
    if not peft_config or _PEFT_ADAPTER not in peft_config:
        raise BackboneError("the backbone's LoRA layers were not added by add_lora (no peft 'default' adapter config)")
    config = peft_config[_PEFT_ADAPTER]
    targets = config.target_modules
    targets = tuple(sorted(targets)) if not isinstance(targets, str) else (targets,)
    modules = _lora_modules(backbone)
    shared = len(targets) > 1 and all(
        modules[(block, target)].lora_A[_PEFT_ADAPTER].weight is modules[(block, targets[0])].lora_A[_PEFT_ADAPTER].weight
        for block in {b for b, _ in modules}
        for target in targets
    )
    return LoraSettings(
        rank=int(config.r), alpha=float(config.lora_alpha), dropout=float(config.lora_dropout), targets=targets, shared_a=shared
    )


def _share_a(backbone: DinoBackbone, targets: tuple[str, ...]) -> None:
    """Make the targets of each block use the first target's ``A`` parameter (see `LoraSettings.shared_a`)."""
    modules = _lora_modules(backbone)
    for block in sorted({b for b, _ in modules}):
        first = modules[(block, targets[0])].lora_A[_PEFT_ADAPTER]
        for target in targets[1:]:
            modules[(block, target)].lora_A[_PEFT_ADAPTER].weight = first.weight


def _lora_modules(backbone: DinoBackbone) -> dict[tuple[int, str], Any]:
    """Map (block index, target leaf name) to the peft LoRA layer."""
    peft = _require_peft()
    found: dict[tuple[int, str], Any] = {}
    for name, module in backbone.model.named_modules():
        match = re.search(r"(?:^|\.)layer\.(\d+)\.(?:.+\.)?([A-Za-z0-9_]+)$", name)
        if match and isinstance(module, peft.tuners.lora.LoraLayer):
            found[(int(match.group(1)), match.group(2))] = module
    return found


def lora_state_dict(backbone: DinoBackbone) -> dict[str, Tensor]:
    """The LoRA tensors in geofeat's layout (detached CPU copies).

    Returns
    -------
    dict of str to torch.Tensor
        ``layer.<i>.<target>.lora_A.weight`` (rank, in) and ``layer.<i>.<target>.lora_B.weight``
        (out, rank), float32.
    """
    _active_settings(backbone)
    out: dict[str, Tensor] = {}
    for (block, target), module in sorted(_lora_modules(backbone).items()):
        for part in ("A", "B"):
            weight = getattr(module, f"lora_{part}")[_PEFT_ADAPTER].weight
            out[f"layer.{block}.{target}.lora_{part}.weight"] = weight.detach().to("cpu", torch.float32, copy=True).contiguous()
    return out


def _load_lora_tensors(backbone: DinoBackbone, tensors: Mapping[str, Tensor], source: str) -> None:
    """Copy geofeat-layout LoRA tensors into the backbone's LoRA (every LoRA layer must be covered)."""
    modules = _lora_modules(backbone)
    expected = {f"layer.{b}.{t}.lora_{p}.weight" for (b, t) in modules for p in "AB"}
    missing, unexpected = sorted(expected - set(tensors)), sorted(set(tensors) - expected)
    if missing or unexpected:
        raise BackboneError(
            f"the LoRA tensors from {source} do not fit this backbone's LoRA: missing {missing[:6]}, unexpected "
            f"{unexpected[:6]}; the LoRA was made for another architecture or other targets"
        )
    if _active_settings(backbone).shared_a:
        for block in sorted({b for b, _ in modules}):
            a = [tensors[f"layer.{block}.{t}.lora_A.weight"] for (b, t) in sorted(modules) if b == block]
            if any(not torch.equal(a[0], other) for other in a[1:]):
                raise BackboneError(
                    f"the LoRA from {source} has different lora_A tensors for the targets of block {block}, but this "
                    "backbone's LoRA shares one A per block (shared_a); load it into a LoRA with shared_a=False"
                )
    with torch.no_grad():
        for (block, target), module in modules.items():
            for part in ("A", "B"):
                key = f"layer.{block}.{target}.lora_{part}.weight"
                weight = getattr(module, f"lora_{part}")[_PEFT_ADAPTER].weight
                value = tensors[key]
                if tuple(value.shape) != tuple(weight.shape):
                    raise BackboneError(
                        f"LoRA tensor {key} from {source} has shape {tuple(value.shape)}, expected {tuple(weight.shape)}"
                    )
                if not value.is_floating_point() or not bool(value.isfinite().all()):
                    problem = "NaN or infinite values" if value.is_floating_point() else f"dtype {value.dtype}"
                    raise BackboneError(
                        f"LoRA tensor {key} from {source} holds {problem}, not finite floating-point weights; the file "
                        "is damaged or was written by a diverged training: use another checkpoint"
                    )
                weight.copy_(value.to(weight.device, weight.dtype))


# ----------------------------------------------------------------------------- files


def save_lora(
    backbone: DinoBackbone,
    folder: str | os.PathLike,
    settings: LoraSettings | None = None,
    extra_info: Mapping[str, Any] | None = None,
    *,
    extra_files: Mapping[str, Any] | None = None,
) -> Path:
    """Save the backbone's LoRA as a `geofeat.storage.pretrained` folder (``config.json`` + ``weights.safetensors``).

    Parameters
    ----------
    backbone : DinoBackbone
        A backbone with LoRA (`add_lora`, `load_lora` or `load_official_lora`).
    folder : str or os.PathLike
        Created if needed; a LoRA folder (or any folder written by `geofeat.storage.pretrained.save_pretrained`)
        there is replaced whole and atomically; a folder holding other files is refused.
    settings : LoraSettings, optional
        Its ``training`` dict is stored; its rank, alpha and dropout must agree with the
        backbone's LoRA (None: read them from it, no training settings).
    extra_info : Mapping, optional
        JSON-serialisable extra information (e.g. step, loss), stored as the folder's ``info``.
    extra_files : Mapping of str to callable, optional
        More files of the folder, ``{name: writer(path)}`` (the trainer's ``trainer_state.pt``).

    Returns
    -------
    pathlib.Path
        The folder.

    Raises
    ------
    BackboneError
        No LoRA on the backbone, settings that disagree with it, ``extra_info`` that is not
        JSON-serialisable, or a folder that holds other files.
    """
    active = _active_settings(backbone)
    if settings is not None:
        mismatch = [n for n in ("rank", "alpha", "dropout") if getattr(settings, n) != getattr(active, n)]
        if settings.targets is not None and set(settings.targets) != set(active.targets or ()):
            mismatch.append("targets")
        if mismatch:
            raise BackboneError(
                f"settings disagree with the backbone's LoRA on {mismatch}: the LoRA has rank={active.rank}, "
                f"alpha={active.alpha}, dropout={active.dropout}, targets={list(active.targets or ())}"
            )
        active = dataclasses.replace(active, training=dict(settings.training))
    config = {
        "backbone_kind": backbone.kind,
        "backbone_digest": backbone.weights_digest,
        "backbone_source": backbone.source,
        "num_layers": backbone.num_layers,
        **active.to_dict(unknown=False),
    }
    tensors = lora_state_dict(backbone)
    folder = save_pretrained(folder, LORA_KIND, config, tensors, info=extra_info, extra_files=extra_files, error=BackboneError)
    logger.info("saved LoRA (%d tensors) to %s", len(tensors), folder)
    return folder


def _read_lora(folder: Path) -> tuple[Pretrained, dict[str, Any]]:
    """The LoRA folder and its checked config (the backbone keys and the `LoraSettings` fields)."""
    saved = from_pretrained(folder, LORA_KIND, BackboneError)
    config = saved.config
    missing = [k for k in _REQUIRED_KEYS if k not in config]
    if missing:
        raise BackboneError(
            f"the config of {folder} lacks the keys {missing}; it was not written by save_lora. Save the LoRA again."
        )
    unknown = sorted(set(config) - set(LoraSettings.field_names()) - set(_BACKBONE_KEYS))
    if unknown:
        logger.debug("ignoring unknown keys %s in the config of %s", unknown, folder)
    return saved, config


def _settings_of(config: Mapping[str, Any]) -> LoraSettings:
    return LoraSettings.from_dict({k: config[k] for k in LoraSettings.field_names() if k in config})


def _check_backbone(backbone: DinoBackbone, config: Mapping[str, Any], folder: Path) -> None:
    kind, digest = config["backbone_kind"], config["backbone_digest"]
    if kind != backbone.kind or digest != backbone.weights_digest:
        source = config.get("backbone_source") or "unrecorded weights"
        raise BackboneError(
            f"the LoRA in {folder} was trained on a {kind} backbone from {source} (weights digest {str(digest)[:12]}...), "
            f"but this is a {backbone.kind} backbone from {backbone.source} (digest {backbone.weights_digest[:12]}...); "
            "load the same backbone weights the LoRA was trained on"
        )


def load_lora(backbone: DinoBackbone, folder: str | os.PathLike) -> DinoBackbone:
    """Restore a LoRA written by `save_lora` (or a trainer checkpoint) onto a backbone with the same base weights.

    Adds the LoRA layers first when the backbone has none (the base weights are frozen, the
    LoRA parameters trainable, so training can resume); otherwise the existing LoRA must
    have the same rank, alpha and targets and is overwritten. Unknown config keys are ignored
    (debug log).

    Parameters
    ----------
    backbone : DinoBackbone
        Its `weights_digest` and kind must match those recorded in the LoRA folder.
    folder : str or os.PathLike
        A folder written by `save_lora` (``config.json`` of kind ``"lora"`` and
        ``weights.safetensors``).

    Returns
    -------
    DinoBackbone
        ``backbone`` itself, in ``eval()`` mode.

    Raises
    ------
    BackboneError
        Missing or malformed files, a folder of another layout (the message says to save it
        again), or another backbone (the message names the one it was trained on).
    """
    folder = Path(folder)
    saved, config = _read_lora(folder)
    _check_backbone(backbone, config, folder)
    settings = _settings_of(config)
    tensors = saved.tensors()
    _attach(backbone, settings, str(folder))
    _load_lora_tensors(backbone, tensors, str(folder))
    backbone.model.eval()
    logger.info("loaded LoRA from %s", folder)
    return backbone


def _attach(backbone: DinoBackbone, settings: LoraSettings, source: str) -> None:
    """Add LoRA with ``settings``, or check that the existing LoRA has the same structure."""
    if not has_lora(backbone):
        add_lora(backbone, settings)
        return
    active = _active_settings(backbone)
    targets = settings.targets if settings.targets is not None else backbone.attention_projections
    if (active.rank, active.alpha, set(active.targets or ()), active.shared_a) != (
        settings.rank,
        settings.alpha,
        set(targets),
        settings.shared_a,
    ):
        raise BackboneError(
            f"the LoRA from {source} has rank={settings.rank}, alpha={settings.alpha}, targets={list(targets)}, "
            f"shared_a={settings.shared_a} but the backbone already carries rank={active.rank}, alpha={active.alpha}, "
            f"targets={list(active.targets or ())}, shared_a={active.shared_a}; load it onto a fresh backbone"
        )


def _digest(kind: str, base_digest: str, settings: LoraSettings, tensors: Mapping[str, Tensor]) -> str:
    head = {
        "backbone_kind": kind,
        "backbone_digest": base_digest,
        "rank": settings.rank,
        "alpha": settings.alpha,
        "targets": sorted(settings.targets or ()),
    }
    digest = hashlib.sha256(json.dumps(head, sort_keys=True).encode())
    digest.update(state_dict_digest(tensors).encode())
    return digest.hexdigest()


def lora_digest(folder: str | os.PathLike) -> str:
    """SHA-256 of what determines a LoRA's output, for feature cache keys.

    Covers the LoRA tensors (names, shapes, dtypes, bytes), rank, alpha, targets and the base
    backbone's kind and digest; not the training settings or extra information. Equal to
    `loaded_lora_digest` of a backbone carrying that LoRA.

    Returns
    -------
    str
        64 hexadecimal characters.
    """
    saved, config = _read_lora(Path(folder))
    return _digest(config["backbone_kind"], config["backbone_digest"], _settings_of(config), saved.tensors())


def loaded_lora_digest(backbone: DinoBackbone) -> str:
    """`lora_digest` of the LoRA a backbone carries now (also for converted release checkpoints).

    Returns
    -------
    str
        64 hexadecimal characters.
    """
    return _digest(backbone.kind, backbone.weights_digest, _active_settings(backbone), lora_state_dict(backbone))


# ----------------------------------------------------------------------------- official checkpoints


def _official_blocks(state_dict: Mapping[str, Any]) -> dict[int, dict[str, Tensor]]:
    """Group the release checkpoint's tensors by block: {i: {"A": (r, D), "B": (3D, r)}}."""
    blocks: dict[int, dict[str, Tensor]] = {}
    for key, value in state_dict.items():
        match = _OFFICIAL_KEY.match(str(key))
        if match is None or not isinstance(value, Tensor):
            raise BackboneError(
                f"unexpected entry {key!r} in the GeoLoRA checkpoint; expected only keys like {_OFFICIAL_EXAMPLE}"
            )
        blocks.setdefault(int(match.group(1)), {})[match.group(2)] = value
    if not blocks:
        raise BackboneError(f"the GeoLoRA checkpoint holds no LoRA tensors; expected keys like {_OFFICIAL_EXAMPLE}")
    incomplete = sorted(i for i, parts in blocks.items() if set(parts) != {"A", "B"})
    if incomplete or sorted(blocks) != list(range(len(blocks))):
        raise BackboneError(
            f"the GeoLoRA checkpoint should hold lora_A and lora_B for blocks 0..N-1, found blocks {sorted(blocks)[:12]} "
            f"(incomplete: {incomplete[:12]})"
        )
    return blocks


def _check_official_shapes(i: int, a: Tensor, b: Tensor, rank: int, dim: int) -> None:
    if a.ndim != 2 or b.ndim != 2 or a.shape != (rank, dim) or b.shape != (3 * dim, rank):
        raise BackboneError(
            f"block {i} of the GeoLoRA checkpoint has lora_A {tuple(a.shape)} and lora_B {tuple(b.shape)}; expected "
            f"({rank}, {dim}) and ({3 * dim}, {rank}) for a {dim}-wide backbone with a fused qkv projection of rank {rank}"
        )


def convert_official_lora(
    state_dict: Mapping[str, Any], embed_dim: int, targets: tuple[str, str, str] = ("q_proj", "k_proj", "v_proj")
) -> dict[str, Tensor]:
    """Split a fused-qkv GeoLoRA release checkpoint into per-projection LoRA tensors (exact).

    Parameters
    ----------
    state_dict : Mapping[str, torch.Tensor]
        Keys ``base_model.model.blocks.<i>.attn.qkv.lora_A.default.weight`` (r, D) and
        ``...lora_B.default.weight`` (3D, r); nothing else.
    embed_dim : int
        Width ``D`` of the backbone.
    targets : (str, str, str)
        Leaf names of the query, key and value projections, in that order.

    Returns
    -------
    dict of str to torch.Tensor
        geofeat layout: for each block, the three targets share ``lora_A`` (r, D) and get rows
        ``[0:D]``, ``[D:2D]``, ``[2D:3D]`` of ``lora_B`` (D, r), float32.
    """
    blocks = _official_blocks(state_dict)
    rank = int(blocks[0]["A"].shape[0]) if blocks[0]["A"].ndim == 2 else -1
    out: dict[str, Tensor] = {}
    for i, parts in blocks.items():
        a, b = parts["A"].float(), parts["B"].float()
        _check_official_shapes(i, a, b, rank, embed_dim)
        for third, target in enumerate(targets):
            out[f"layer.{i}.{target}.lora_A.weight"] = a.clone()
            out[f"layer.{i}.{target}.lora_B.weight"] = b[third * embed_dim : (third + 1) * embed_dim].clone()
    return out


def official_lora_state_dict(backbone: DinoBackbone) -> dict[str, Tensor]:
    """The LoRA in the release layout: one fused ``qkv`` LoRA per block (the inverse of `convert_official_lora`).

    Needs a LoRA on the query, key and value projections of every block with one ``A``
    shared by the three (``LoraSettings.shared_a``, as the ``reference`` training recipe and
    `load_official_lora` make it): the fused ``B`` is the three ``B`` stacked.

    Returns
    -------
    dict of str to torch.Tensor
        ``base_model.model.blocks.<i>.attn.qkv.lora_A.default.weight`` (rank, D) and
        ``...lora_B.default.weight`` (3D, rank), float32 CPU tensors, as the official
        ``get_state_dict_lora`` saves them.

    Raises
    ------
    BackboneError
        No LoRA, or one that the fused layout cannot hold (separate ``A`` per projection,
        or targets other than query, key and value).
    """
    settings = _active_settings(backbone)
    targets = backbone.attention_projections
    if not settings.shared_a or set(settings.targets) != set(targets):
        raise BackboneError(
            "the release layout holds one LoRA on each block's fused qkv projection: it needs a LoRA on "
            f"{list(targets)} with one A shared by the three (shared_a=True, the reference recipe's); this one has "
            f"targets {list(settings.targets)}, shared_a={settings.shared_a}"
        )
    tensors = lora_state_dict(backbone)
    out: dict[str, Tensor] = {}
    for block in range(backbone.num_layers):
        prefix = f"base_model.model.blocks.{block}.attn.qkv"
        out[f"{prefix}.lora_A.default.weight"] = tensors[f"layer.{block}.{targets[0]}.lora_A.weight"]
        out[f"{prefix}.lora_B.default.weight"] = torch.cat([tensors[f"layer.{block}.{t}.lora_B.weight"] for t in targets])
    return out


def save_official_lora(backbone: DinoBackbone, path: str | os.PathLike) -> Path:
    """Write the LoRA as a release checkpoint ``.pth`` (`official_lora_state_dict`), atomically.

    The official code loads it with its ``load_state_dict`` into its peft model, and
    `load_official_lora` reads it back exactly.

    Parameters
    ----------
    backbone : DinoBackbone
        With a shared-A LoRA on query, key and value.
    path : str or os.PathLike

    Returns
    -------
    pathlib.Path
    """
    from geofeat.storage.files import atomic_write

    state = official_lora_state_dict(backbone)
    return atomic_write(Path(path), lambda tmp: torch.save(state, tmp))


def _read_official(path_or_state_dict: str | os.PathLike | Mapping[str, Any]) -> tuple[Mapping[str, Any], str]:
    if isinstance(path_or_state_dict, Mapping):
        return path_or_state_dict, "the given state dict"
    path = Path(path_or_state_dict)
    raw = load_torch_file(path, BackboneError, what="a GeoLoRA release checkpoint")
    if not isinstance(raw, Mapping):
        raise BackboneError(f"{path} holds a {type(raw).__name__}, expected a state dict of LoRA tensors")
    return raw, str(path)


def load_official_lora(
    backbone: DinoBackbone, path_or_state_dict: str | os.PathLike | Mapping[str, Any], *, alpha: float = OFFICIAL_ALPHA
) -> DinoBackbone:
    """Load a GeoLoRA release checkpoint (``saved_models/*.pth``) into per-projection LoRA.

    The rank is read from the checkpoint (16 for the releases); ``alpha`` must be the one used in
    training (32 for the releases, scale ``alpha / rank`` = 2). Adds LoRA to the backbone when it
    has none.

    Parameters
    ----------
    backbone : DinoBackbone
        The DINOv3 the LoRA was trained on (ViT-B/16 for the releases); depth and width must match.
    path_or_state_dict : str, os.PathLike or Mapping
        The ``.pth`` file or its loaded state dict.
    alpha : float
        LoRA alpha of the checkpoint.

    Returns
    -------
    DinoBackbone
        ``backbone`` itself, with the converted LoRA, in ``eval()`` mode.

    Raises
    ------
    BackboneError
        Unknown keys, missing blocks, wrong shapes, or a depth that does not match the backbone.
    """
    state_dict, source = _read_official(path_or_state_dict)
    targets = backbone.attention_projections
    tensors = convert_official_lora(state_dict, backbone.embed_dim, targets)
    depth = len(tensors) // 6
    if depth != backbone.num_layers:
        raise BackboneError(
            f"the GeoLoRA checkpoint {source} adapts {depth} blocks but this backbone has {backbone.num_layers}; "
            "the release checkpoints are for DINOv3 ViT-B/16 (12 blocks, width 768)"
        )
    rank = int(tensors[f"layer.0.{targets[0]}.lora_A.weight"].shape[0])
    _attach(backbone, LoraSettings(rank=rank, alpha=alpha, targets=targets, shared_a=True), source)
    _load_lora_tensors(backbone, tensors, source)
    backbone.model.eval()
    logger.info("loaded GeoLoRA release checkpoint %s (rank %d, alpha %g, %d blocks)", source, rank, alpha, depth)
    return backbone
