"""Reports of benchmark runs: Markdown tables, PCK plots and correspondence pictures.

The plots need matplotlib (the ``bench`` extra: ``pip install 'geofeat[bench]'``), imported
on first use only, so that importing this module (or `markdown_table`) costs nothing. They
draw on `matplotlib.figure.Figure` objects and write PNG files without touching pyplot's
global state or backend.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.errors import MissingDependencyError
from geofeat.mesh import Mesh

__all__ = [
    "markdown_table",
    "plot_mesh_colors",
    "plot_pairs",
    "plot_pck",
    "position_colors",
    "transferred_colors",
]

#: Colour of vertices without a predicted counterpart.
NO_MATCH_COLOR = np.array([0.55, 0.55, 0.55])


def markdown_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """A Markdown table.

    Parameters
    ----------
    rows : list of dict
    columns : list of (key, header, format)
        ``format`` is a format spec such as ``".2f"``; missing values print as a dash.

    Returns
    -------
    str
        Header, separator and one line per row, joined by newlines.
    """
    lines = ["| " + " | ".join(header for _, header, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = []
        for key, _, fmt in columns:
            value = row.get(key)
            cells.append("-" if value is None else format(value, fmt))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _figure(**settings: Any):
    """A new matplotlib ``Figure`` (no pyplot); `MissingDependencyError` naming the extra without matplotlib."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:
        raise MissingDependencyError(
            "plots need matplotlib, which is not installed; install the bench extra: pip install 'geofeat[bench]'"
        ) from exc
    return Figure(**settings)


def plot_pck(curves: dict[str, tuple[np.ndarray, np.ndarray]], path: str | os.PathLike, title: str) -> None:
    """Save PCK curves, one per label: fraction of matches within a geodesic error threshold.

    Parameters
    ----------
    curves : dict
        ``label -> (thresholds (T,), fractions (T,))``.
    path : str or os.PathLike
        PNG to write.
    title : str
    """
    fig = _figure(figsize=(5, 4))
    ax = fig.subplots()
    for label, (thresholds, fractions) in curves.items():
        ax.plot(thresholds, fractions, label=label)
    ax.set_xlabel("geodesic error threshold (fraction of sqrt(area))")
    ax.set_ylabel("fraction of correspondences")
    ax.set_ylim(0, 1)
    ax.set_xlim(0, max(t.max() for t, _ in curves.values()))
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(Path(path), dpi=120)


def position_colors(mesh: Mesh) -> np.ndarray:
    """Per-vertex RGB from the bounding-box position, shape (V, 3) in [0, 1]."""
    lo, hi = mesh.verts.min(axis=0), mesh.verts.max(axis=0)
    return (mesh.verts - lo) / np.where(hi > lo, hi - lo, 1.0)


def transferred_colors(colors_x: np.ndarray, map_yx: np.ndarray) -> np.ndarray:
    """Colours of X (V_x, 3) pulled back to Y through a map (gray where ``map_yx == -1``), shape (V_y, 3)."""
    out = np.tile(NO_MATCH_COLOR, (map_yx.size, 1))
    valid = map_yx >= 0
    out[valid] = colors_x[map_yx[valid]]
    return out


def _draw(ax, mesh: Mesh, colors: np.ndarray, title: str) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    verts = mesh.verts[:, [0, 2, 1]]  # show y up
    face_colors = colors[mesh.faces].mean(axis=1)
    normals = np.cross(verts[mesh.faces[:, 1]] - verts[mesh.faces[:, 0]], verts[mesh.faces[:, 2]] - verts[mesh.faces[:, 0]])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    shade = 0.55 + 0.45 * np.abs(normals @ np.array([0.0, -1.0, 0.3]) / np.linalg.norm([0.0, -1.0, 0.3]))
    collection = Poly3DCollection(verts[mesh.faces], facecolors=np.clip(face_colors * shade[:, None], 0, 1), linewidths=0)
    ax.add_collection3d(collection)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    center, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(center[0] - half, center[0] + half)
    ax.set_ylim(center[1] - half, center[1] + half)
    ax.set_zlim(center[2] - half, center[2] + half)
    ax.view_init(elev=10, azim=-90)
    ax.set_axis_off()
    ax.set_title(title, fontsize=8)


def _fill(fig) -> None:
    """Let the 3D panels fill the figure (``tight_layout`` would draw every mesh once more to measure them)."""
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.96, wspace=0, hspace=0.08)


def plot_pairs(pairs: list[tuple], path: str | os.PathLike) -> None:
    """Pictures of pairs: X in position colours, Y coloured through the predicted map, and through the truth.

    Parameters
    ----------
    pairs : list of (ShapePair, predicted map_yx (V_y,), label)
    path : str or os.PathLike
        PNG to write.
    """
    fig = _figure(figsize=(9, 3.2 * len(pairs)))
    for row, (pair, predicted, label) in enumerate(pairs):
        colors_x = position_colors(pair.x)
        panels = [
            (pair.x, colors_x, f"X: {pair.x.name}"),
            (pair.y, transferred_colors(colors_x, predicted), f"Y via prediction ({label})"),
            (pair.y, transferred_colors(colors_x, pair.map_yx), "Y via ground truth"),
        ]
        for col, (mesh, colors, title) in enumerate(panels):
            ax = fig.add_subplot(len(pairs), 3, 3 * row + col + 1, projection="3d")
            _draw(ax, mesh, colors, title)
    _fill(fig)
    fig.savefig(Path(path), dpi=110)


def plot_mesh_colors(mesh: Mesh, colors: np.ndarray, path: str | os.PathLike, title: str) -> None:
    """A mesh with per-vertex colours (V, 3) seen from the front and from the back, saved as a PNG."""
    fig = _figure(figsize=(6, 3.6))
    for col, (azimuth, side) in enumerate(((-90, "front"), (90, "back"))):
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        _draw(ax, mesh, colors, f"{title}, {side}" if col == 0 else side)
        ax.view_init(elev=10, azim=azimuth)
    _fill(fig)
    fig.savefig(Path(path), dpi=110)
