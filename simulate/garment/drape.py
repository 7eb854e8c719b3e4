"""Quasi-static draping of generated garments on canonical bodies (TailorNet's A-pose
rest garments, CLOTH3D's "resized garment" step): every garment is one world of one
batched cloth model, each on the canonical-pose body of its own shape.

A garment starts at its generated rest geometry (already outside the body by its
looseness), relaxes under gravity against the body (with friction), and bottoms hang
from their waistband by soft attachment springs to their start positions.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from simulate.garment.templates import GarmentTemplate

#: Body parts in a garment's collider, per garment type: the parts it can touch plus those
#: beyond its openings (legs below a top's hem, head above its collar, hands past long sleeves),
#: so a garment's openings never meet an open cut of the culled body (a point nearest a cut
#: counts as outside, ``simulate.contact.closest``, and gets no push from it).
#: Used by the canonical drape, the dataset pipeline and the reports.
COLLISION_PARTS: dict[str, tuple[str, ...]] = {
    "tshirt": ("torso", "arms", "legs", "head"),
    "shirt": ("torso", "arms", "legs", "head", "hands"),  # long sleeves reach the wrist cut
    "pants": ("torso", "legs", "feet"),
    "shorts": ("torso", "legs"),
    "skirt": ("torso", "legs"),
    "top": ("torso", "arms", "legs", "head"),
    "dress": ("torso", "arms", "legs", "head"),
    "jumpsuit": ("torso", "arms", "legs", "head", "feet"),  # long legs reach the ankle cut
}
#: A garment vertex deeper than this inside the body counts as penetrating [m]
#: (HOOD-style evaluations use 1 mm).
PENETRATION_TOLERANCE_M = 1.0e-3


@dataclass
class DrapeResult:
    """Outcome of :func:`drape_canonical`, one entry per world (garment).

    Attributes:
        vertices: draped rest garments [m], list of (V_w, 3) float32 arrays.
        status: per-world simulator status names ("CONVERGED", "MAX_STEPS", "EXPLODED").
        frames: frames each world ran, (W,).
        max_penetration_m: deepest garment vertex inside the body [m] (0 if none), (W,).
        penetrating_fraction: fraction of vertices deeper than PENETRATION_TOLERANCE_M, (W,).
        start_penetrating_fraction: the same for the undraped start geometry, (W,).
        seconds: wall time of the relaxation [s].
        settings: the simulator settings used (as a dict).
    """

    vertices: list[np.ndarray]
    status: list[str]
    frames: np.ndarray
    max_penetration_m: np.ndarray
    penetrating_fraction: np.ndarray
    start_penetrating_fraction: np.ndarray
    seconds: float
    settings: dict = field(default_factory=dict)

    @property
    def ok(self) -> np.ndarray:
        """Worlds that converged without penetration beyond tolerance, (W,) bool."""
        return np.array([s == "CONVERGED" for s in self.status]) & (self.penetrating_fraction == 0)


def _penetration(collider, points: np.ndarray, world: np.ndarray) -> np.ndarray:
    """Signed distance [m] of points to their world's body (negative inside)."""
    return collider.signed_distance(points.astype(np.float32), world.astype(np.int32), max_dist=0.2)


def drape_simulator(garments: list[dict], body_vertices: np.ndarray, body_faces: np.ndarray, *, device: str,
                    settings, thickness: float, solver: str = "xpbd", features=None,
                    start_vertices: np.ndarray | None = None, body_face_groups: list[np.ndarray] | None = None):
    """The drape of W garments on W static bodies (one world each), ready to relax: the one set-up
    behind ``drape_canonical`` (templates on canonical bodies) and ``simulate.sequence.drape_static``
    (the dataset's start drapes). ``sim.relax()`` then steps every world until it comes to rest
    (or ``settings.max_frames``).

    Args:
        garments: per world, the ``ClothBuilder.add_garment`` arguments (vertices [m] (V, 3), faces,
            fabric, attached, skinning_weights, material_uv, ...).
        body_vertices: the static bodies [m], (W, Vb, 3); body_faces: the faces they collide with.
        device: Warp device; settings: ``SimSettings``; thickness: contact distance to the body [m].
        solver: the solver's name; features: the model's ``Features`` (None: the builder's default).
        start_vertices: initial positions [m] per world, (W, V, 3) (default: the garments' vertices).
        body_face_groups: primary collision bodies (``BodyCollider``'s ``face_groups``; the
            garments' ``body_part`` picks one per vertex), or None.
    Returns:
        the ``QuasiStaticSimulator`` (its ``model`` and ``collider`` hold the batch).
    """
    from simulate.cloth import ClothBuilder
    from simulate.contact.body_collider import BodyCollider
    from simulate.quasi_static import QuasiStaticSimulator

    builder = ClothBuilder()
    for garment in garments:
        builder.add_garment(**garment)
    model = builder.finalize(device, features=features)
    collider = BodyCollider(body_vertices, body_faces, device=device, thickness=thickness, face_groups=body_face_groups)
    sim = QuasiStaticSimulator(model, collider, solver=solver, settings=settings)
    if start_vertices is not None:
        for w in range(len(garments)):
            sim.set_positions(np.asarray(start_vertices[w], np.float32), world=w)
    return sim


def drape_canonical(
    garments: list[tuple[GarmentTemplate, np.ndarray]],
    body,
    shapes,
    *,
    fabric: str = "cotton",
    device: str = "cpu",
    max_frames: int = 240,
    tolerance: float = 0.02,
    substeps: int = 10,
    iterations: int = 10,
    body_thickness: float = 2.0e-3,
    damping: float = 2.0,
    explosion_stretch: float = 10.0,
) -> DrapeResult:
    """Drapes garments on the canonical-pose bodies of their shapes, all in one batch.

    The garment assets of ``drape garment``, style spaces and the report scenes. Its settings
    differ from the dataset's (``SimSettings`` defaults) for this use: every garment type is
    draped straight from its generated geometry on bodies of any shape, not only the t-shirt the
    dataset settings are tuned on, so a light damping (2/s) lets the garment slide into place, a
    10x stretch limit passes first-contact transients at shoulders and waistbands without letting
    a blow-up through, the garment sits closer to the skin (2 mm), frames are 1/60 s with the body
    queried on every substep, and a world is at rest when its fastest particle is slower than
    ``tolerance`` for 5 frames (no outliers, no limit cycles); with these all five
    types converge on three shapes without penetration (tests/test_garment_drape.py).

    Args:
        garments: (template, vertices (V, 3) [m]) per world; the vertices are a generated
            style on the canonical body of that world's shape (``generate_garment(...,
            shape=shapes[w])``).
        body: the BodyModel.
        shapes: one shape per world, (W, S), or one (S,) shared by all.
        fabric: fabric preset name (see ``simulate.cloth.FABRICS``).
        device: Warp device ("cpu", "cuda:0").
        max_frames: frames (1/60 s) before a still-moving world is given up (MAX_STEPS).
        tolerance: converged when the fastest particle is slower than this [m/s].
        substeps, iterations: XPBD substeps per frame and iterations per substep.
        body_thickness: contact distance kept from the body surface [m].
        damping: extra velocity damping [1/s] (quasi-static: settles faster).
        explosion_stretch: triangle stretch ratio [-] that marks a world EXPLODED; higher
            than the simulator's default because the few triangles at a garment's
            first contact (shoulders, waistband) stretch transiently while settling.
    """
    from simulate.quasi_static import SimSettings, WorldStatus

    if len(garments) == 0:
        raise ValueError("garments must hold at least one (template, vertices) pair, got none")
    shp = np.asarray(shapes, dtype=np.float32)
    if shp.ndim == 1:
        shp = np.tile(shp[None], (len(garments), 1))
    if shp.ndim != 2 or shp.shape[0] != len(garments) or shp.shape[1] != body.shape_size:
        raise ValueError(f"shapes must have shape ({len(garments)}, {body.shape_size}) or ({body.shape_size},), "
                         f"got {np.shape(shapes)}")
    pieces, parts = [], set()
    for w, (tpl, verts) in enumerate(garments):
        v = np.asarray(verts, dtype=np.float64)
        if v.shape != (tpl.vertex_count, 3):
            raise ValueError(f"garments[{w}] vertices must have shape ({tpl.vertex_count}, 3) for its "
                             f"{tpl.garment_type} template, got {v.shape}")
        pieces.append({"vertices": v, "faces": tpl.faces, "fabric": fabric,
                       "attached": tpl.attachment if len(tpl.attachment) else None,
                       "skinning_weights": tpl.skinning_weights, "material_uv": tpl.face_uv})
        parts.update(COLLISION_PARTS[tpl.garment_type])
    posed = body.pose(shp, body.canonical_pose)
    settings = SimSettings(max_frames=int(max_frames), tolerance=float(tolerance), substeps=int(substeps),
                           iterations=int(iterations), damping=float(damping),
                           explosion_stretch=float(explosion_stretch), patience=5, outlier_fraction=0.0,
                           limit_cycle_window=0, frame_dt=1.0 / 60.0, body_contact_detect_every=1)
    sim = drape_simulator(pieces, posed.vertices.astype(np.float64), body.part_faces(sorted(parts)), device=device,
                          settings=settings, thickness=body_thickness)
    model, collider = sim.model, sim.collider
    world = np.asarray(model.particle_world_np)
    start = sim.positions()
    sd0 = _penetration(collider, start, world)
    t0 = time.perf_counter()
    status = sim.relax()
    seconds = time.perf_counter() - t0
    q = sim.positions()
    sd = _penetration(collider, q, world)
    out, depth, frac, frac0 = [], [], [], []
    for w in range(len(garments)):
        sl = model.world_slice(w)
        out.append(q[sl].astype(np.float32))
        depth.append(float(max(0.0, -sd[sl].min())))
        frac.append(float((sd[sl] < -PENETRATION_TOLERANCE_M).mean()))
        frac0.append(float((sd0[sl] < -PENETRATION_TOLERANCE_M).mean()))
    return DrapeResult(
        vertices=out, status=[WorldStatus(int(s)).name for s in status], frames=sim.world_frames.copy(),
        max_penetration_m=np.array(depth), penetrating_fraction=np.array(frac),
        start_penetrating_fraction=np.array(frac0), seconds=seconds,
        settings={"fabric": fabric, "device": str(device), "max_frames": int(max_frames), "tolerance": float(tolerance),
                  "substeps": int(substeps), "iterations": int(iterations), "body_thickness": float(body_thickness),
                  "damping": float(damping), "explosion_stretch": float(explosion_stretch)},
    )
