"""Spectral descriptors: Heat Kernel Signature and Wave Kernel Signature."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from geofeat.checks import check_boolean, check_choice, check_integer
from geofeat.descriptors.base import Descriptor
from geofeat.errors import DescriptorError
from geofeat.geometry.laplacian import LAPLACIANS
from geofeat.geometry.spectral import SpectralBasis, mass_normalize, spectral_basis
from geofeat.mesh import Mesh

#: The WKS energy range is empty when the log non-zero eigenvalues span less than this
#: (repeated eigenvalues of a symmetric shape, to round-off, span about 1e-15).
WKS_MIN_LOG_RANGE = 1e-8


def _checked_spectral_params(descriptor: str, n_eig, n_descr, laplacian, normalize) -> dict:
    """The four parameters checked by type and range, in canonical Python types."""
    params = {
        "n_eig": check_integer(n_eig, "n_eig", owner=descriptor, low=1),
        "n_descr": check_integer(n_descr, "n_descr", owner=descriptor, low=1),
        "laplacian": check_choice(laplacian, "laplacian", LAPLACIANS, owner=descriptor),
        "normalize": check_boolean(normalize, "normalize", owner=descriptor),
    }
    if params["n_eig"] < 3:
        raise DescriptorError(f"{descriptor}: n_eig must be at least 3 to span a range of scales; found {n_eig}.")
    return params


def nonzero_spectrum(basis: SpectralBasis) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs past the zero modes (`SpectralBasis.n_zero`: one per connected component), shapes (K',) and (V, K')."""
    evals = np.abs(basis.evals)
    n_zero = basis.n_zero
    if basis.k - n_zero < 2:
        raise DescriptorError(f"only {basis.k - n_zero} non-zero eigenvalue(s) among {basis.k}: raise n_eig.")
    return evals[n_zero:], basis.evecs[:, n_zero:]


def wave_kernel_signature(basis: SpectralBasis, n_descr: int) -> np.ndarray:
    """Wave Kernel Signature (Aubry et al. 2011) with the automatic energy range of pyFM/ULRSSM.

    Parameters
    ----------
    basis : SpectralBasis
        Eigenpairs, shapes (K,) and (V, K).
    n_descr : int
        Number of energies E.

    Returns
    -------
    numpy.ndarray, shape (V, E), float64
        ``sum_k phi_k(x)^2 g_e(lambda_k) / sum_k g_e(lambda_k)`` with Gaussians
        ``g_e(lambda) = exp(-(e - log lambda)^2 / (2 sigma^2))`` on log-eigenvalues, energies
        ``e`` evenly spaced on ``[log lambda_min + 2 sigma, log lambda_max - 2 sigma]`` and
        ``sigma = 7 (log lambda_max - log lambda_min) / E``, over the non-zero eigenvalues.

    Raises
    ------
    DescriptorError
        The non-zero eigenvalues are all equal (an empty energy range), or fewer than two.
    """
    evals, evecs = nonzero_spectrum(basis)
    log_evals = np.log(evals)
    e_min, e_max = log_evals.min(), log_evals.max()
    if not e_max - e_min > WKS_MIN_LOG_RANGE:
        raise DescriptorError(
            f"wks: the {evals.size} non-zero eigenvalue(s) among the first {basis.k} are all equal to {evals[0]:.6g} "
            f"(log range {e_max - e_min:.2g}); the Wave Kernel Signature spaces its energies over their range, so it "
            "would be undefined (NaN). Symmetric shapes repeat eigenvalues: raise n_eig."
        )
    sigma = 7.0 * (e_max - e_min) / n_descr
    energies = np.linspace(e_min + 2 * sigma, e_max - 2 * sigma, n_descr)
    coefs = np.exp(-np.square(energies[:, None] - log_evals[None, :]) / (2 * sigma**2))  # (E, K)
    return (np.square(evecs) @ coefs.T) / coefs.sum(axis=1)[None, :]


def heat_kernel_signature(basis: SpectralBasis, n_descr: int) -> np.ndarray:
    """Heat Kernel Signature (Sun et al. 2009) at log-spaced times, scaled by the heat trace.

    Parameters
    ----------
    basis : SpectralBasis
        Eigenpairs, shapes (K,) and (V, K).
    n_descr : int
        Number of times T.

    Returns
    -------
    numpy.ndarray, shape (V, T), float64
        ``sum_k exp(-t lambda_k) phi_k(x)^2 / sum_k exp(-t lambda_k)`` for ``T`` times
        log-spaced between ``4 ln 10 / lambda_max`` and ``4 ln 10 / lambda_1`` (the
        smallest non-zero eigenvalue). The sums run over all K eigenpairs, the constant
        one included.
    """
    evals = np.abs(basis.evals)
    nonzero, _ = nonzero_spectrum(basis)
    times = np.geomspace(4 * np.log(10) / nonzero.max(), 4 * np.log(10) / nonzero.min(), n_descr)
    coefs = np.exp(-np.outer(times, evals))  # (T, K)
    return (np.square(basis.evecs) @ coefs.T) / coefs.sum(axis=1)[None, :]


class SpectralSignature(Descriptor):
    """Shared body of HKS and WKS: a signature of the Laplace-Beltrami eigenpairs.

    Subclasses set ``signature`` (a function ``(basis, n_descr) -> (V, n_descr)``) and
    declare their keyword parameters ``n_eig``, ``n_descr``, ``laplacian``, ``normalize``.
    """

    signature: Callable[[SpectralBasis, int], np.ndarray] | None = None
    n_eig: int
    n_descr: int
    laplacian: str
    normalize: bool

    def _store(self, n_eig: int, n_descr: int, laplacian: str, normalize: bool) -> None:
        for name, value in _checked_spectral_params(self.name, n_eig, n_descr, laplacian, normalize).items():
            setattr(self, name, value)

    def compute(self, mesh: Mesh) -> np.ndarray:
        """Signature of shape (V, n_descr), channels mass-normalised when ``normalize``."""
        signature = type(self).signature
        if signature is None:
            raise NotImplementedError(f"{type(self).__name__} sets no signature function")
        basis = spectral_basis(mesh, self.n_eig, self.laplacian)
        features = signature(basis, self.n_descr)
        return mass_normalize(features, basis.mass) if self.normalize else features


class WKS(SpectralSignature):
    """Wave Kernel Signature, as ULRSSM and pyFM compute it.

    Parameters
    ----------
    n_eig : int
        Number of Laplace-Beltrami eigenpairs.
    n_descr : int
        Number of energies (output channels).
    laplacian : {"robust", "cotan"}
        Discretisation of the Laplacian (``"cotan"`` matches pyFM's ``TriMesh.process``).
    normalize : bool
        Scale each channel to unit mass-weighted L2 norm, as ULRSSM does.

    Notes
    -----
    Differences from pyFM's ``mesh_WKS`` (pyfmaps 1.3):

    * ``normalize=True`` (the default, as in ULRSSM) scales each channel by its
      mass-weighted norm; pyFM's ``mesh_WKS`` does not, so compare with ``normalize=False``.
    * The energy range starts at the smallest non-zero eigenvalue. pyFM takes the second
      eigenvalue, which is the same on a connected mesh but zero (log = -inf) on a mesh
      with several components.
    * The default Laplacian is the robust one; pyFM uses the cotangent Laplacian.
    """

    name = "wks"
    version = "1"
    signature = staticmethod(wave_kernel_signature)

    def __init__(self, *, n_eig: int = 128, n_descr: int = 128, laplacian: str = "robust", normalize: bool = True):
        self._store(n_eig, n_descr, laplacian, normalize)


class HKS(SpectralSignature):
    """Heat Kernel Signature with log-spaced times.

    Parameters
    ----------
    n_eig : int
        Number of Laplace-Beltrami eigenpairs.
    n_descr : int
        Number of time scales (output channels).
    laplacian : {"robust", "cotan"}
        Discretisation of the Laplacian (``"cotan"`` matches pyFM's ``TriMesh.process``).
    normalize : bool
        Scale each channel to unit mass-weighted L2 norm.

    Notes
    -----
    With ``normalize=False`` and ``laplacian="cotan"`` this equals pyFM's ``mesh_HKS``
    (times from the same automatic range, scaled by the heat trace), except that the time
    range starts from the smallest non-zero eigenvalue rather than the second one (the same
    on a connected mesh). DiffusionNet's ``compute_hks_autoscale`` uses fixed times
    ``logspace(-2, 0)`` without scaling: a different descriptor.
    """

    name = "hks"
    version = "1"
    signature = staticmethod(heat_kernel_signature)

    def __init__(self, *, n_eig: int = 128, n_descr: int = 16, laplacian: str = "robust", normalize: bool = True):
        self._store(n_eig, n_descr, laplacian, normalize)
