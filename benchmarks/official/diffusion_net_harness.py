#!/usr/bin/env python
"""DiffusionNet's own operators of a point cloud or a mesh, for `benchmarks.parity.diffusion_net_cloud`
and `benchmarks.speed.diffusion_net_operators`.

Runs in an environment of the DiffusionNet reference code (nmwsharp/diffusion-net), not
geofeat's: ``python -m venv dn-venv`` and ``dn-venv/bin/pip install torch numpy scipy
robust_laplacian potpourri3d scikit-learn`` (the reference runs on the CPU as it is). It
imports ``diffusion_net`` from the clone given on the command line:

    dn-venv/bin/python diffusion_net_harness.py CLONE IN.npz OUT.npz

IN.npz holds ``verts`` (V, 3) float64, ``k_eig`` and, for a mesh, ``faces`` (F, 3). They
are passed to the reference's ``compute_operators`` as float64 and int64 tensors; without
``faces`` the face tensor is empty (its point-cloud path). OUT.npz holds ``frames`` (V, 3, 3), ``mass`` (V,), ``evals`` (k,), ``evecs``
(V, k), and the sparse ``L``, ``gradX`` and ``gradY`` as ``*_row``, ``*_col`` and ``*_data``
(COO), all as the reference returns them (float64 tensors; its sparse values pass through
float32 on the way), and ``wall_time`` (seconds of the call). For a mesh it also writes
``L_exact_*``: the float64 cotan Laplacian that the reference's eigensolve starts from
(``potpourri3d.cotan_laplacian`` with the reference's ``denom_eps``), computed after the
timed call.
"""

import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    clone, source, target = sys.argv[1:4]
    sys.path.insert(0, str(Path(clone) / "src"))
    import torch
    from diffusion_net.geometry import compute_operators

    with np.load(source) as inputs:
        verts = torch.from_numpy(np.asarray(inputs["verts"], dtype=np.float64))
        k_eig = int(inputs["k_eig"])
        faces = np.asarray(inputs["faces"], dtype=np.int64) if "faces" in inputs else np.zeros((0, 3), dtype=np.int64)
    faces = torch.from_numpy(faces)
    start = time.perf_counter()
    frames, mass, lap, evals, evecs, grad_x, grad_y = compute_operators(verts, faces, k_eig)
    wall = time.perf_counter() - start
    out = {"frames": frames, "mass": mass, "evals": evals, "evecs": evecs}
    arrays = {name: value.numpy() for name, value in out.items()}
    for name, matrix in (("L", lap), ("gradX", grad_x), ("gradY", grad_y)):
        matrix = matrix.coalesce()
        arrays[f"{name}_row"], arrays[f"{name}_col"] = matrix.indices().numpy()
        arrays[f"{name}_data"] = matrix.values().numpy()
    if faces.numel():  # the float64 Laplacian the reference's eigsh saw, from the same call it makes
        import potpourri3d as pp3d

        exact = pp3d.cotan_laplacian(verts.numpy(), faces.numpy(), denom_eps=1e-10).tocoo()
        arrays["L_exact_row"], arrays["L_exact_col"], arrays["L_exact_data"] = exact.row, exact.col, exact.data
    np.savez(target, wall_time=wall, **arrays)


if __name__ == "__main__":
    main()
