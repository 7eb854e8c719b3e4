"""Point labels on a matplotlib plot that do not cover each other."""
from __future__ import annotations

from typing import Any, Sequence

#: Offsets [points] from a point to its label's anchor (left edge right of the point, right edge
#: left of it), tried in this order.
_SIDES = ((4.0, 3.0), (4.0, -11.0), (-4.0, 3.0), (-4.0, -11.0))


def place_labels(ax: Any, xy: Sequence[tuple[float, float]], labels: Sequence[str], *, fontsize: float = 7.0,
                 color: Any = "black", colors: Sequence[Any] | None = None) -> list[Any]:
    """Annotates each point ``xy[i]`` (data coordinates) with ``labels[i]`` where the label covers
    no text of the axes already there and no label placed before it: the four sides next to the
    point first, then steps of one line further up and down, as far as it takes (points that sit on
    top of each other get their labels stacked), inside the axes where a place there is free.
    ``colors`` (one per point, e.g. the markers' colours) colours each label like its point, so a
    label stacked a line or two away still reads as its point's. Call after the axes' limits,
    scales and the figure's layout are set. Returns the annotations."""
    renderer = ax.figure.canvas.get_renderer()
    frame = ax.get_window_extent(renderer)
    placed = [t.get_window_extent(renderer) for t in ax.texts]  # window extents of the labels so far
    step = fontsize * 1.4
    offsets = [(dx, dy + step * ((k + 1) // 2) * (1 if k % 2 else -1))
               for k in range(4 * len(labels) + 1) for dx, dy in _SIDES]
    out = []
    if colors is not None and len(colors) != len(labels):
        raise ValueError(f"colors must give one colour per label ({len(labels)}), got {len(colors)}")
    for k, ((x, y), text) in enumerate(zip(xy, labels)):
        annotation = ax.annotate(text, (x, y), xytext=offsets[0], textcoords="offset points", fontsize=fontsize,
                                 color=color if colors is None else colors[k], ha="left")

        def free(offset: tuple[float, float], inside: bool) -> bool:
            annotation.set_position(offset)
            annotation.set_ha("left" if offset[0] > 0 else "right")
            box = annotation.get_window_extent(renderer)
            if inside and not (frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1):
                return False
            return not any(box.overlaps(other) for other in placed)

        if not any(free(o, True) for o in offsets):
            any(free(o, False) for o in offsets)  # outside the axes then (the last offset if none is free)
        placed.append(annotation.get_window_extent(renderer))
        out.append(annotation)
    return out
