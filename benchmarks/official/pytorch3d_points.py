#!/usr/bin/env python
"""pytorch3d's ``PointsRasterizer`` on arrays from an .npz, for `benchmarks.parity.point_renderer`.

Runs in an environment with pytorch3d (here a CPU build from source), not geofeat's; it
imports nothing of geofeat. ``PYTORCH3D_SRC`` (optional) is put first on ``sys.path``, for a
source tree built in place::

    python pytorch3d_points.py IN.npz OUT.npz [PYTORCH3D_SRC]

IN.npz holds, in pytorch3d's conventions:

* ``points`` (P, 3) float32: world points;
* ``R`` (N, 3, 3) and ``T`` (N, 3) float32: the views (row vectors, ``X_view = X @ R + T``);
* ``focal_length`` (): of ``PerspectiveCameras`` in NDC (principal point 0);
* ``image_size`` (2,): (H, W);
* ``radius`` (N, P) float32: each point's disc radius in each view, in NDC units.

Each view is drawn alone with ``points_per_pixel=1`` and ``bin_size=0`` (the CPU has only
the naive rasterizer). OUT.npz holds ``idx`` (N, H, W) int64 (-1 on background), ``zbuf``
(N, H, W) float32 (view-space z, -1 on background), ``dists`` (N, H, W) float32 (squared NDC
distance of the pixel from its point) and ``seconds`` (N,): the wall time of each view.
"""

import sys
import time

import numpy as np


def rasterize(arrays):
    """pytorch3d's nearest point, depth and squared distance per pixel of every view."""
    import torch
    from pytorch3d.renderer import PerspectiveCameras, PointsRasterizationSettings, PointsRasterizer
    from pytorch3d.structures import Pointclouds

    points = torch.as_tensor(arrays["points"], dtype=torch.float32)
    height, width = (int(s) for s in arrays["image_size"])
    outputs = {"idx": [], "zbuf": [], "dists": [], "seconds": []}
    for view in range(len(arrays["R"])):
        cameras = PerspectiveCameras(
            focal_length=float(arrays["focal_length"]),
            R=torch.as_tensor(arrays["R"][view : view + 1], dtype=torch.float32),
            T=torch.as_tensor(arrays["T"][view : view + 1], dtype=torch.float32),
        )
        settings = PointsRasterizationSettings(
            image_size=(height, width),
            radius=torch.as_tensor(arrays["radius"][view : view + 1], dtype=torch.float32),
            points_per_pixel=1,
            bin_size=0,
        )
        start = time.perf_counter()
        fragments = PointsRasterizer(cameras=cameras, raster_settings=settings)(Pointclouds(points=[points]))
        outputs["seconds"].append(time.perf_counter() - start)
        outputs["idx"].append(fragments.idx[0, ..., 0].long().numpy())
        outputs["zbuf"].append(fragments.zbuf[0, ..., 0].numpy())
        outputs["dists"].append(fragments.dists[0, ..., 0].numpy())
    return {name: np.stack(values) if name != "seconds" else np.array(values) for name, values in outputs.items()}


def main(argv):
    if len(argv) not in (3, 4):
        raise SystemExit(__doc__)
    if len(argv) == 4:
        sys.path.insert(0, argv[3])
    arrays = dict(np.load(argv[1]))
    np.savez(argv[2], **rasterize(arrays))


if __name__ == "__main__":
    main(sys.argv)
