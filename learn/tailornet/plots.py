"""Figures for ``drape evaluate``: error against run time, and predicted-vs-simulated renders.

matplotlib only (Agg backend, no display needed); every function writes one PNG and
returns its path.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from simulate.reports.labels import place_labels  # noqa: E402


def error_vs_runtime_figure(points: Sequence[dict[str, Any]], *, title: str = "Error vs run time") -> Any:
    """The figure of :func:`plot_error_vs_runtime` (open; the caller closes it)."""
    if not points:
        raise ValueError("plot_error_vs_runtime needs at least one point, got none")
    for i, point in enumerate(points):
        for key in ("label", "ms_per_frame", "error_mm"):
            if key not in point:
                raise ValueError(f"points[{i}] lacks '{key}'; got keys {sorted(point)}")
        if not point["ms_per_frame"] > 0:
            raise ValueError(f"points[{i}].ms_per_frame must be > 0 for a log axis, got {point['ms_per_frame']}")
    figure, axis = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    colors = []
    for point in points:
        marker = axis.scatter(point["ms_per_frame"], point["error_mm"], s=30)
        colors.append(marker.get_facecolor()[0])
    axis.set_xscale("log")
    axis.margins(x=0.15, y=0.3)  # room for the labels of the outermost points
    axis.set_xlabel("time per frame [ms] (log)")
    axis.set_ylabel("mean per-vertex error [mm]")
    axis.set_title(title)
    axis.grid(True, which="both", alpha=0.3)
    figure.tight_layout()
    # after the layout: the labels are placed where they cover no other label, in window coordinates
    place_labels(axis, [(p["ms_per_frame"], p["error_mm"]) for p in points], [str(p["label"]) for p in points],
                 fontsize=7, colors=colors)
    return figure


def plot_error_vs_runtime(
    points: Sequence[dict[str, Any]], path: str | os.PathLike[str], *, title: str = "Error vs run time"
) -> Path:
    """Scatter of mean per-vertex error [mm] against time per frame [ms] (log scale), each point
    labelled where its label covers no other (points of equal error and time get stacked labels).

    points: dicts with ``label`` (str), ``ms_per_frame`` (> 0) and ``error_mm`` (>= 0),
    e.g. one per (learner, split, device, batch size) and one for the simulator.
    """
    figure = error_vs_runtime_figure(points, title=title)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path


LIGHT_DIRECTION = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])


def mesh_axis(axis: Any, vertices: np.ndarray, faces: np.ndarray, colors: Any, limits: np.ndarray) -> None:
    """Draws a mesh (vertices [m], faces (F, 3)) shaded with ``colors`` into a 3D axis fitted to ``limits`` (2, 3)."""
    # Body frame is y up: show (x, z, y) so the figure stands upright.
    view = vertices[:, [0, 2, 1]]
    triangles = view[faces]  # (F, 3, 3)
    normals = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    # Two-sided Lambert shading so folds read as geometry, not as flat colour.
    shade = 0.35 + 0.65 * np.abs(normals @ LIGHT_DIRECTION)
    rgba = np.broadcast_to(np.asarray(colors, dtype=np.float64), (faces.shape[0], 4)).copy()
    rgba[:, :3] *= shade[:, None]
    axis.add_collection3d(Poly3DCollection(triangles, facecolors=rgba, edgecolors="none", linewidths=0))
    centre, half = limits.mean(axis=0), (limits[1] - limits[0]).max() / 2
    axis.set_xlim(centre[0] - half, centre[0] + half)
    axis.set_ylim(centre[1] - half, centre[1] + half)
    axis.set_zlim(centre[2] - half, centre[2] + half)
    axis.set_box_aspect((1, 1, 1))
    axis.view_init(elev=10, azim=-90)
    axis.set_axis_off()


def render_prediction(
    predicted: np.ndarray,
    simulated: np.ndarray,
    faces: np.ndarray,
    path: str | os.PathLike[str],
    *,
    body_vertices: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    title: str = "",
    max_error_mm: float | None = None,
) -> Path:
    """Side-by-side render: predicted garment coloured by per-vertex error, and simulated.

    predicted, simulated: garment vertices [m], shape (V, 3); faces (F, 3); optional
    body mesh [m] drawn in grey behind both. The colour scale runs from 0 to
    ``max_error_mm`` (default: the 99th percentile of this frame's errors).
    """
    predicted = np.asarray(predicted, dtype=np.float64)
    simulated = np.asarray(simulated, dtype=np.float64)
    faces = np.asarray(faces)
    if predicted.shape != simulated.shape or predicted.ndim != 2 or predicted.shape[1] != 3:
        raise ValueError(
            f"predicted and simulated must both have shape (V, 3), got {predicted.shape} and {simulated.shape}"
        )
    error_mm = np.linalg.norm(predicted - simulated, axis=1) * 1000.0
    scale = float(max_error_mm if max_error_mm is not None else max(np.percentile(error_mm, 99), 1e-6))
    face_error = error_mm[faces].mean(axis=1)
    colormap = plt.get_cmap("viridis")
    stacked = [predicted, simulated] + ([np.asarray(body_vertices)] if body_vertices is not None else [])
    everything = np.concatenate(stacked)[:, [0, 2, 1]]
    limits = np.stack([everything.min(axis=0), everything.max(axis=0)])
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure = plt.figure(figsize=(8.0, 4.4), dpi=120)
    panels = (
        (predicted, colormap(np.clip(face_error / scale, 0.0, 1.0)), f"predicted (mean error {error_mm.mean():.1f} mm)"),
        (simulated, (0.75, 0.55, 0.45, 1.0), "simulated"),
    )
    for column, (vertices, colors, label) in enumerate(panels):
        axis = figure.add_subplot(1, 2, column + 1, projection="3d")
        if body_vertices is not None and body_faces is not None:
            mesh_axis(axis, np.asarray(body_vertices), np.asarray(body_faces), (0.8, 0.8, 0.8, 0.35), limits)
        mesh_axis(axis, vertices, faces, colors, limits)
        axis.set_title(label, fontsize=9)
    mappable = plt.cm.ScalarMappable(cmap=colormap, norm=plt.Normalize(0.0, scale))
    figure.colorbar(mappable, ax=figure.axes, shrink=0.6, label="per-vertex error [mm]")
    if title:
        figure.suptitle(title, fontsize=10)
    figure.savefig(path)
    plt.close(figure)
    return path
