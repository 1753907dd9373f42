"""The `Descriptor` contract shared by every per-vertex feature."""

from __future__ import annotations

import inspect
import json
from typing import Any, ClassVar

import numpy as np

from geofeat.checks import canonical
from geofeat.errors import DescriptorError
from geofeat.mesh import Mesh


class Descriptor:
    """Base class of per-vertex descriptors.

    A subclass declares its parameters as explicit keyword arguments of ``__init__`` with
    defaults, stores each under the same attribute name and does no I/O there (the
    scikit-learn estimator rule). ``compute`` does the work; calling the descriptor checks
    and returns a C-contiguous float32 array of shape (V, dim) of finite values.

    Parameters are checked at the boundary with `geofeat.checks` (booleans are booleans;
    NumPy scalars are accepted and stored as the equal Python value).

    Class attributes
    ----------------
    name : str
        Registry name.
    version : str
        Code version; bump it whenever the output for the same parameters changes, so that
        old cache entries are not reused.
    """

    name: ClassVar[str] = ""
    version: ClassVar[str] = "1"

    @classmethod
    def param_names(cls) -> list[str]:
        """Names of the keyword parameters of ``__init__``."""
        signature = inspect.signature(cls.__init__)
        return [p.name for p in signature.parameters.values() if p.name != "self" and p.kind is p.KEYWORD_ONLY]

    @classmethod
    def param_defaults(cls) -> dict[str, Any]:
        """Default value of every parameter."""
        signature = inspect.signature(cls.__init__)
        return {name: signature.parameters[name].default for name in cls.param_names()}

    def get_params(self) -> dict[str, Any]:
        """Parameters in their canonical Python form (see `geofeat.checks.canonical`); they are part of the cache key."""
        return {name: canonical(getattr(self, name)) for name in self.param_names()}

    def params_json(self) -> str:
        """Canonical JSON of the parameters (sorted keys, no spaces)."""
        try:
            return json.dumps(self.get_params(), sort_keys=True, separators=(",", ":"), allow_nan=False)
        except (TypeError, ValueError) as err:
            raise DescriptorError(f"parameters of {self.name!r} must be JSON-serialisable: {err}") from err

    def weights_digest(self) -> str | None:
        """Digest of the model weights the descriptor uses, or None when it uses none."""
        return None

    def compute(self, mesh: Mesh) -> np.ndarray:
        """Return features of shape (V, dim); subclasses implement this."""
        raise NotImplementedError

    def prepare(self, mesh: Mesh) -> object | None:
        """Work for ``mesh`` that may run ahead, on a background thread, while another shape is computed.

        The DINO descriptors make the cameras and render the views here, on their device.
        Default: nothing (None).
        """
        return None

    def compute_prepared(self, mesh: Mesh, prepared: object | None) -> np.ndarray:
        """`compute` given what ``prepare(mesh)`` returned (None: nothing was prepared). Default: ``compute(mesh)``."""
        return self.compute(mesh)

    def __call__(self, mesh: Mesh, prepared: object | None = None) -> np.ndarray:
        """Compute features, shape (V, dim), C-contiguous float32, every value finite.

        Parameters
        ----------
        mesh : Mesh
        prepared : object, optional
            What ``prepare(mesh)`` returned, when it ran ahead (`compute_prepared`).

        Raises
        ------
        DescriptorError
            The output has the wrong shape or holds NaN or infinite values (also after the
            cast to float32: values beyond its range). Such output is never returned, so it
            is never cached either.
        """
        raw = self.compute(mesh) if prepared is None else self.compute_prepared(mesh, prepared)
        features = np.ascontiguousarray(raw, dtype=np.float32)
        if features.ndim != 2 or features.shape[0] != mesh.n_vertices:
            raise DescriptorError(f"descriptor {self.name!r} returned shape {features.shape}; expected ({mesh.n_vertices}, dim).")
        finite = np.isfinite(features)
        if not finite.all():
            bad_rows = ~finite.all(axis=1)
            n_nan = int(np.count_nonzero(np.isnan(features)))
            n_inf = int(features.size - np.count_nonzero(finite) - n_nan)
            problems = "; ".join(mesh.report()) or "none reported"
            raise DescriptorError(
                f"descriptor {self!r} gave non-finite features on mesh {mesh.name or '<unnamed>'!r}: "
                f"{n_nan} NaN and {n_inf} infinite value(s) in {int(bad_rows.sum())} of {mesh.n_vertices} vertices "
                f"(first at vertex {int(np.flatnonzero(bad_rows)[0])}); expected finite values. Nothing was cached. "
                f"Mesh problems: {problems}. Try other parameters (for spectral descriptors a larger n_eig) "
                "or repair the mesh."
            )
        return features

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in self.get_params().items())
        return f"{type(self).__name__}({args})"
