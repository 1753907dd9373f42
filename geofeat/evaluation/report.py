"""Reports of benchmark runs: Markdown tables, PCK plots and correspondence pictures.

The plots need matplotlib (the ``bench`` extra: ``pip install 'geofeat[bench]'``), imported
on first use only, so that importing this module (or `markdown_table`) costs nothing. They
draw on `matplotlib.figure.Figure` objects and write PNG files without touching pyplot's
global state or backend.
"""

from __future__ import annotations

import os
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from geofeat.datasets.records import ShapePair
from geofeat.errors import MissingDependencyError
from geofeat.mesh import Mesh

__all__ = [
    "COLOR_CAPTION",
    "PairPicture",
    "markdown_table",
    "plot_matches",
    "plot_mesh_colors",
    "plot_pairs",
    "plot_pck",
    "position_colors",
    "transferred_colors",
]

#: Colour of vertices without a predicted counterpart.
NO_MATCH_COLOR = np.array([0.55, 0.55, 0.55])

#: What the colours of `plot_matches` (and `plot_pairs`) mean, for a caption.
COLOR_CAPTION = (
    "Colours: every vertex of the target X is coloured by its position (red grows towards the body's left, "
    "green upwards, blue to the front). Each vertex of the source Y takes the colour of the vertex of X it is "
    "matched to: through the ground truth (what a perfect map shows) and through each pipeline's predicted map. "
    "Where a prediction's colours differ from the ground truth's the map is wrong there; a limb coloured like "
    "its mirror twin is left-right (symmetry) confusion. Grey: no counterpart."
)


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


def plot_pck(
    curves: dict[str, tuple[np.ndarray, np.ndarray]],
    path: str | os.PathLike,
    title: str,
    *,
    styles: dict[str, dict[str, Any]] | None = None,
    xmax: float | None = None,
    legend_columns: int = 1,
    legend_below: bool = False,
    figsize: tuple[float, float] = (5, 4),
    dpi: int = 120,
) -> None:
    """Save PCK curves, one per label: fraction of matches within a geodesic error threshold.

    Parameters
    ----------
    curves : dict
        ``label -> (thresholds (T,), fractions (T,))``, in legend order.
    path : str or os.PathLike
        PNG to write.
    title : str
    styles : dict, optional
        ``label -> matplotlib line settings`` (``color``, ``linestyle``, ``linewidth``...).
    xmax : float, optional
        Right end of the x axis (default the largest threshold).
    legend_columns : int
        Columns of the legend (its entries fill column by column).
    legend_below : bool
        Put the legend under the plot instead of in its lower right corner.
    figsize : (float, float)
        Inches.
    dpi : int
    """
    styles = styles or {}
    fig = _figure(figsize=figsize)
    ax = fig.subplots()
    for label, (thresholds, fractions) in curves.items():
        ax.plot(thresholds, fractions, label=label, **styles.get(label, {}))
    ax.set_xlabel("geodesic error threshold (fraction of sqrt(area) of the target)")
    ax.set_ylabel("fraction of correspondences within the threshold")
    ax.set_ylim(0, 1)
    ax.set_xlim(0, xmax if xmax is not None else max(t.max() for t, _ in curves.values()))
    ax.grid(alpha=0.3)
    if legend_below:
        ax.legend(fontsize=7, ncol=legend_columns, loc="upper center", bbox_to_anchor=(0.5, -0.13), frameon=False)
    else:
        ax.legend(fontsize=7, ncol=legend_columns, loc="lower right")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(Path(path), dpi=dpi)


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


def _draw(ax, mesh: Mesh, colors: np.ndarray, title: str, tight: bool = False) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    verts = mesh.verts[:, [0, 2, 1]]  # show y up
    if mesh.faces is None:  # a point cloud: dots, as large as the figure allows them to be told apart
        ax.scatter(verts[:, 0], verts[:, 1], verts[:, 2], c=np.clip(colors, 0, 1), s=1.5, linewidths=0, depthshade=False)
    else:
        face_colors = colors[mesh.faces].mean(axis=1)
        normals = np.cross(verts[mesh.faces[:, 1]] - verts[mesh.faces[:, 0]], verts[mesh.faces[:, 2]] - verts[mesh.faces[:, 0]])
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        shade = 0.55 + 0.45 * np.abs(normals @ np.array([0.0, -1.0, 0.3]) / np.linalg.norm([0.0, -1.0, 0.3]))
        collection = Poly3DCollection(verts[mesh.faces], facecolors=np.clip(face_colors * shade[:, None], 0, 1), linewidths=0)
        ax.add_collection3d(collection)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    if tight:  # a box around the mesh (same scale on every axis), filling the panel
        extent = np.maximum(hi - lo, 1e-3 * (hi - lo).max())
        ax.set_xlim(lo[0], lo[0] + extent[0])
        ax.set_ylim(lo[1], lo[1] + extent[1])
        ax.set_zlim(lo[2], lo[2] + extent[2])
        ax.set_box_aspect(tuple(extent), zoom=1.0)
    else:
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


@dataclass
class PairPicture:
    """One row of `plot_matches`: a pair, the maps to show and the panel titles.

    Attributes
    ----------
    pair : ShapePair
        X (the target) is drawn in position colours, Y through the ground truth ``pair.map_yx``
        and through each prediction.
    predictions : list of (str, numpy.ndarray, float or None)
        ``(label, map_yx (V_y,), geodesic error x100 of the pair or None)``.
    x_title, y_title : str, optional
        Titles of the X and Y panels (default: name, full or partial, vertex count).
    row_title : str, optional
        Written beside the row (e.g. the kind of pair).
    """

    pair: ShapePair
    predictions: list[tuple[str, np.ndarray, float | None]] = field(default_factory=list)
    x_title: str | None = None
    y_title: str | None = None
    row_title: str | None = None


def _shape_title(role: str, mesh: Mesh, partial: bool) -> str:
    kind = f"{'partial' if partial else 'full'} shape, {mesh.n_vertices:,} vertices"
    if mesh.faces is None:
        kind = f"{'partial' if partial else 'full'} point cloud, {mesh.n_vertices:,} points"
    return f"{role}: {mesh.name}\n{kind}"


def plot_matches(rows: list[PairPicture], path: str | os.PathLike, caption: str | None = COLOR_CAPTION, dpi: int = 75) -> None:
    """Pictures of matched pairs, one row per pair: X, Y through the ground truth, Y through each prediction.

    Parameters
    ----------
    rows : list of PairPicture
    path : str or os.PathLike
        PNG to write.
    caption : str, optional
        Text under the pictures (default `COLOR_CAPTION`, what the colours mean); None for none.
    dpi : int
    """
    columns = 2 + max(len(row.predictions) for row in rows)
    width = 2.3 * columns
    caption_lines = textwrap.wrap(caption, width=int(width * 15)) if caption else []
    caption_height = 0.2 + 0.17 * len(caption_lines)
    row_height = 3.0
    height = row_height * len(rows) + caption_height
    fig = _figure(figsize=(width, height))
    for r, row in enumerate(rows):
        pair = row.pair
        colors_x = position_colors(pair.x)
        x_partial = pair.protocol == "p2p"
        y_partial = pair.protocol in ("p2f", "p2p")
        panels = [
            (pair.x, colors_x, row.x_title or _shape_title("target X", pair.x, x_partial)),
            (
                pair.y,
                transferred_colors(colors_x, pair.map_yx),
                (row.y_title or _shape_title("source Y", pair.y, y_partial)) + "\nthrough the ground truth",
            ),
        ]
        for label, predicted, error in row.predictions:
            score = "" if error is None else f"\ngeodesic error {error:.1f}"
            panels.append((pair.y, transferred_colors(colors_x, predicted), f"Y through {label}{score}"))
        for c, (mesh, colors, title) in enumerate(panels):
            ax = fig.add_subplot(len(rows), columns, r * columns + c + 1, projection="3d")
            _draw(ax, mesh, colors, title, tight=True)
        if row.row_title:
            top = 1 - (r * row_height) / height
            fig.text(0.005, top - 0.5 * row_height / height, row.row_title, rotation=90, va="center", ha="left", fontsize=9)
    fig.subplots_adjust(left=0.02, right=1, bottom=caption_height / height, top=1 - 0.55 / height, wspace=0, hspace=0.3)
    if caption_lines:
        fig.text(0.01, 0.1 * caption_height / height, "\n".join(caption_lines), va="bottom", ha="left", fontsize=7.5)
    fig.savefig(Path(path), dpi=dpi)


def plot_pairs(pairs: list[tuple], path: str | os.PathLike) -> None:
    """Pictures of pairs: X in position colours, Y through the ground truth and through the predicted map.

    Parameters
    ----------
    pairs : list of (ShapePair, predicted map_yx (V_y,), label) or (..., label, geodesic error x100)
    path : str or os.PathLike
        PNG to write, captioned with what the colours mean (see `plot_matches`).
    """
    rows = [PairPicture(pair, [(label, predicted, rest[0] if rest else None)]) for pair, predicted, label, *rest in pairs]
    plot_matches(rows, path)


def plot_mesh_colors(mesh: Mesh, colors: np.ndarray, path: str | os.PathLike, title: str) -> None:
    """A mesh with per-vertex colours (V, 3) seen from the front and from the back, saved as a PNG."""
    fig = _figure(figsize=(6, 3.6))
    for col, (azimuth, side) in enumerate(((-90, "front"), (90, "back"))):
        ax = fig.add_subplot(1, 2, col + 1, projection="3d")
        _draw(ax, mesh, colors, f"{title}, {side}" if col == 0 else side)
        ax.view_init(elev=10, azim=azimuth)
    _fill(fig)
    fig.savefig(Path(path), dpi=110)
