"""`LearnedHead`: the shared part of every head with a torch module (ULRSSM, DPFM, EchoMatch).

A learned head builds its module from the input width (`LearnedHead.build_model`), gives a
training loss for a pair (`LearnedHead.training_loss`) and a prediction for a pair
(`LearnedHead.predict`). This module holds what they share: the per-shape inputs (input
features as a tensor and DiffusionNet's surface operators, kept for the last 64 meshes),
the training loop (Adam, optional cosine annealing, gradient clipping, time budget,
progress bar) and the weights of a checkpoint.

torch is imported inside the methods that need it: subclassing costs nothing until a
module is built.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from geofeat.adapters.base import Head, HeadConfig
from geofeat.adapters.inputs import laplacian_for
from geofeat.checks import is_integer
from geofeat.datasets.records import Match, ShapePair
from geofeat.errors import HeadError, UnusablePair
from geofeat.mesh import Mesh
from geofeat.runtime.progress import progress_bar
from geofeat.storage.lru import LRUCache
from geofeat.storage.pretrained import CONFIG_FILE, Pretrained

if TYPE_CHECKING:
    import torch

    from geofeat.adapters.blocks.operators import SurfaceOperators

log = logging.getLogger(__name__)

__all__ = ["LearnedHead"]

#: Meshes whose input features and operators a learned head keeps (`LearnedHead.shape_inputs`).
_INPUTS_KEPT = 64
#: Training steps whose losses `LearnedHead.fit` keeps on the device before reading them back
#: at once (reading a loss waits for the device to finish its step).
_LOSSES_READ_EVERY = 256


class LearnedHead(Head):
    """A head with a torch module: the shared inputs, training loop and checkpoint weights.

    Subclasses implement `build_model` (the module, from the input width), `training_loss`
    (a scalar tensor for one pair) and `predict` (a `Match` for one pair, under ``no_grad``).
    """

    def __init__(self, config: HeadConfig | None = None, **settings: Any):
        super().__init__(config, **settings)
        self.model: torch.nn.Module | None = None
        self.in_channels: int | None = None
        self._inputs: LRUCache[str, tuple[torch.Tensor, SurfaceOperators]] = LRUCache(_INPUTS_KEPT)
        # mesh hash -> (the eigenvalues of its operators in _inputs, a CPU copy of them)
        self._host_evals: LRUCache[str, tuple[torch.Tensor, torch.Tensor]] = LRUCache(_INPUTS_KEPT)

    def build_model(self, in_channels: int) -> torch.nn.Module:
        """The trainable module for ``in_channels`` input features."""
        raise NotImplementedError

    def training_loss(self, pair: ShapePair) -> torch.Tensor:
        """Scalar training loss of one pair."""
        raise NotImplementedError

    def predict(self, pair: ShapePair) -> Match:
        """The prediction for one pair (gradients off)."""
        raise NotImplementedError

    # -- inputs

    def operators(self, mesh: Mesh) -> SurfaceOperators:
        """Surface operators of a mesh of a prepared pair, on the CPU (a point cloud's from its point-cloud Laplacian)."""
        from geofeat.adapters.blocks.operators import surface_operators

        c = self.config
        return surface_operators(mesh, c.n_eig, laplacian_kind=laplacian_for(mesh, c.laplacian), construction=c.operators)

    def shape_inputs(self, mesh: Mesh) -> tuple[torch.Tensor, SurfaceOperators]:
        """Input features as a tensor (V, C) and the surface operators, on the head's device (kept for 64 meshes)."""
        import torch

        def build() -> tuple[torch.Tensor, SurfaceOperators]:
            feats = torch.tensor(self.features(mesh), device=self.device)  # a copy: the array is shared and read-only
            host = self.operators(mesh)
            ops = host.to(self.device)
            self._host_evals.put(mesh.hash, (ops.evals, host.evals))
            return feats, ops

        return self._inputs.get_or_compute(mesh.hash, build)

    def host_eigenvalues(self, mesh: Mesh) -> torch.Tensor:
        """The eigenvalues of the operators of `shape_inputs`, on the CPU, shape (k,) float32.

        For what is computed on the host from them (functional-map masks, partial ranks):
        a copy kept from when the operators were built, so that reading them does not wait
        for the device. Operators given by `use_inputs` (or put in the cache otherwise) are
        copied once.
        """
        ops = self.shape_inputs(mesh)[1]
        kept = self._host_evals.get(mesh.hash)
        if kept is None or kept[0] is not ops.evals:
            kept = self._host_evals.put(mesh.hash, (ops.evals, ops.evals.cpu()))
        return kept[1]

    def use_inputs(self, mesh: Mesh, features: torch.Tensor, operators: SurfaceOperators) -> None:
        """Use these input features and operators for ``mesh`` instead of computing them.

        For feeding a head exactly the inputs of another implementation (``python -m benchmarks.parity``)
        or inputs computed elsewhere. They are kept like computed ones (64 meshes).

        Parameters
        ----------
        mesh : Mesh
        features : torch.Tensor, shape (V, C)
        operators : SurfaceOperators
            With at least ``n_eig`` eigenpairs where the head needs them.
        """
        if features.ndim != 2 or features.shape[0] != mesh.n_vertices or operators.n_vertices != mesh.n_vertices:
            raise HeadError(
                f"use_inputs: features (V, C) and operators must be of mesh {mesh.name!r} with {mesh.n_vertices} vertices; "
                f"found features {tuple(features.shape)} and operators of {operators.n_vertices} vertices."
            )
        import torch

        self._inputs.put(mesh.hash, (features.to(self.device, torch.float32), operators.to(self.device)))
        self._host_evals.pop(mesh.hash)

    def _ensure_model(self, mesh: Mesh) -> torch.nn.Module:
        import torch

        if self.model is None:
            torch.manual_seed(self.config.seed)
            self.in_channels = int(self.shape_inputs(mesh)[0].shape[1])
            self.model = self.build_model(self.in_channels).to(self.device)
        return self.model

    # -- training and matching

    def fit(self, pairs: Sequence[ShapePair]) -> list[float]:
        """Adam over ``epochs`` passes of the pairs in a seeded order; returns the loss of every step."""
        if len(pairs) == 0:
            raise HeadError(f"head {self.name!r}: no training pairs.")
        import torch

        config = self.config
        model = self._ensure_model(pairs[0].x)
        optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=config.lr)
        total = config.epochs * len(pairs)
        scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total) if config.cosine_annealing else None
        rng = np.random.default_rng(config.seed)
        losses: list[float] = []
        pending: list[torch.Tensor] = []  # detached losses not read back yet
        start = time.perf_counter()
        bar = progress_bar(total=total, desc=f"training {self.name}", unit="pair", show=config.progress)
        try:
            for _ in range(config.epochs):
                for index in rng.permutation(len(pairs)):
                    model.train()
                    try:
                        loss = self.training_loss(self.prepare(pairs[int(index)]))
                    except UnusablePair as skipped:
                        log.info("%s: skipped a training pair: %s", self.name, skipped)
                        bar.update(1)
                        continue
                    optimizer.zero_grad(set_to_none=True)
                    loss.backward()
                    if config.grad_clip is not None:
                        torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                    optimizer.step()
                    if scheduler is not None:
                        scheduler.step()
                    pending.append(loss.detach())
                    bar.update(1)
                    if not bar.disable or len(pending) >= _LOSSES_READ_EVERY:  # a shown loss is read at every step
                        _read_back(pending, losses)
                        bar.set_postfix(loss=f"{losses[-1]:.4f}")
                    if config.max_minutes is not None and time.perf_counter() - start > 60.0 * config.max_minutes:
                        _read_back(pending, losses)
                        log.info("%s: time budget spent after %d steps", self.name, len(losses))
                        return losses
        finally:
            bar.close()
        _read_back(pending, losses)
        return losses

    def match(self, pair: ShapePair) -> Match:
        """`predict` the prepared pair with gradients off and the module in evaluation mode."""
        import torch

        pair = self.prepare(pair)
        self._ensure_model(pair.x).eval()
        with torch.no_grad():
            return self.predict(pair)

    # -- weights

    def saved_state(self) -> tuple[dict[str, Any], dict[str, torch.Tensor]]:
        """The input width (``info["in_channels"]``) and the module's state dict, for `Head.save`."""
        if self.model is None:
            raise HeadError(f"head {self.name!r} has no model yet: fit it (or load one) before saving.")
        return {"in_channels": self.in_channels}, dict(self.model.state_dict())

    def restore(self, saved: Pretrained) -> None:
        """Build the module for the saved input width and load the saved weights exactly (`load_head`)."""
        in_channels = saved.info.get("in_channels")
        if not is_integer(in_channels) or in_channels < 1:
            raise HeadError(
                f"{saved.folder / CONFIG_FILE} has no valid 'in_channels' entry under info (found {in_channels!r}); "
                "it was not written by Head.save. Save the head again."
            )
        self.load_state(saved.tensors("cpu"), int(in_channels), source=str(saved.weights_path))

    def load_state(self, state: dict[str, torch.Tensor], in_channels: int, source: str) -> None:
        """Build the module for ``in_channels`` and load ``state`` exactly (see `release.check_state`)."""
        from geofeat.adapters.release import check_state

        self.in_channels = int(in_channels)
        model = self.build_model(self.in_channels)
        check_state(model, state, source)
        model.load_state_dict(state, strict=True)
        self.model = model.to(self.device)


def _read_back(pending: list[torch.Tensor], losses: list[float]) -> None:
    """Append the values of the scalar tensors ``pending`` to ``losses`` (one read from their device) and empty it.

    Raises
    ------
    HeadError
        A loss is not finite: training diverged (or met a singular system on a GPU).
    """
    if pending:
        import torch

        values = torch.stack(pending).tolist()
        pending.clear()
        bad = next((i for i, value in enumerate(values) if not math.isfinite(value)), None)
        if bad is not None:
            step = len(losses) + bad + 1
            raise HeadError(
                f"the training loss is not finite ({values[bad]}) at step {step}: training diverged, the weights are "
                "unusable. Lower the learning rate or check the input features for extreme values."
            )
        losses.extend(values)
