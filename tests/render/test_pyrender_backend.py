"""The OpenGL backend (``gl`` extra) against the PyTorch rasterizer.

pyrender renders with 4x multisampling and reads one depth sample per pixel. That sample
is not at the pixel centre (on Mesa it is the standard sample 0, at (0.375, 0.125) from the
bottom-left pixel corner, i.e. (-0.125, +0.375) from the centre in our x-right, y-down
pixels). Shifting our principal point by the opposite offset makes our rasterizer sample
where OpenGL did, and then the two must agree to float precision: any error in the camera
pose, intrinsics, image orientation or depth definition would break that.
"""

import dataclasses
import importlib.util

import numpy as np
import pytest
import torch

from geofeat.errors import MissingDependencyError
from geofeat.render import (
    RasterSettings,
    fibonacci_cameras,
    gl_platform,
    official_grid_cameras,
    orbit_cameras,
    pyrender_depth,
    rasterize,
)

#: Candidate positions of the depth sample relative to the pixel centre (x right, y down, pixels).
SAMPLE_OFFSETS = [(0.0, 0.0), (-0.125, 0.375), (0.125, 0.375), (-0.375, -0.125), (0.375, 0.125), (0.125, -0.375)]


@pytest.fixture(scope="module")
def gl():
    """The GL platform; skips (with the reason) only when this machine has no headless OpenGL."""
    try:
        return gl_platform()
    except MissingDependencyError as err:
        pytest.skip(f"environment, not geofeat: {err}")


def agreement(ours, theirs, diagonal):
    ours_fg, theirs_fg = torch.isfinite(ours), torch.isfinite(theirs)
    both = ours_fg & theirs_fg
    iou = float(both.sum() / (ours_fg | theirs_fg).sum())
    error = (ours[both] - theirs[both]).abs() / diagonal
    return iou, float(error.median()), float(torch.quantile(error, 0.99))


def best_sample_offset(mesh, cams, gl_depth):
    cx, cy = cams.principal_point
    results = []
    for dx, dy in SAMPLE_OFFSETS:
        # sampling at centre + (dx, dy) = moving the principal point by -(dx, dy)
        shifted = dataclasses.replace(cams, principal_point=(cx - dx, cy - dy))
        depth = rasterize(mesh, None, shifted).depth
        results.append((agreement(depth, gl_depth, mesh.bbox_diagonal()), (dx, dy)))
    return max(results, key=lambda r: (r[0][0], -r[0][2]))


@pytest.mark.parametrize("layout", ["official", "uniform_offcentre"])
def test_depth_maps_agree_with_the_rasterizer_on_faust(gl, faust_mesh, layout):
    if layout == "official":
        cams = official_grid_cameras(faust_mesh, 9, image_size=(96, 128), device="cpu")
    else:  # portrait images and an off-centre principal point
        cams = fibonacci_cameras(faust_mesh, 4, image_size=(128, 80), device="cpu")
        cams = dataclasses.replace(cams, principal_point=(36.3, 70.2))
    gl_depth = pyrender_depth(faust_mesh, None, cams)
    assert gl_depth.shape == (len(cams), *cams.image_size) and gl_depth.dtype == torch.float32
    assert torch.isinf(gl_depth).any() and torch.isfinite(gl_depth).any()
    # at pixel centres: same silhouettes up to a pixel's edge, depths within the sample offset's slope
    iou, median, _ = agreement(rasterize(faust_mesh, None, cams).depth, gl_depth, faust_mesh.bbox_diagonal())
    assert iou > 0.9 and median < 5e-3
    # at OpenGL's sample position: the same picture
    (iou, median, p99), offset = best_sample_offset(faust_mesh, cams, gl_depth)
    assert iou > 0.995, f"best sample offset {offset}: foreground IoU {iou:.4f}"
    assert median < 1e-5 and p99 < 1e-4, f"best sample offset {offset}: depth error median {median:.2e}, p99 {p99:.2e} diagonals"


def test_culling_switch(gl):
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], dtype=float) * 5  # fills the view
    faces = np.array([[0, 1, 2], [0, 2, 3]])  # front side +z
    behind = orbit_cameras(np.zeros(3), 3.0, [0.0], [180.0], 16, device="cpu")
    assert torch.isinf(pyrender_depth(verts, faces, behind)).all()
    unculled = pyrender_depth(verts, faces, behind, cull_backfaces=False)
    ours = rasterize(verts, faces, behind, RasterSettings(cull_backfaces=False)).depth
    assert torch.isfinite(unculled).all()
    torch.testing.assert_close(unculled, ours, rtol=1e-4, atol=0)  # a plane facing the camera: z is constant


def test_numpy_is_left_unpatched(gl):
    verts = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0]], dtype=float)
    pyrender_depth(verts, np.array([[0, 1, 2]]), orbit_cameras(np.zeros(3), 3.0, [0.0], [0.0], 8, device="cpu"))
    if np.lib.NumpyVersion(np.__version__) >= "2.0.0":
        assert not hasattr(np, "infty")


def test_missing_pyrender_names_the_gl_extra(monkeypatch):
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyrender" else real_find_spec(name, *a))
    cams = orbit_cameras(np.zeros(3), 3.0, [0.0], [0.0], 8, device="cpu")
    with pytest.raises(MissingDependencyError, match=r"geofeat\[gl\]") as info:
        pyrender_depth(np.eye(3), np.array([[0, 1, 2]]), cams)
    assert "libegl1" in str(info.value) and "libosmesa6" in str(info.value)
