"""Full shapes for GeoLoRA training: loaded, decimated and reduced to one piece.

Every full shape is loaded once, decimated when it has more than ``max_vertices`` vertices
(quadric decimation, as the GeoLoRA release does above 12,000) and reduced to its largest
connected component (geodesics between components are infinite). Its geodesic matrix is
`geofeat.train.geodesics`'s.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from geofeat.errors import TrainingError
from geofeat.geometry.partial import largest_component_submesh
from geofeat.mesh import MESH_SUFFIXES, Mesh, load_mesh
from geofeat.runtime.progress import progress_bar

log = logging.getLogger(__name__)

__all__ = [
    "OFFICIAL_TRAINING_SETS",
    "decimate",
    "load_training_shapes",
    "official_training_files",
    "prepare_full_shape",
]


def decimate(mesh: Mesh, max_vertices: int) -> Mesh:
    """Quadric decimation to about ``max_vertices`` vertices (unchanged when already below), as the GeoLoRA release.

    The fraction ``1 - max_vertices / V`` of the faces is removed (trimesh's
    ``simplify_quadric_decimation``, fast-simplification's quadric decimation), so the result
    has about ``max_vertices`` vertices.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh with V vertices.
    max_vertices : int

    Returns
    -------
    Mesh
        The mesh itself when ``V <= max_vertices``; otherwise a new mesh named like it.
    """
    if mesh.n_vertices <= max_vertices:
        return mesh
    import trimesh

    try:  # as the GeoLoRA release: remove the fraction 1 - max_vertices / V of the faces
        simplified = trimesh.Trimesh(np.array(mesh.verts), np.array(mesh.faces), process=False).simplify_quadric_decimation(
            1.0 - max_vertices / mesh.n_vertices
        )
    except (ImportError, ModuleNotFoundError) as exc:
        raise TrainingError(
            f"{mesh.name!r} has {mesh.n_vertices} vertices (> {max_vertices}) and decimating it needs the "
            "fast-simplification package: pip install fast-simplification"
        ) from exc
    out = Mesh(np.asarray(simplified.vertices, dtype=np.float64), np.asarray(simplified.faces, dtype=np.int64), mesh.name)
    log.info("decimated %s from %d to %d vertices", mesh.name, mesh.n_vertices, out.n_vertices)
    return out


def prepare_full_shape(mesh: Mesh, max_vertices: int) -> Mesh:
    """Decimate (when too large) and keep the largest connected component.

    Raises
    ------
    TrainingError
        A point cloud (training renders triangles).
    """
    if mesh.faces is None:
        raise TrainingError(f"{mesh.name!r} is a point cloud; GeoLoRA training renders meshes, give triangle meshes.")
    mesh = decimate(mesh, max_vertices)
    kept, _, _ = largest_component_submesh(mesh, name=mesh.name)
    if kept.n_vertices < mesh.n_vertices:
        log.warning("%s: kept its largest connected component (%d of %d vertices)", mesh.name, kept.n_vertices, mesh.n_vertices)
    return kept if kept.n_vertices < mesh.n_vertices else mesh


#: The official release's training sets (``config/train/*.yaml`` of vikiehm/geo-lora): the
#: folder under the data root and which of its meshes are trained on.
OFFICIAL_TRAINING_SETS = {
    "faust": "FAUST_r/off: the first 80 shapes (sorted by name)",
    "becos": "BeCoS/full_full/train: every shape of the pair folders, each once",
    "becos_without_shrec16": "BeCoS/full_full/train without the SHREC'16 classes (cat, dog, michael, david, victoria, "
    "wolf, centaur, horse)",
    "smal": "SMAL_r/off: the shapes whose name holds cow, dog, fox, lion or wolf, turned 180 degrees about x",
}
#: ``red_list`` of the official ``becos_without_shrec16`` configuration: file names matching one are left out.
SHREC16_RED_LIST = (
    *(rf"{name}[0-9]" for name in ("cat", "dog", "michael", "david", "victoria", "wolf", "centaur", "horse")),
    *(rf"{name}.off" for name in ("cat", "dog", "michael", "david", "victoria", "wolf", "centaur", "horse")),
)
#: ``pattern`` of the official ``smal`` configuration.
SMAL_PATTERN = ("cow", "dog", "fox", "lion", "wolf")


def official_training_files(name: str, root: str | os.PathLike | None) -> list[Path]:
    """The mesh files an official training configuration trains on, in a fixed order.

    The official data set lists folders with ``os.listdir``, whose order the file system
    decides; here names are sorted (BeCoS's pair folders by number), so the set is the
    official one and the order is the same everywhere.

    Parameters
    ----------
    name : str
        A key of `OFFICIAL_TRAINING_SETS`.
    root : str or os.PathLike, optional
        The folder holding ``FAUST_r/``, ``BeCoS/`` or ``SMAL_r/`` (``$GEOFEAT_DATA`` when None).

    Returns
    -------
    list of pathlib.Path

    Raises
    ------
    TrainingError
        A missing folder (with the expected layout) or no shape in it.
    """
    import re

    base = Path(root if root is not None else os.environ.get("GEOFEAT_DATA", ".")).expanduser()
    folder = {"faust": base / "FAUST_r" / "off", "smal": base / "SMAL_r" / "off"}.get(
        name, base / "BeCoS" / "full_full" / "train"
    )
    if not folder.is_dir():
        raise TrainingError(f"the {name!r} training set reads {folder}, which does not exist ({OFFICIAL_TRAINING_SETS[name]}).")
    if name == "faust":
        files = _folder_meshes(folder)[:80]
    elif name == "smal":
        files = [p for p in _folder_meshes(folder) if any(animal in p.name for animal in SMAL_PATTERN)]
    else:
        red_list = SHREC16_RED_LIST if name == "becos_without_shrec16" else ()
        files, seen = [], set()
        pairs = sorted((p for p in folder.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
        for pair in pairs:
            for path in sorted(pair.glob("*.off")):
                stem = path.name.split("_", 1)[-1]  # 0_<shape>.off and 1_<shape>.off are the same shape
                if stem not in seen and not any(re.search(pattern, path.name) for pattern in red_list):
                    seen.add(stem)
                    files.append(path)
    if not files:
        raise TrainingError(f"no training shape of the {name!r} set in {folder} ({OFFICIAL_TRAINING_SETS[name]}).")
    return files


def _folder_meshes(folder: Path) -> list[Path]:
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise TrainingError(f"{folder} holds no mesh file ({', '.join(MESH_SUFFIXES)}); give a folder of full shapes.")
    return files


def _dataset_meshes(name: str, root: str | None, split: str) -> list[Mesh]:
    from geofeat.datasets import load_dataset

    dataset = load_dataset(name, root=root, split=split)
    if not hasattr(dataset, "shape_names") or not hasattr(dataset, "mesh"):
        raise TrainingError(
            f"dataset {name!r} is not a collection of full shapes; train on 'faust_r' or 'scape_r', or on a folder of meshes."
        )
    return [dataset.mesh(shape) for shape in dataset.shape_names]


def load_training_shapes(
    data: str,
    *,
    root: str | None = None,
    split: str = "train",
    first: int | None = None,
    max_vertices: int = 12000,
    progress: bool = True,
) -> list[Mesh]:
    """The full shapes of a training run.

    Parameters
    ----------
    data : str
        A folder of meshes, a full-shape dataset name (``faust_r``, ``scape_r``) or an
        official training set (`OFFICIAL_TRAINING_SETS`: ``faust``, ``becos``,
        ``becos_without_shrec16``, ``smal``).
    root : str, optional
        Dataset root (``$GEOFEAT_DATA`` when None); only for dataset names.
    split : str
        Dataset split; only for dataset names.
    first : int, optional
        Keep the first N shapes.
    max_vertices : int
        Decimation threshold.
    progress : bool

    Returns
    -------
    list of Mesh
        Connected triangle meshes with at most about ``max_vertices`` vertices.
    """
    folder = Path(data).expanduser()
    if data in OFFICIAL_TRAINING_SETS:
        files = official_training_files(data, root)[:first]
        meshes = [load_mesh(p) for p in progress_bar(files, desc="loading shapes", unit="shape", show=progress)]
        if data == "smal":  # stored upside down: turned as the official data set does
            meshes = [Mesh(m.verts @ np.diag([1.0, -1.0, -1.0]), m.faces, m.name) for m in meshes]
    elif folder.is_dir():
        files = _folder_meshes(folder)[:first]
        meshes = [load_mesh(p) for p in progress_bar(files, desc="loading shapes", unit="shape", show=progress)]
    elif os.sep in data or data.startswith("."):
        raise TrainingError(f"the training data folder {data} does not exist.")
    else:
        meshes = _dataset_meshes(data, root, split)[:first]
    return [prepare_full_shape(m, max_vertices) for m in meshes]
