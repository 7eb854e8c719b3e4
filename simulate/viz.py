"""Small, dependency-light mesh previews (PNG) with matplotlib: depth-sorted, Lambert-
shaded triangles, optional per-vertex scalar colouring (e.g. error in mm). Good for
a quick look at a body, a garment on a body, or predicted vs simulated drapes; not a
renderer for figures."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class MeshLayer:
    """One mesh to draw: vertices [m] (V,3), faces (F,3), a base RGB colour or
    per-vertex scalars (V,) mapped through ``cmap`` between ``vmin`` and ``vmax``."""

    vertices: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float] = (0.75, 0.75, 0.78)
    scalars: np.ndarray | None = None
    cmap: str = "viridis"
    vmin: float | None = None
    vmax: float | None = None
    alpha: float = 1.0
    label: str | None = None
    extra: dict = field(default_factory=dict)


def _view_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    ry = np.array([[np.cos(az), 0, np.sin(az)], [0, 1, 0], [-np.sin(az), 0, np.cos(az)]])
    rx = np.array([[1, 0, 0], [0, np.cos(el), -np.sin(el)], [0, np.sin(el), np.cos(el)]])
    return rx @ ry


def _draw(ax, layers: list[MeshLayer], rot: np.ndarray) -> None:
    import matplotlib
    from matplotlib.collections import PolyCollection

    polys, colors, depths = [], [], []
    light = np.array([0.3, 0.5, 1.0])
    light /= np.linalg.norm(light)
    for layer in layers:
        v = np.asarray(layer.vertices, dtype=np.float64) @ rot.T
        tri = v[layer.faces]  # (F, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        shade = 0.35 + 0.65 * np.abs(n @ light)
        if layer.scalars is not None:
            s = np.asarray(layer.scalars, dtype=np.float64)[layer.faces].mean(1)
            lo = np.nanmin(s) if layer.vmin is None else layer.vmin
            hi = np.nanmax(s) if layer.vmax is None else layer.vmax
            base = matplotlib.colormaps[layer.cmap]((s - lo) / max(hi - lo, 1e-12))[:, :3]
        else:
            base = np.tile(np.asarray(layer.color, dtype=np.float64), (len(tri), 1))
        rgb = np.clip(base * shade[:, None], 0, 1)
        polys.append(tri[:, :, :2])
        colors.append(np.concatenate([rgb, np.full((len(tri), 1), layer.alpha)], axis=1))
        depths.append(tri[:, :, 2].mean(1))
    order = np.argsort(np.concatenate(depths))  # far (small z) first: painter's algorithm
    all_polys = np.concatenate(polys)[order]
    all_colors = np.concatenate(colors)[order]
    ax.add_collection(PolyCollection(all_polys, facecolors=all_colors, edgecolors="none", antialiased=False))
    pts = all_polys.reshape(-1, 2)
    pad = 0.05 * (pts.max(0) - pts.min(0)).max()
    ax.set_xlim(pts[:, 0].min() - pad, pts[:, 0].max() + pad)
    ax.set_ylim(pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    ax.set_aspect("equal")
    ax.axis("off")


def render_png(
    path: str | Path,
    layers: list[MeshLayer] | list[list[MeshLayer]],
    *,
    views: tuple[float, ...] = (0.0, 180.0),
    elevation: float = 10.0,
    titles: list[str] | None = None,
    colorbar_label: str | None = None,
    size_px: int = 900,
) -> Path:
    """Draws one or more panels (a list of layer lists) from each azimuth in ``views``.

    Args:
        path: output PNG path.
        layers: layers of one panel, or a list of panels (e.g. [predicted, simulated]).
        views: azimuths [deg] about the up (y) axis; 0 looks at the front (+z).
        titles: optional title per panel.
        colorbar_label: adds a colour bar for the first scalar layer found.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = layers if layers and isinstance(layers[0], list) else [layers]
    ncols = len(panels) * len(views)
    fig, axes = plt.subplots(1, ncols, figsize=(size_px / 100 * ncols / 2, size_px / 100), dpi=100, squeeze=False)
    for p, panel in enumerate(panels):
        for k, az in enumerate(views):
            ax = axes[0, p * len(views) + k]
            _draw(ax, panel, _view_rotation(az, elevation))
            if titles:
                ax.set_title(f"{titles[p]} ({'front' if az == 0 else 'back' if az == 180 else f'{az:g} deg'})", fontsize=9)
    if colorbar_label:
        scalar = next((l for panel in panels for l in panel if l.scalars is not None), None)
        if scalar is not None:
            import matplotlib.cm as cm
            from matplotlib.colors import Normalize

            lo = np.nanmin(scalar.scalars) if scalar.vmin is None else scalar.vmin
            hi = np.nanmax(scalar.scalars) if scalar.vmax is None else scalar.vmax
            fig.colorbar(cm.ScalarMappable(Normalize(lo, hi), cmap=scalar.cmap), ax=axes.ravel().tolist(),
                         shrink=0.6, label=colorbar_label)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
