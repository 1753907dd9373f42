"""Rendering: cameras, a PyTorch rasterizer, a point renderer, gray Phong shading and an optional OpenGL backend.

>>> from geofeat.render import make_cameras, render_phong
>>> cameras = make_cameras(mesh, n_views=9, layout="official", image_size=224, device="auto")
>>> images, fragments = render_phong(mesh, None, cameras)
>>> images.shape, fragments.pix_to_face.shape
(torch.Size([9, 224, 224, 3]), torch.Size([9, 224, 224]))

Point clouds are drawn as camera-facing discs by `rasterize_points` (`render_points_phong`
shades them). The rasterizers and the shader run on ``cameras.device`` (CPU or CUDA) with no
compiled code.
`pyrender_depth` needs the ``gl`` extra and is imported lazily. The features lifted from these
renders to the vertices are `geofeat.multiview`'s.
"""

from geofeat.render.camera_layouts import (
    CAMERA_LAYOUTS,
    OFFICIAL_DISTANCE_FACTOR,
    fibonacci_cameras,
    fibonacci_directions,
    look_at_rotation,
    make_cameras,
    official_grid_angles,
    official_grid_cameras,
    orbit_cameras,
)
from geofeat.render.cameras import OFFICIAL_FOV_DEGREES, Cameras, ProjectedPoints
from geofeat.render.points import PointFragments, PointRasterizer, SplatSettings, rasterize_points, splat_points
from geofeat.render.pyrender_backend import gl_platform, pyrender_depth
from geofeat.render.rasterizer import Fragments, MeshRasterizer, RasterSettings, rasterize
from geofeat.render.shading import (
    PhongSettings,
    Rendering,
    cloud_normals,
    render_phong,
    render_points_phong,
    shade_phong,
    shade_points_phong,
    vertex_normals,
)

__all__ = [
    "CAMERA_LAYOUTS",
    "OFFICIAL_DISTANCE_FACTOR",
    "OFFICIAL_FOV_DEGREES",
    "Cameras",
    "Fragments",
    "MeshRasterizer",
    "PhongSettings",
    "PointFragments",
    "PointRasterizer",
    "ProjectedPoints",
    "RasterSettings",
    "Rendering",
    "SplatSettings",
    "cloud_normals",
    "fibonacci_cameras",
    "fibonacci_directions",
    "gl_platform",
    "look_at_rotation",
    "make_cameras",
    "official_grid_angles",
    "official_grid_cameras",
    "orbit_cameras",
    "pyrender_depth",
    "rasterize",
    "rasterize_points",
    "render_phong",
    "render_points_phong",
    "shade_phong",
    "shade_points_phong",
    "splat_points",
    "vertex_normals",
]
