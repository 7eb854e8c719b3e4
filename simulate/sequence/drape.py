"""Relaxing garments on static bodies: the canonical drapes every sequence starts from."""
from __future__ import annotations

import numpy as np
import torch

from simulate.body.base import BodyModel
from simulate.cloth import ClothBuilder, Features
from simulate.contact import BodyCollider
from simulate.quasi_static import QuasiStaticSimulator, SimSettings
from simulate.sequence.settings import SequenceSettings


def drape_static(
    body: BodyModel,
    faces: np.ndarray,
    rest_vertices: np.ndarray,
    *,
    shapes: np.ndarray,
    poses: np.ndarray,
    body_faces: np.ndarray,
    settings: SequenceSettings,
    device: str,
    fabric: object = "cotton",
    start_vertices: np.ndarray | None = None,
    max_frames: int | None = None,
    material_uv: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Relaxes W garments on W static bodies (one world each) until they come to rest.

    Args:
        rest_vertices: cloth rest geometry per world [m], (W, V, 3) (also the start unless given).
        shapes: (W, S) body shapes; poses: (W, 60) body poses.
        start_vertices: initial positions [m], (W, V, 3) (default: ``rest_vertices``).
        max_frames: frame budget (default ``settings.sim.max_frames``).
        material_uv: pattern UVs per face corner, (F, 3, 2) (a template's ``face_uv``; see
            ``ClothBuilder.add_garment``); None: the builder's grain axis (+y).
    Returns:
        (positions (W, V, 3) [m], status (W,) WorldStatus values).
    """
    rest_vertices = np.asarray(rest_vertices, np.float32)
    w_count = len(rest_vertices)
    torch_device = "cuda" if str(device).startswith("cuda") and torch.cuda.is_available() else "cpu"
    with torch.no_grad():
        posed = body.on_device(torch_device).pose_torch(torch.as_tensor(np.asarray(shapes, np.float32), device=torch_device),
                                torch.as_tensor(np.asarray(poses, np.float32), device=torch_device))
    body_vertices = posed.vertices.cpu().numpy()
    builder = ClothBuilder()
    for w in range(w_count):
        builder.add_garment(rest_vertices[w], faces, fabric=fabric, material_uv=material_uv)
    model = builder.finalize(device, features=Features(self_contact=settings.self_contact, friction=settings.friction != 0.0))
    collider = BodyCollider(body_vertices, body_faces, device=device, thickness=settings.contact_thickness)
    budget = settings.sim.max_frames if max_frames is None else int(max_frames)
    sim = QuasiStaticSimulator(model, collider, solver=settings.solver,
                               settings=SimSettings(**{**settings.sim.__dict__, "max_frames": budget}))
    if start_vertices is not None:
        for w in range(w_count):
            sim.set_positions(np.asarray(start_vertices[w], np.float32), world=w)
    status = sim.relax(budget)
    positions = sim.positions()
    return np.stack([positions[model.world_slice(w)] for w in range(w_count)]), status
