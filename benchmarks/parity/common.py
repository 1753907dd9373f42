"""Shared pieces of the parity checks (``python -m benchmarks.parity``): importing a reference clone, measuring differences.

The reference repositories are imported at run time from the folder the user passes; their
code is never copied into geofeat. Several of them use the same top-level package names
(``utils``, ``networks``, ``models``, ``losses``), so `reference_import` forgets those
modules before and after each use.
"""

from __future__ import annotations

import contextlib
import importlib
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from geofeat.adapters.blocks.operators import SurfaceOperators, surface_operators

#: Top-level package names of the reference repositories.
REFERENCE_PACKAGES = ("utils", "networks", "models", "losses", "datasets", "metrics", "diffusion_net", "model", "dpfm")


class Stage(NamedTuple):
    """One row of a parity table: the largest difference between the two implementations at one stage."""

    stage: str
    max_abs: float
    scale: float
    note: str = ""

    @property
    def relative(self) -> float:
        """``max_abs / scale`` (the scale is the largest magnitude of the reference's values)."""
        return self.max_abs / self.scale if self.scale > 0 else self.max_abs


def compare(stage: str, ours, theirs, note: str = "") -> Stage:
    """`Stage` of two arrays or tensors of the same shape (compared in float64)."""
    a, b = _numpy(ours), _numpy(theirs)
    if a.shape != b.shape:
        raise ValueError(f"{stage}: shapes differ, ours {a.shape} vs reference {b.shape}")
    return Stage(stage, float(np.abs(a - b).max()) if a.size else 0.0, float(np.abs(b).max()) if b.size else 0.0, note)


def _numpy(value) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().to("cpu")
        value = value.to_dense() if value.is_sparse else value
        return value.double().numpy()
    return np.asarray(value, dtype=np.float64)


def _forget(names: tuple[str, ...]) -> None:
    for name in list(sys.modules):
        if name.split(".")[0] in names:
            del sys.modules[name]


@contextlib.contextmanager
def reference_import(repo: str | Path, subfolder: str = "") -> Iterator[Callable[[str], object]]:
    """Import modules of a reference clone: ``with reference_import(repo) as load: net = load("networks.x")``.

    Parameters
    ----------
    repo : path-like
        The user's clone of the reference repository.
    subfolder : str
        Folder inside the clone that the reference's own imports are relative to.
    """
    root = Path(repo).resolve() / subfolder
    if not root.is_dir():
        raise SystemExit(f"parity: {root} is not a folder; pass the path of your clone of the reference repository")
    _forget(REFERENCE_PACKAGES)
    sys.path.insert(0, str(root))
    try:
        yield importlib.import_module
    finally:
        sys.path.remove(str(root))
        _forget(REFERENCE_PACKAGES)


def as_surface_operators(ref: dict, mesh) -> SurfaceOperators:
    """A reference's operators (keys ``mass``, ``evals``, ``evecs``, ``gradX``, ``gradY``, ``frames``) in our record, same tensors.

    Faces and edges (which the reference keeps elsewhere) come from ``mesh``.
    """
    ours = surface_operators(mesh, 2, laplacian_kind="cotan", cache=False)
    return SurfaceOperators(
        mass=ref["mass"].float(),
        evals=ref["evals"].float(),
        evecs=ref["evecs"].float(),
        grad_x=ref["gradX"].float().coalesce(),
        grad_y=ref["gradY"].float().coalesce(),
        frames=ref["frames"].float(),
        faces=ours.faces,
        edges=ours.edges,
    )


def evecs_up_to_sign(ours: torch.Tensor, theirs: torch.Tensor, mass: torch.Tensor, k: int) -> Stage:
    """Eigenvectors compared up to sign: the largest ``1 - |<phi_ours, phi_ref>_M|`` over the first k."""
    inner = (ours[:, :k].double() * mass[:, None].double() * theirs[:, :k].double()).sum(0).abs()
    gap = (1 - inner).abs()
    return Stage(
        f"operators: eigenvectors 0..{k - 1} (1 - |<ours, ref>_M|)", float(gap.max()), 1.0, f"worst: index {int(gap.argmax())}"
    )


def seconds_per_call(fn: Callable[[], object], repeat: int = 3) -> float:
    """Median wall time of ``repeat`` calls of ``fn`` after one warm-up call."""
    fn()
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def cell(text: str) -> str:
    """``text`` safe inside a Markdown table cell: pipes escaped, ``<`` as an entity (``<ours, ref>`` is no HTML tag)."""
    return str(text).replace("|", "\\|").replace("<", "&lt;")


def markdown(rows: list[Stage], title: str) -> str:
    """A Markdown table of `Stage` rows."""
    lines = [f"### {title}", "", "| stage | max abs diff | reference scale | relative | note |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {cell(r.stage)} | {r.max_abs:.3g} | {r.scale:.3g} | {r.relative:.2e} | {cell(r.note)} |")
    return "\n".join(lines) + "\n"
