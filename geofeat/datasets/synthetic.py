"""A built-in, procedural collection of articulated humanoid shapes, for machines with no data.

One template body is made once from implicit primitives (tapered capsules and spheres,
blended with a smooth minimum) and meshed by marching cubes on a grid that is mirror
symmetric in x, so the template has an exact left-right vertex mirror map. Every shape of
the collection is that template deformed by linear blend skinning: per-bone scalings give
each individual its proportions, per-joint rotations give its pose. All shapes therefore
share the template's connectivity: the correspondence between any two is the identity, and
the mirrored correspondence is the template's mirror map.

Axes: y up, x from the body's right to its left, z forward (the face and toes point to +z).
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from geofeat.mesh import Mesh

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Bone:
    """A segment of the skeleton with its flesh.

    Attributes
    ----------
    name : str
    parent : int
        Index of the parent bone, -1 for the root.
    head, tail : tuple of float
        Rest-pose joint positions (the bone rotates about its head).
    radius_head, radius_tail : float
        Flesh radius at both ends (a tapered capsule).
    """

    name: str
    parent: int
    head: tuple[float, float, float]
    tail: tuple[float, float, float]
    radius_head: float
    radius_tail: float


def _mirror(bone: Bone, parent: int) -> Bone:
    flip = lambda p: (-p[0], p[1], p[2])  # noqa: E731
    return Bone(bone.name.replace("left", "right"), parent, flip(bone.head), flip(bone.tail), bone.radius_head, bone.radius_tail)


def _skeleton() -> tuple[Bone, ...]:
    """The rest-pose skeleton (an A-pose), left limbs mirrored to the right."""
    bones = [
        Bone("pelvis", -1, (0.0, 0.92, 0.0), (0.0, 1.12, 0.0), 0.135, 0.125),
        Bone("chest", 0, (0.0, 1.12, 0.0), (0.0, 1.42, 0.0), 0.125, 0.14),
        Bone("neck", 1, (0.0, 1.42, 0.0), (0.0, 1.58, 0.01), 0.055, 0.05),
        Bone("head", 2, (0.0, 1.58, 0.01), (0.0, 1.76, 0.02), 0.09, 0.085),
        Bone("nose", 3, (0.0, 1.66, 0.08), (0.0, 1.65, 0.115), 0.022, 0.012),
    ]
    left = [
        Bone("left_upper_arm", 1, (0.19, 1.40, 0.0), (0.38, 1.19, 0.0), 0.055, 0.045),
        Bone("left_forearm", -2, (0.38, 1.19, 0.0), (0.55, 1.00, 0.03), 0.042, 0.034),
        Bone("left_hand", -2, (0.55, 1.00, 0.03), (0.62, 0.91, 0.05), 0.035, 0.025),
        Bone("left_thigh", 0, (0.095, 0.92, 0.0), (0.11, 0.50, 0.0), 0.085, 0.058),
        Bone("left_shin", -2, (0.11, 0.50, 0.0), (0.12, 0.09, -0.01), 0.055, 0.04),
        Bone("left_foot", -2, (0.12, 0.09, -0.01), (0.13, 0.04, 0.15), 0.04, 0.03),
    ]
    for bone in left:  # a parent of -2 means "the bone before me"
        parent = len(bones) - 1 if bone.parent == -2 else bone.parent
        bones.append(Bone(bone.name, parent, bone.head, bone.tail, bone.radius_head, bone.radius_tail))
    for bone in left:
        right = _mirror(bone, 0)
        parent = len(bones) - 1 if bone.parent == -2 else bone.parent
        bones.append(Bone(right.name, parent, right.head, right.tail, right.radius_head, right.radius_tail))
    return tuple(bones)


SKELETON = _skeleton()
#: Smooth-minimum blending width of the flesh primitives.
BLEND = 0.035


def _segment_distance(points: np.ndarray, head: np.ndarray, tail: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (N,) of points (N, 3) to a segment and the segment parameter t (N,) in [0, 1]."""
    axis = tail - head
    t = np.clip((points - head) @ axis / (axis @ axis), 0.0, 1.0)
    # One coordinate at a time: the same arithmetic as the norm of the (N, 3) offsets
    # (squares summed x, y, then z), without its slow reduction over rows of three.
    squares = [np.square(points[:, k] - (head[k] + t * axis[k])) for k in range(3)]
    return np.sqrt(squares[0] + squares[1] + squares[2]), t


def _body_sdf(points: np.ndarray) -> np.ndarray:
    """Signed distance-like field (N,) of the rest body: negative inside."""
    field = None
    for bone in SKELETON:
        dist, t = _segment_distance(points, np.array(bone.head), np.array(bone.tail))
        sdf = dist - (bone.radius_head + t * (bone.radius_tail - bone.radius_head))
        if field is None:
            field = sdf
        else:  # polynomial smooth minimum
            h = np.clip(0.5 + 0.5 * (sdf - field) / BLEND, 0.0, 1.0)
            field = sdf * (1 - h) + field * h - BLEND * h * (1 - h)
    return field


@functools.lru_cache(maxsize=4)
def template(spacing: float = 0.022) -> tuple[Mesh, np.ndarray]:
    """The rest-pose template mesh and its left-right mirror map.

    Parameters
    ----------
    spacing : float
        Marching-cubes grid spacing in body units (the body is about 1.8 tall); 0.022
        gives about 5,000 vertices.

    Returns
    -------
    mesh : Mesh
        The template, one closed component.
    mirror : numpy.ndarray, shape (V,), int64
        ``mirror[i]`` is the vertex at the mirror image (x -> -x) of vertex ``i``.
    """
    from skimage.measure import marching_cubes

    half_x = spacing * np.ceil(0.72 / spacing)
    xs = np.linspace(-half_x, half_x, 2 * int(round(half_x / spacing)) + 1)  # symmetric about x = 0
    ys = np.arange(-0.02, 1.86, spacing)
    zs = np.arange(-0.2, 0.25, spacing)
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    # The smooth minimum is not associative, so blending left before right bones is not
    # exactly symmetric: average the field with its mirror image to make it so.
    volume = 0.5 * (_body_sdf(grid) + _body_sdf(grid * np.array([-1.0, 1.0, 1.0])))
    volume = volume.reshape(len(xs), len(ys), len(zs))
    verts, faces, _, _ = marching_cubes(volume, level=0.0, spacing=(spacing,) * 3, allow_degenerate=False)
    verts = verts + np.array([xs[0], ys[0], zs[0]])
    faces = faces[:, ::-1]  # outward normals for a negative-inside field
    verts, faces = _weld(verts, faces)
    mirrored = verts * np.array([-1.0, 1.0, 1.0])
    distance, mirror = cKDTree(verts).query(mirrored)
    if distance.max() > 1e-4 * spacing or np.any(mirror[mirror] != np.arange(len(verts))):
        raise RuntimeError(f"template is not mirror symmetric (largest mirror gap {distance.max():.2e})")
    verts = 0.5 * (verts + mirrored[mirror])  # remove marching cubes' float32 rounding: exact symmetry
    return Mesh(verts, faces, name="synthetic_template"), mirror.astype(np.int64)


def _weld(verts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge coincident marching-cubes vertices and drop faces that become degenerate."""
    keys = np.round(verts / 1e-9).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # keep vertices in order of first appearance
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    verts = verts[np.sort(first)]
    faces = rank[inverse.ravel()[faces]]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    return verts, faces[keep]


@functools.lru_cache(maxsize=4)
def skinning_weights(spacing: float = 0.022) -> np.ndarray:
    """Linear-blend-skinning weights of the template, shape (V, n_bones), rows summing to 1.

    Each vertex is weighted by the inverse fourth power of its distance to the flesh
    surface of each bone, over its three nearest bones.
    """
    mesh, _ = template(spacing)
    distances = np.empty((mesh.n_vertices, len(SKELETON)))
    for b, bone in enumerate(SKELETON):
        dist, t = _segment_distance(mesh.verts, np.array(bone.head), np.array(bone.tail))
        distances[:, b] = np.maximum(dist - (bone.radius_head + t * (bone.radius_tail - bone.radius_head)), 0.0) + 0.01
    weights = distances**-4.0
    np.put_along_axis(weights, np.argsort(distances, axis=1)[:, 3:], 0.0, axis=1)  # nearest three bones only
    weights /= weights.sum(axis=1, keepdims=True)
    # Ties between a left and a right bone are broken by index order: average with the
    # mirror image so that the weights are exactly left-right symmetric.
    _, mirror = template(spacing)
    return 0.5 * (weights + weights[mirror][:, _bone_mirror()])


def _bone_mirror() -> np.ndarray:
    """For each bone, the index of its left-right twin (itself on the midline), shape (n_bones,)."""
    names = [bone.name for bone in SKELETON]
    swap = {"left_": "right_", "right_": "left_"}
    return np.array([names.index(next((n.replace(a, b) for a, b in swap.items() if n.startswith(a)), n)) for n in names])


@dataclass(frozen=True)
class Proportions:
    """Per-bone length and thickness scales of one individual, each shape (n_bones,)."""

    length: np.ndarray
    thickness: np.ndarray

    @staticmethod
    def random(rng: np.random.Generator, spread: float = 0.15) -> Proportions:
        """Left and right limbs share their scales, so individuals stay mirror symmetric."""
        length = np.ones(len(SKELETON))
        thickness = np.ones(len(SKELETON))
        for b, bone in enumerate(SKELETON):
            if bone.name.startswith("right_"):
                twin = _bone_mirror()[b]
                length[b], thickness[b] = length[twin], thickness[twin]
            else:
                length[b] = 1.0 + rng.uniform(-spread, spread)
                thickness[b] = 1.0 + rng.uniform(-1.3 * spread, 1.3 * spread)
        return Proportions(length, thickness)


#: Joint rotation ranges in degrees about the x (flexion), y (twist) and z (side) axes, left side.
JOINT_RANGES = {
    "pelvis": ((-10, 10), (-25, 25), (-8, 8)),
    "chest": ((-15, 30), (-30, 30), (-15, 15)),
    "neck": ((-25, 30), (-45, 45), (-20, 20)),
    "head": ((-15, 15), (-20, 20), (-10, 10)),
    "nose": ((0, 0), (0, 0), (0, 0)),
    "left_upper_arm": ((-70, 70), (-30, 30), (-40, 60)),
    "left_forearm": ((-100, 0), (-20, 20), (-10, 10)),
    "left_hand": ((-30, 30), (-20, 20), (-20, 20)),
    "left_thigh": ((-70, 25), (-20, 20), (-5, 30)),
    "left_shin": ((0, 100), (-10, 10), (-5, 5)),
    "left_foot": ((-20, 25), (-10, 10), (-5, 5)),
}


def random_pose(rng: np.random.Generator, amount: float = 1.0) -> np.ndarray:
    """Local joint rotations, shape (n_bones, 3, 3), drawn within `JOINT_RANGES` scaled by ``amount``."""
    rotations = np.empty((len(SKELETON), 3, 3))
    for b, bone in enumerate(SKELETON):
        mirrored = bone.name.startswith("right_")
        ranges = JOINT_RANGES[bone.name.replace("right_", "left_")]
        angles = np.array([rng.uniform(lo, hi) for lo, hi in ranges]) * amount
        if mirrored:  # mirror image of a left-side rotation: flip the twist and side angles
            angles[1:] *= -1
        rotations[b] = Rotation.from_euler("xyz", angles, degrees=True).as_matrix()
    return rotations


def bone_transforms(proportions: Proportions, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Affine maps of every bone, rest template -> individual in pose.

    Returns
    -------
    linear : numpy.ndarray, shape (n_bones, 3, 3)
    offset : numpy.ndarray, shape (n_bones, 3)
        Bone ``b`` maps a rest point ``p`` to ``linear[b] @ p + offset[b]``.
    """
    n = len(SKELETON)
    linear = np.empty((n, 3, 3))
    offset = np.empty((n, 3))
    world_rotation = np.empty((n, 3, 3))
    for b, bone in enumerate(SKELETON):  # parents come first
        head = np.array(bone.head)
        direction = np.array(bone.tail) - head
        direction /= np.linalg.norm(direction)
        scale = proportions.thickness[b] * np.eye(3) + (proportions.length[b] - proportions.thickness[b]) * np.outer(
            direction, direction
        )
        if bone.parent < 0:
            world_rotation[b] = pose[b]
            new_head = head
        else:
            world_rotation[b] = world_rotation[bone.parent] @ pose[b]
            new_head = linear[bone.parent] @ head + offset[bone.parent]
        linear[b] = world_rotation[b] @ scale
        offset[b] = new_head - linear[b] @ head
    return linear, offset


def posed_shape(proportions: Proportions, pose: np.ndarray, name: str, spacing: float = 0.022) -> Mesh:
    """The template deformed by linear blend skinning to an individual in a pose."""
    mesh, _ = template(spacing)
    weights = skinning_weights(spacing)
    linear, offset = bone_transforms(proportions, pose)
    per_bone = np.einsum("bij,vj->vbi", linear, mesh.verts) + offset[None]  # (V, n_bones, 3)
    verts = np.einsum("vb,vbi->vi", weights, per_bone)
    verts[:, 1] -= verts[:, 1].min()  # stand on the floor
    return Mesh(verts, mesh.faces, name=name)


@dataclass(frozen=True)
class SyntheticHumans:
    """A seeded family of ``n_individuals x n_poses`` humanoid shapes sharing one connectivity.

    Shape ``i`` is individual ``i // n_poses`` in pose ``i % n_poses`` (pose 0 of every
    individual is a near-rest pose). Correspondence between any two shapes is the identity
    on vertices; `mirror` gives the left-right mirrored correspondence.

    Parameters
    ----------
    n_individuals, n_poses : int
    seed : int
    spacing : float
        Template grid spacing (0.022: about 5,000 vertices).
    """

    n_individuals: int = 4
    n_poses: int = 5
    seed: int = 0
    spacing: float = 0.022

    def __len__(self) -> int:
        return self.n_individuals * self.n_poses

    @property
    def names(self) -> list[str]:
        """``synth_IIPP`` for individual II in pose PP."""
        return [f"synth_{i // self.n_poses:02d}{i % self.n_poses:02d}" for i in range(len(self))]

    @property
    def mirror(self) -> np.ndarray:
        """Left-right mirror map of the shared connectivity, shape (V,), int64."""
        return template(self.spacing)[1]

    def shape(self, index: int) -> Mesh:
        """Shape ``index`` (deterministic: it depends only on the seed and the index)."""
        if not 0 <= index < len(self):
            raise IndexError(f"shape index {index} out of range for {len(self)} shapes")
        individual, pose_index = divmod(index, self.n_poses)
        proportions = Proportions.random(np.random.default_rng([self.seed, individual, 0]))
        pose_rng = np.random.default_rng([self.seed, individual, pose_index + 1])
        pose = random_pose(pose_rng, amount=0.15 if pose_index == 0 else 1.0)
        return posed_shape(proportions, pose, self.names[index], self.spacing)
