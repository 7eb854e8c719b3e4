"""Relaxing garments on static bodies: the canonical drapes every sequence starts from."""
from __future__ import annotations

import numpy as np
import torch

from simulate.body.base import BodyModel
from simulate.cloth import Features
from simulate.quasi_static import SimSettings
from simulate.sequence.settings import SequenceSettings


def drape_static(
    body: BodyModel,
    faces: np.ndarray,
    rest_vertices: np.ndarray,
    *,
    shapes: np.ndarray,
    poses: np.ndarray,
    body_faces: np.ndarray,
    body_face_groups: list[np.ndarray] | None = None,
    body_part: np.ndarray | None = None,
    settings: SequenceSettings,
    device: str,
    fabric: object = "cotton",
    start_vertices: np.ndarray | None = None,
    max_frames: int | None = None,
    material_uv: np.ndarray | None = None,
    attached: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Relaxes W garments on W static bodies (one world each) until they come to rest, with the
    sequence's settings (``simulate.garment.drape.drape_simulator`` sets the batch up).

    Args:
        rest_vertices: cloth rest geometry per world [m], (W, V, 3) (also the start unless given).
        shapes: (W, S) body shapes; poses: (W, 60) body poses.
        start_vertices: initial positions [m], (W, V, 3) (default: ``rest_vertices``).
        max_frames: frame budget (default ``settings.sim.max_frames``).
        fabric: fabric preset name or Fabric for every world, or a list of them, one per world.
        material_uv: pattern UVs per face corner, (F, 3, 2) (a template's ``face_uv``; see
            ``ClothBuilder.add_garment``); None: the builder's grain axis (+y).
        body_face_groups, body_part: primary collision bodies, as for ``run_sequences``.
        attached: vertex indices held by soft springs at their rest positions (a template's
            ``attachment``: the waistband of pants, shorts and skirts), as ``run_sequences``
            holds them to the moving body; None or empty: none.
    Returns:
        (positions (W, V, 3) [m], status (W,) WorldStatus values).
    """
    rest_vertices = np.asarray(rest_vertices, np.float32)
    w_count = len(rest_vertices)
    fabrics = list(fabric) if isinstance(fabric, (list, tuple)) else [fabric] * w_count
    if len(fabrics) != w_count:
        raise ValueError(f"fabric must be one fabric or one per world ({w_count}), got {len(fabrics)}")
    torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    with torch.no_grad():
        posed = body.on_device(torch_device).pose_torch(torch.as_tensor(np.asarray(shapes, np.float32), device=torch_device),
                                torch.as_tensor(np.asarray(poses, np.float32), device=torch_device))
    body_vertices = posed.vertices.cpu().numpy()
    from simulate.garment.drape import drape_simulator  # (the garment package is heavy to import)

    budget = settings.sim.max_frames if max_frames is None else int(max_frames)
    held = None if attached is None or len(attached) == 0 else np.asarray(attached, np.int64)
    sim = drape_simulator([{"vertices": rest_vertices[w], "faces": faces, "fabric": fabrics[w], "material_uv": material_uv,
                            "body_part": body_part, "attached": held} for w in range(w_count)], body_vertices, body_faces, device=device,
                          settings=SimSettings(**{**settings.sim.__dict__, "max_frames": budget}),
                          thickness=settings.contact_thickness, solver=settings.solver,
                          features=Features(self_contact=settings.self_contact, friction=settings.friction != 0.0),
                          start_vertices=start_vertices, body_face_groups=body_face_groups)
    status = sim.relax(budget)
    positions = sim.positions()
    return np.stack([positions[sim.model.world_slice(w)] for w in range(w_count)]), status
