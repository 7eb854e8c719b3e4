"""Picture of garments drawn from the GCVAE: one panel per garment, on the body (front view)."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from learn.tailornet.plots import mesh_axis, plt

GARMENT_COLOUR = (0.30, 0.45, 0.75, 1.0)
BODY_COLOUR = (0.8, 0.8, 0.8, 0.35)


def render_samples(body_vertices: np.ndarray, body_faces: np.ndarray, garments: list[tuple[np.ndarray, np.ndarray]],
                   path: str | os.PathLike, *, titles: list[str] | None = None, columns: int = 4) -> Path:
    """PNG of ``garments`` ([(vertices (V, 3) [m], faces (F, 3))]) each on the body mesh."""
    if not garments:
        raise ValueError("render_samples needs at least one garment")
    body_vertices = np.asarray(body_vertices, np.float64)
    view = body_vertices[:, [0, 2, 1]]
    limits = np.stack([view.min(0), view.max(0)])
    columns = min(columns, len(garments))
    rows = int(np.ceil(len(garments) / columns))
    figure = plt.figure(figsize=(2.2 * columns, 2.6 * rows), dpi=80)
    for k, (v, f) in enumerate(garments):
        axis = figure.add_subplot(rows, columns, k + 1, projection="3d")
        mesh_axis(axis, body_vertices, np.asarray(body_faces), BODY_COLOUR, limits)
        if len(f):
            mesh_axis(axis, np.asarray(v, np.float64), np.asarray(f), GARMENT_COLOUR, limits)
        if titles:
            axis.set_title(titles[k], fontsize=8)
    figure.subplots_adjust(left=0, right=1, bottom=0, top=0.95, wspace=0, hspace=0.05)
    path = Path(path)
    figure.savefig(path)
    plt.close(figure)
    return path
