"""Dresses (top + skirt) and jumpsuits (top + trousers) sewn at the waist into one mesh
(seed 004, Sec. 3.2: "a final step automatically sews them together").

Jumpsuit: the top (neck, armholes) and the trousers (leg cuts) are cut out of the canonical
body as one region, which the waist level set then splits into the upper and the lower
piece (:func:`simulate.garment.mesh_ops.cut_by_field` on both sides of the same field, so both
pieces' waist loops are the same cut points); the pieces are sewn along those loops with
:func:`simulate.garment.mesh_ops.sew_loops`. The sewn mesh is body-topology (every vertex is
embedded in a body triangle) and is styled like trousers (leg length, looseness, width profile).

Dress: the upper piece is a sleeveless top cut at the waist; the skirt is a ring grid whose
first ring is the top's waist loop (one column per loop vertex, at the loop vertices' angles
around the waist), its other rings down to the sampled hem on the hull of hips and legs plus
looseness plus flare; the skirt is sewn to the top along that ring. The upper piece's vertices
come first in the mesh, then the skirt's rows below the seam.

Both keep per-vertex ``piece`` (0 upper, 1 lower) and the ordered ``seam`` loop on the template.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from simulate.body.base import PARTS
from simulate.garment import mesh_ops
from simulate.garment.style import StyleParams

#: Largest distance [m] between matched seam vertices: the loops are built to coincide.
SEAM_TOLERANCE_M = 1.0e-6
#: Share of the median edge length within which a vertex is snapped onto the jumpsuit's waist
#: cut (no sliver triangles along the seam), capped at ``templates.CUT_SNAP_M``.
SEAM_SNAP_FRACTION = 0.3
#: Share of a dress's vertices (at the requested resolution) given to its upper piece.
DRESS_UPPER_SHARE = 0.5


def _waist_height(joints) -> float:
    from simulate.garment.templates import WAIST_BELOW_SPINE1_M

    return float(joints["spine1"][1] - WAIST_BELOW_SPINE1_M)


def _nearest_loop(vertices: np.ndarray, faces: np.ndarray, y: float) -> np.ndarray:
    """The boundary loop whose mean height is nearest ``y``."""
    loops = mesh_ops.boundary_loops(faces)
    return min(loops, key=lambda l: abs(float(vertices[l, 1].mean()) - y))


def split_and_sew(vertices: np.ndarray, faces: np.ndarray, y_seam: float, snap: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Splits a mesh at height ``y_seam`` [m] into an upper and a lower piece and sews them back
    along their waist loops. Returns (vertices (V', 3), faces (F', 3), piece (V',) 0 upper / 1
    lower, seam (N,) ordered loop)."""
    field = np.asarray(vertices)[:, 1] - y_seam
    pieces = []
    for sign in (-1.0, 1.0):  # upper keeps field >= 0, lower keeps field <= 0
        v, f, _, _, _ = mesh_ops.cut_by_field(vertices, faces, sign * field, snap=snap)
        f, used = mesh_ops.remove_unused_vertices(f, len(v))
        v = v[used]
        pieces.append((v, f, _nearest_loop(v, f, y_seam)))
    (va, fa, la), (vb, fb, lb) = pieces
    v, f, _ = mesh_ops.sew_loops(va, fa, la, vb, fb, lb, tolerance=SEAM_TOLERANCE_M)
    piece = np.concatenate([np.zeros(len(va), np.int64), np.ones(len(v) - len(va), np.int64)])
    return v, f, piece, la


def _template_fields(garment_type, body, surf, faces, body_face, body_bary):
    from simulate.garment.templates import _segments, body_joints

    bv, _ = body_joints(body, body.shape_default)
    corner = np.argmax(body_bary, axis=1)
    part = np.asarray(body.vertex_parts)[body.faces[body_face, corner]]
    index = cKDTree(bv).query(surf)[1].astype(np.int64)
    weights = np.einsum("vk,vkj->vj", body_bary, body.skinning_weights[body.faces[body_face]])
    weights = (weights / weights.sum(1, keepdims=True)).astype(np.float32)
    return index, weights, _segments(garment_type, part, np.sign(surf[:, 0]))


def _region_query(garment_type: str, body):
    from simulate.garment.templates import _allowed_parts, body_joints

    bv, _ = body_joints(body, body.shape_default)
    f0 = np.asarray(body.faces, dtype=np.int64)
    region_index = np.nonzero(np.isin(np.asarray(body.vertex_parts)[f0], _allowed_parts(garment_type)).all(1))[0]
    return mesh_ops.ClosestPointQuery(bv, f0[region_index]), region_index


def make_sewn_template(garment_type: str, body, resolution: int, style: StyleParams):
    """The template of a dress or jumpsuit (see the module docstring); ``resolution`` is the
    target vertex count, ``style`` the style of its rest ``vertices``."""
    from simulate.garment import uv as uv_mod
    from simulate.garment.templates import (CUT_SNAP_M, GarmentTemplate, _body_region, _name_loops, apply_style,
                                            body_joints, skirt_skinning_weights, subdivision_level_for)

    _, joints = body_joints(body, body.shape_default)
    y_waist = _waist_height(joints)
    if garment_type == "jumpsuit":
        level = subdivision_level_for(garment_type, body, resolution)
        v, f = _body_region(garment_type, body, level)[:2]
        edges, _ = mesh_ops.unique_edges(f)
        median = float(np.median(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1)))
        v, f, piece, seam = split_and_sew(v, f, y_waist, min(CUT_SNAP_M, SEAM_SNAP_FRACTION * median))
        query, region_index = _region_query(garment_type, body)
        surf, face, bary, _ = query.query(v)
        body_face = region_index[face]
        index, weights, segment = _template_fields(garment_type, body, surf, f, body_face, bary)
        grid = (0, 0)
    else:
        level = subdivision_level_for("dress", body, int(resolution * DRESS_UPPER_SHARE))
        surf_u, f_u, body_face_u, bary_u = _body_region("dress", body, level)[:4]
        loop = _nearest_loop(surf_u, f_u, y_waist)
        cols = len(loop)
        rows = max(4, int(round((resolution - len(surf_u)) / cols)) + 1)
        skirt_f = _skirt_grid_faces(rows, cols)
        skirt_v = np.zeros((rows * cols, 3))
        skirt_v[:cols] = surf_u[loop]
        surf, f, index_b = mesh_ops.sew_loops(surf_u, f_u, loop, skirt_v, skirt_f, np.arange(cols),
                                               tolerance=SEAM_TOLERANCE_M)
        if not np.array_equal(index_b[cols:], len(surf_u) + np.arange((rows - 1) * cols)):
            raise RuntimeError("the dress's skirt rows are not appended in row order")
        seam = loop
        n_u = len(surf_u)
        piece = np.concatenate([np.zeros(n_u, np.int64), np.ones(len(surf) - n_u, np.int64)])
        index_u, weights_u, segment_u = _template_fields("dress", body, surf_u, f_u, body_face_u, bary_u)
        nv = len(surf)
        body_face = np.concatenate([body_face_u, np.full(nv - n_u, -1)])
        bary = np.concatenate([bary_u, np.zeros((nv - n_u, 3))])
        index = np.concatenate([index_u, np.full(nv - n_u, -1)])
        weights = np.concatenate([weights_u, np.zeros((nv - n_u, body.joint_count), np.float32)])
        segment = np.concatenate([segment_u, np.zeros(nv - n_u, np.int64)])
        grid = (rows, cols)
    tpl = GarmentTemplate(
        garment_type=garment_type, vertices=np.asarray(surf, np.float32), faces=np.asarray(f, np.int64),
        uv=np.zeros((len(surf), 2), np.float32), face_uv=np.zeros((len(f), 3, 2), np.float32),
        vertex_panel=np.zeros(len(surf), np.int64), face_panel=np.zeros(len(f), np.int64), panel_names=[],
        boundary_names=[], boundary_loops=[], attachment=np.zeros(0, np.int64), skinning_weights=weights,
        body_vertex_index=np.asarray(index, np.int64), body_face=np.asarray(body_face, np.int64),
        body_bary=np.asarray(bary, np.float32), segment=np.asarray(segment, np.int64), grid_shape=grid,
        resolution=level, body_name=body.name, default_style=dict(style.values),
        piece=piece, seam=np.asarray(seam, np.int64))
    tpl.vertices = apply_style(tpl, style, body)
    if garment_type == "dress":
        n_u = int((piece == 0).sum())
        tpl.skinning_weights[n_u:] = skirt_skinning_weights(body, tpl.vertices[n_u:])
    names, loops = _name_loops(garment_type, tpl.vertices, mesh_ops.boundary_loops(tpl.faces))
    tpl.boundary_names, tpl.boundary_loops = names, loops
    uv_mod.build_uv(tpl)
    return tpl


def _skirt_grid_faces(rows: int, cols: int) -> np.ndarray:
    from simulate.garment.templates import _skirt_faces

    return _skirt_faces(rows, cols)


def dress_vertices(template, style: StyleParams, body, shape=None) -> np.ndarray:
    """Vertices (V, 3) [m] of a dress of ``style`` on the canonical body of ``shape`` (default
    neutral): the upper piece styled as a top cut at the waist; skirt ring k (k = 0 the seam) of
    column c at the height of seam vertex c moved toward the hem by k / (rows - 1), its radius
    around the waist centre the larger of the seam vertex's and the hull's (plus looseness),
    plus ``flare`` times the ring's depth below the seam over the longest skirt's."""
    from simulate.garment.templates import SKIRT_CUT, body_joints, skirt_hull, styled_body_surface

    shape = body.shape_default if shape is None else np.asarray(shape, dtype=np.float32)
    piece = template.piece
    n_u = int((piece == 0).sum())
    rows, cols = template.grid_shape
    upper_faces = template.faces[(piece[template.faces] == 0).all(1)]
    upper = styled_body_surface("dress", style, body, shape, upper_faces, template.body_face[:n_u],
                                template.body_bary[:n_u], template.segment[:n_u])
    _, joints = body_joints(body, shape)
    y_hip = 0.5 * (joints["left_hip"][1] + joints["right_hip"][1])
    y_knee = 0.5 * (joints["left_knee"][1] + joints["right_knee"][1])
    lo, hi = SKIRT_CUT
    y_hem = y_hip + (y_knee - y_hip) * (lo + (hi - lo) * style["length"])
    y_longest = y_hip + (y_knee - y_hip) * hi
    seam = upper[template.seam]  # (cols, 3)
    t = np.linspace(0.0, 1.0, rows)[:, None]
    ring_y = seam[None, :, 1] + (y_hem - seam[None, :, 1]) * t  # (rows, cols)
    centre, radius, bins = skirt_hull(body, shape, ring_y.mean(1))
    rel = seam - centre
    theta = np.arctan2(rel[:, 0], rel[:, 2])
    r_seam = np.linalg.norm(rel[:, [0, 2]], axis=1)
    bin_centres = (np.arange(bins) + 0.5) / bins * 2 * np.pi - np.pi
    depth = (seam[None, :, 1] - ring_y) / max(float(seam[:, 1].mean() - y_longest), 1e-6)
    out = np.zeros((rows, cols, 3))
    for k in range(rows):
        hull = np.interp(theta, bin_centres, radius[k], period=2 * np.pi) + style["looseness"]
        r = np.maximum(hull, r_seam) + style["flare"] * depth[k]
        out[k, :, 0] = centre[0] + r * np.sin(theta)
        out[k, :, 1] = ring_y[k]
        out[k, :, 2] = centre[2] + r * np.cos(theta)
    out[0] = seam
    return np.concatenate([upper, out[1:].reshape(-1, 3)]).astype(np.float32)
