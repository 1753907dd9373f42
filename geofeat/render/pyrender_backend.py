"""Optional OpenGL depth maps through pyrender (the ``gl`` extra), headless via EGL or OSMesa.

The default renderer is `geofeat.render.rasterize` (pure PyTorch). This backend exists to
cross-check it and for users who prefer OpenGL: `pyrender_depth` renders depth maps from the
same `Cameras`, in the same pixel convention, with +inf on background.

Environment
-----------
* ``pip install "geofeat[gl]"`` installs pyrender (0.1.45 pins PyOpenGL 3.1.0).
* Headless rendering needs EGL (``libegl1`` with a Mesa or NVIDIA driver) or OSMesa
  (``libosmesa6``; with pyrender's PyOpenGL 3.1.0 pin OSMesa does not work, because that
  PyOpenGL lacks ``OSMesaCreateContextAttribs``: EGL is the one that works out of the box).
* PyOpenGL picks its platform when it is first imported, from ``PYOPENGL_PLATFORM``, and
  pyrender reads the same variable whenever it opens a context. If the variable is unset,
  the first call tries ``"egl"`` then ``"osmesa"``, each in a short-lived subprocess (a
  broken GL driver can crash a process), and sets ``os.environ["PYOPENGL_PLATFORM"]`` to the
  first that renders, before importing pyrender here. Set the variable yourself to skip the
  probe; if OpenGL was already imported without it, that import's platform is used.
* pyrender 0.1.45 uses ``np.infty``, which numpy 2 removed. While pyrender runs, missing
  aliases from `_NUMPY_ALIASES` are put back on the numpy module and removed afterwards
  (nothing is left patched once `pyrender_depth` returns).

Differences from the PyTorch rasterizer
---------------------------------------
pyrender renders with 4x multisampling and reads back one depth sample per pixel, which is
not exactly the pixel centre; depth agrees with `rasterize` to a small fraction of a pixel's
depth gradient on smooth surfaces, and the foreground masks differ along silhouettes.
OpenGL clips faces at the near plane where `rasterize` drops them.
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os
import subprocess
import sys
from collections.abc import Iterator

import numpy as np
import torch

from geofeat.errors import MissingDependencyError, RenderError
from geofeat.mesh import Mesh
from geofeat.render.cameras import Cameras
from geofeat.render.rasterizer import mesh_tensors

log = logging.getLogger(__name__)

#: Headless PyOpenGL platforms, in the order they are tried.
GL_PLATFORMS = ("egl", "osmesa")
#: numpy names that pyrender 0.1.45 still uses and numpy 2 removed, and the names they stood for.
_NUMPY_ALIASES = {"infty": "inf"}
_PROBE_TIMEOUT_S = 120
_SYSTEM_PACKAGES = "libegl1 (EGL, with a Mesa or NVIDIA driver) or libosmesa6 (OSMesa)"

_PROBE_CODE = """
import numpy as np
for name, target in {aliases!r}.items():
    if not hasattr(np, name):
        setattr(np, name, getattr(np, target))
import pyrender
renderer = pyrender.OffscreenRenderer(8, 8)
renderer.delete()
print("ok")
"""


def gl_platform() -> str:
    """The headless PyOpenGL platform that `pyrender_depth` uses, probing EGL then OSMesa if unset.

    Returns
    -------
    str
        ``os.environ["PYOPENGL_PLATFORM"]`` after the choice (``"egl"`` or ``"osmesa"``).

    Raises
    ------
    MissingDependencyError
        pyrender is not installed, or no headless platform can open a context (the message
        gives each platform's error and the system packages to install).
    """
    _require_pyrender()
    chosen = os.environ.get("PYOPENGL_PLATFORM")
    if chosen:
        return chosen
    if "OpenGL" in sys.modules:
        raise MissingDependencyError(
            "OpenGL was imported before PYOPENGL_PLATFORM was set, so no headless platform can be chosen now. "
            "Set PYOPENGL_PLATFORM=egl (or osmesa) before anything imports OpenGL or pyrender."
        )
    failures = []
    for platform in GL_PLATFORMS:
        error = _probe(platform)
        if error is None:
            os.environ["PYOPENGL_PLATFORM"] = platform
            log.info("pyrender backend: using PYOPENGL_PLATFORM=%s", platform)
            return platform
        failures.append(f"{platform}: {error}")
    raise MissingDependencyError(
        "pyrender is installed but no headless OpenGL platform works here ("
        + "; ".join(failures)
        + f"). Install the system packages {_SYSTEM_PACKAGES}, e.g. `apt-get install libegl1 libgl1 libosmesa6`; "
        "OSMesa also needs PyOpenGL >= 3.1.5, newer than pyrender's pin. The default renderer "
        "geofeat.render.rasterize needs none of this."
    )


def pyrender_depth(
    verts: Mesh | np.ndarray | torch.Tensor,
    faces: np.ndarray | torch.Tensor | None,
    cameras: Cameras,
    cull_backfaces: bool = True,
) -> torch.Tensor:
    """Depth maps of a mesh rendered with pyrender (OpenGL) from the given cameras.

    Parameters
    ----------
    verts : Mesh or array_like, shape (V, 3)
        A `Mesh` (pass ``faces=None``) or world-space vertex positions.
    faces : array_like of int, shape (F, 3), or None
    cameras : Cameras
        Any device; the work is done by OpenGL and the result moved to ``cameras.device``.
    cull_backfaces : bool
        Skip faces seen from behind (OpenGL back-face culling, counter-clockwise front faces).

    Returns
    -------
    torch.Tensor, shape (N, H, W), float32
        Camera-space z (distance along the optical axis) per pixel; +inf on background.
    """
    verts_t, faces_t = mesh_tensors(verts, faces, "cpu")
    verts_np, faces_np = verts_t.numpy(), faces_t.numpy()
    z_near, z_far = _depth_range(verts_np, cameras)
    gl_platform()
    with _numpy_aliases():
        pyrender = _import_pyrender()
        scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.ones(3))
        material = pyrender.MetallicRoughnessMaterial(doubleSided=not cull_backfaces)  # used by the colour pass
        primitive = pyrender.Primitive(
            positions=verts_np.astype(np.float32), indices=faces_np.astype(np.uint32), material=material
        )
        scene.add(pyrender.Mesh(primitives=[primitive]))
        cx, cy = cameras.principal_point
        focal = cameras.focal_length
        camera = pyrender.IntrinsicsCamera(fx=focal, fy=focal, cx=cx, cy=cy, znear=z_near, zfar=z_far)
        camera_node = scene.add(camera, pose=np.eye(4))
        depth = np.empty((len(cameras), *cameras.image_size), dtype=np.float32)
        flags = _render_flags(pyrender, cull_backfaces)
        renderer = _offscreen_renderer(pyrender, cameras.width, cameras.height)
        try:
            for view, pose in enumerate(_opengl_poses(cameras)):
                scene.set_pose(camera_node, pose)
                rendered = renderer.render(scene, flags=flags)
                depth[view] = rendered if cull_backfaces else rendered[1]
        finally:
            renderer.delete()
    depth[depth <= 0] = np.inf
    return torch.from_numpy(depth).to(cameras.device)


def _require_pyrender() -> None:
    if importlib.util.find_spec("pyrender") is None:
        raise MissingDependencyError(
            'the OpenGL depth backend needs pyrender: install the gl extra, `pip install "geofeat[gl]"`, '
            f"and the system packages {_SYSTEM_PACKAGES}. The default renderer geofeat.render.rasterize needs neither."
        )


def _import_pyrender():
    try:
        import pyrender
    except Exception as err:  # PyOpenGL raises several error types when its platform library is missing
        raise MissingDependencyError(
            f"pyrender could not be imported with PYOPENGL_PLATFORM={os.environ.get('PYOPENGL_PLATFORM')!r}: "
            f"{type(err).__name__}: {err}. Install the system packages {_SYSTEM_PACKAGES}, or unset PYOPENGL_PLATFORM "
            "to let geofeat try egl, then osmesa."
        ) from err
    return pyrender


def _probe(platform: str) -> str | None:
    """None when pyrender can open an offscreen context with ``platform`` (in a subprocess), else the error."""
    env = dict(os.environ, PYOPENGL_PLATFORM=platform)
    code = _PROBE_CODE.format(aliases=_NUMPY_ALIASES)
    try:
        result = subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=_PROBE_TIMEOUT_S, check=False
        )
    except subprocess.TimeoutExpired:
        return f"opening a context took more than {_PROBE_TIMEOUT_S} s"
    if result.returncode == 0 and result.stdout.strip().endswith("ok"):
        return None
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    return lines[-1] if lines else f"exit status {result.returncode}"


@contextlib.contextmanager
def _numpy_aliases() -> Iterator[None]:
    """Temporarily restore numpy names that pyrender needs (see the module notes)."""
    added = [name for name in _NUMPY_ALIASES if not hasattr(np, name)]
    for name in added:
        setattr(np, name, getattr(np, _NUMPY_ALIASES[name]))
    try:
        yield
    finally:
        for name in added:
            delattr(np, name)


def _offscreen_renderer(pyrender, width: int, height: int):
    try:
        return pyrender.OffscreenRenderer(viewport_width=width, viewport_height=height)
    except Exception as err:  # GL errors come from several libraries with their own exception types
        raise MissingDependencyError(
            f"pyrender could not open an offscreen OpenGL context with PYOPENGL_PLATFORM="
            f"{os.environ.get('PYOPENGL_PLATFORM')!r}: {type(err).__name__}: {err}. "
            f"Install the system packages {_SYSTEM_PACKAGES}, or set PYOPENGL_PLATFORM to another platform"
            " (OSMesa also needs PyOpenGL >= 3.1.5, newer than pyrender's pin; EGL works with the pin)."
        ) from err


def _render_flags(pyrender, cull_backfaces: bool) -> int:
    """pyrender's depth-only pass always culls back faces; without culling draw flat colour and keep the depth."""
    if cull_backfaces:
        return pyrender.RenderFlags.DEPTH_ONLY
    return pyrender.RenderFlags.FLAT | pyrender.RenderFlags.SKIP_CULL_FACES


def _opengl_poses(cameras: Cameras) -> np.ndarray:
    """Camera-to-world 4x4 poses in OpenGL's camera frame (x right, y up, looking down -z), shape (N, 4, 4)."""
    rotation = cameras.rotation.cpu().numpy()
    poses = np.tile(np.eye(4), (len(cameras), 1, 1))
    poses[:, :3, :3] = np.transpose(rotation, (0, 2, 1)) * np.array([1.0, -1.0, -1.0])  # flip y and z columns
    poses[:, :3, 3] = cameras.position.cpu().numpy()
    return poses


def _depth_range(verts: np.ndarray, cameras: Cameras) -> tuple[float, float]:
    """Near and far planes that hold the whole mesh in every view."""
    depth = cameras.world_to_camera(torch.from_numpy(verts).to(cameras.device))[..., 2]
    far = float(depth.max())
    if not far > 0:
        raise RenderError("the mesh lies entirely behind every camera; there is nothing to render.")
    near = float(depth.min())
    near = 0.5 * near if near > 0 else 1e-3 * far
    return near, 1.5 * far
