"""Primary collision bodies: the body split into overlapping parts, each cloth vertex colliding with one.

Seed 001 (appendix D.6) decomposes the body into the left arm, the right arm and the torso and gives
each cloth vertex one of them as its primary collision body. Skinning makes the skins of an arm and
the torso interpenetrate at the armpit and brings them within a few millimetres of each other when
the arm hangs down; a sleeve held off the arm and a torso panel held off the torso then each feel
only their own skin, and neither is pushed through the other by the wrong one.

A body vertex belongs to the part of the bone that moves it most (``BodyModel.vertex_parts``),
split by side for arms (with hands) and legs (with feet); the head and everything else count as
torso. Each part's collision mesh also takes the faces within ``overlap_rings`` face rings of it,
so the shoulder and the hip are covered from both sides and a cloth vertex near a part's boundary
does not fall through the cut.

Which scheme a garment uses (``GARMENT_SCHEMES``): tops split arms from the torso, pants and shorts
legs from the torso; a skirt, whose panels hang across both legs, collides with the whole body, and
so do the sleeveless top and the dress; a jumpsuit splits its legs from the torso like trousers.
"""

from __future__ import annotations

import numpy as np

from simulate.body.base import PARTS, BodyModel

__all__ = ["COLLISION_PART_NAMES", "GARMENT_SCHEMES", "OVERLAP_RINGS", "CollisionParts", "collision_parts"]

COLLISION_PART_NAMES: tuple[str, ...] = ("torso", "left_arm", "right_arm", "left_leg", "right_leg")
"""Names of the body's collision parts; a part index is a position in this tuple."""

GARMENT_SCHEMES: dict[str, tuple[str, ...]] = {
    "tshirt": ("torso", "left_arm", "right_arm"),
    "shirt": ("torso", "left_arm", "right_arm"),
    "pants": ("torso", "left_leg", "right_leg"),
    "shorts": ("torso", "left_leg", "right_leg"),
    "skirt": ("torso",),
    "top": ("torso",),  # sleeveless: no sleeve is held off an arm
    "dress": ("torso",),
    "jumpsuit": ("torso", "left_leg", "right_leg"),
}
"""Collision parts per garment type; a body vertex of a part not listed counts as the first (torso)."""

OVERLAP_RINGS = 2
"""Face rings each part's collision mesh reaches past its own vertices (anny: ~2-4 cm)."""


def _vertex_part_labels(body: BodyModel, rest_vertices: np.ndarray) -> np.ndarray:
    """Index into COLLISION_PART_NAMES per body vertex (V,); left is +x."""
    region = np.asarray(PARTS)[np.asarray(body.vertex_parts)]
    left = np.asarray(rest_vertices)[:, 0] > 0.0
    label = np.zeros(len(region), np.int64)
    arm = np.isin(region, ("arms", "hands"))
    leg = np.isin(region, ("legs", "feet"))
    label[arm & left] = COLLISION_PART_NAMES.index("left_arm")
    label[arm & ~left] = COLLISION_PART_NAMES.index("right_arm")
    label[leg & left] = COLLISION_PART_NAMES.index("left_leg")
    label[leg & ~left] = COLLISION_PART_NAMES.index("right_leg")
    return label


class CollisionParts:
    """The collision parts of one body mesh for one garment type.

    Attributes:
        names: the parts in use, a tuple of COLLISION_PART_NAMES entries (first: torso).
        vertex_part: (Vb,) int64, index into ``names`` per body vertex.
        face_groups: per part, the rows of ``faces`` in its collision mesh (the part's faces and
            those within ``overlap_rings`` rings of it), int64 arrays.
    """

    def __init__(self, names: tuple[str, ...], vertex_part: np.ndarray, faces: np.ndarray, overlap_rings: int) -> None:
        self.names = tuple(names)
        self.vertex_part = np.asarray(vertex_part, np.int64)
        faces = np.asarray(faces, np.int64)
        groups = []
        for p in range(len(self.names)):
            member = self.vertex_part == p
            for _ in range(int(overlap_rings)):
                touched = member[faces].any(axis=1)
                member = member.copy()
                member[faces[touched].reshape(-1)] = True
            groups.append(np.nonzero(member[faces].any(axis=1))[0])
        self.face_groups = groups

    def garment_vertex_parts(self, garment_vertices: np.ndarray, body_vertices: np.ndarray) -> np.ndarray:
        """Primary part per garment vertex (V,) int32: the part of its nearest body vertex, both at rest
        on the same body [m] ((V, 3) and (Vb, 3))."""
        from scipy.spatial import cKDTree

        g = np.asarray(garment_vertices, np.float64)
        b = np.asarray(body_vertices, np.float64)
        if g.ndim != 2 or g.shape[1] != 3 or b.shape != (len(self.vertex_part), 3):
            raise ValueError(f"garment_vertices must be (V, 3) and body_vertices ({len(self.vertex_part)}, 3) "
                             f"(got {g.shape} and {b.shape})")
        _, nearest = cKDTree(b).query(g)
        return self.vertex_part[nearest].astype(np.int32)


def collision_parts(body: BodyModel, garment_type: str, faces: np.ndarray | None = None, *,
                    overlap_rings: int = OVERLAP_RINGS) -> CollisionParts:
    """Collision parts of ``body`` for ``garment_type`` over ``faces`` (default the body's).

    Args:
        body: body model (its ``vertex_parts`` and neutral rest shape decide the labels).
        garment_type: a key of GARMENT_SCHEMES.
        faces: the body faces the garment can touch, (Fb, 3) (the culled set given to the collider).
        overlap_rings: face rings each part reaches past its vertices (>= 0).
    """
    if garment_type not in GARMENT_SCHEMES:
        raise ValueError(f"garment type {garment_type!r} has no collision parts; expected one of "
                         f"{', '.join(GARMENT_SCHEMES)}")
    if int(overlap_rings) != overlap_rings or overlap_rings < 0:
        raise ValueError(f"overlap_rings must be an integer >= 0 (got {overlap_rings!r})")
    names = GARMENT_SCHEMES[garment_type]
    rest, _ = body.rest(body.shape_default)
    full = _vertex_part_labels(body, np.asarray(rest).reshape(-1, 3))
    local = np.zeros(len(full), np.int64)  # parts the scheme does not name count as its first
    for k, name in enumerate(names):
        local[full == COLLISION_PART_NAMES.index(name)] = k
    return CollisionParts(names, local, body.faces if faces is None else faces, int(overlap_rings))
