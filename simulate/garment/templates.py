"""Garment templates on the canonical body: t-shirt, shirt, sleeveless top, pants, shorts
(body-surface regions, TailorNet's indicator I), skirt (its own surface, attached at the
waist), and the dress and jumpsuit sewn from an upper and a lower piece at the waist
(the last section of this module).

A body-topology garment is cut out of the canonical body mesh (neutral shape, canonical
A-pose) along level sets defined from joint positions (planes through the hips, a
tilted neck cut, cuts perpendicular to the limb axes), cleaned to a manifold with simple
boundary loops, midpoint-subdivided to the requested resolution and embedded in the
body's triangles (``body_face``, ``body_bary``): the garment surface on any body shape
is the same barycentric points on that shape's mesh, and a style is an outward offset
of that surface (see :func:`apply_style`). The embedding also gives I
(``body_vertex_index``: the nearest body vertex of each garment vertex) and the
skinning weights (barycentric interpolation of the body's weights).

The skirt is a ring grid (rows x columns) from the waist down, with radii from the
hull of the hips and legs; I = -1 and its skinning weights are inverse-distance
averages of its K = 100 nearest torso/leg body vertices (TailorNet).

Frame: metres, y up, facing +z, left +x (see :mod:`simulate.body.base`).
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from simulate.body.base import PARTS, POSE_JOINTS
from simulate.garment import mesh_ops
from simulate.garment.cloth3d import CLOTH3D
from simulate.garment.style import GARMENT_TYPES, STYLE_SPECS, StyleParams, check_garment_type

#: Default target vertex count per type (TailorNet's counts: t-shirt 7,702, shirt 9,723,
#: pants 4,718, skirt 7,130). Body-topology garments take the subdivision level whose
#: count is nearest in log scale, so actual counts differ (see the template).
DEFAULT_RESOLUTION: dict[str, int] = {"tshirt": 7700, "shirt": 9700, "pants": 4700, "shorts": 3000, "skirt": 7100,
                                      "top": 6000, "dress": 9000, "jumpsuit": 9000}

#: Expected boundary loop names per type.
BOUNDARY_NAMES: dict[str, tuple[str, ...]] = {
    "tshirt": ("neck", "hem", "left_sleeve", "right_sleeve"),
    "shirt": ("neck", "hem", "left_sleeve", "right_sleeve"),
    "pants": ("waist", "left_hem", "right_hem"),
    "shorts": ("waist", "left_hem", "right_hem"),
    "skirt": ("waist", "hem"),
    "top": ("neck", "hem", "left_armhole", "right_armhole"),
    "dress": ("neck", "hem", "left_armhole", "right_armhole"),
    "jumpsuit": ("neck", "left_armhole", "right_armhole", "left_hem", "right_hem"),
}
#: Types whose upper part is a top: a neck cut and (tshirt, shirt) sleeves or armholes.
UPPER_TYPES = ("tshirt", "shirt", "top", "dress", "jumpsuit")
#: Types cut at the arm roots (sleeveless).
ARMHOLE_TYPES = ("top", "dress", "jumpsuit")

#: Segment ids stored per vertex (which length parameter slides it).
SEGMENT_NONE, SEGMENT_TORSO, SEGMENT_LEFT, SEGMENT_RIGHT = 0, 1, 2, 3

#: Limb chains (joint names) and cut positions in "bone units" u: u = i + t is the point
#: at fraction t along bone i of the chain. (anchor, shortest, longest).
LIMB_CUTS: dict[str, tuple[str, float, float, float]] = {
    "tshirt": ("arm", 0.2, 0.35, 0.85),
    "shirt": ("arm", 0.2, 1.3, 1.92),
    "pants": ("leg", 0.25, 1.3, 1.92),
    "shorts": ("leg", 0.25, 0.35, 0.8),
    "jumpsuit": ("leg", 0.25, 0.35, 1.92),  # from shorts' shortest to pants' longest
}
#: Torso hem of tops in units of (spine2 height - hip height) below spine2: (anchor, shortest, longest).
TORSO_CUT: tuple[float, float, float] = (0.3, 0.55, 1.05)
#: Skirt hem: fraction of hip -> knee height (shortest, longest).
SKIRT_CUT: tuple[float, float] = (0.35, 1.2)
#: Waist of pants/shorts/skirt below the spine1 joint [m] (anny spine1 is near the navel).
WAIST_BELOW_SPINE1_M = 0.01
#: Skinning weights of the skirt: K nearest body vertices (TailorNet).
SKIRT_SKINNING_NEIGHBOURS = 100
#: Generated garment vertices are kept at least this far outside the body [m].
PUSH_CLEARANCE_M = 0.004
#: Radius [m] over which the normals of the style offset are smoothed (at least 10 rings):
#: sharper normals converge in concave places and fold loose offsets there.
OFFSET_NORMAL_RADIUS_M = 0.05
#: Offset faces smaller than this fraction of their surface face are smoothed (unfold_offset).
UNFOLD_AREA_FRACTION = 0.2
#: An offset point must stay this fraction of its offset away from the body.
SAFE_OFFSET_RATIO = 0.95
#: Edges shorter than this fraction of the median edge are collapsed.
SHORT_EDGE_FRACTION = 0.35
#: Cut vertices closer than this to a cut are snapped onto it (no slivers) [m].
CUT_SNAP_M = 0.004


def _chain(kind: str, side: int) -> list[str]:
    s = "left" if side > 0 else "right"
    return [f"{s}_shoulder", f"{s}_elbow", f"{s}_wrist"] if kind == "arm" else [f"{s}_hip", f"{s}_knee", f"{s}_ankle"]


_JOINTS_CACHE: dict[tuple, tuple[np.ndarray, dict[str, np.ndarray]]] = {}


def body_joints(body, shape) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Canonical-pose vertices (V, 3) and the 20 posable joints {name: (3,)} [m] for a
    shape (cached per body and shape values; callers must not modify the arrays)."""
    shape = np.asarray(shape, dtype=np.float32).reshape(-1)
    key = (id(body), body.name, shape.tobytes())
    if key not in _JOINTS_CACHE:
        if len(_JOINTS_CACHE) > 32:
            _JOINTS_CACHE.clear()
        posed = body.pose(shape, body.canonical_pose)
        j = posed.joints[0][body.pose_joint_indices]
        verts = posed.vertices[0].astype(np.float64)
        verts.setflags(write=False)
        _JOINTS_CACHE[key] = (verts, {n: j[i].astype(np.float64) for i, n in enumerate(POSE_JOINTS)})
    return _JOINTS_CACHE[key]


def limb_coordinate(points: np.ndarray, chain: list[np.ndarray]) -> np.ndarray:
    """Bone-unit coordinate u (N,) of points along a joint polyline (u = i + t on bone i)."""
    best_d = np.full(len(points), np.inf)
    u = np.zeros(len(points))
    for i in range(len(chain) - 1):
        a, b = chain[i], chain[i + 1]
        ab = b - a
        t = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        d = np.linalg.norm(points - (a + t[:, None] * ab), axis=1)
        better = d < best_d
        best_d[better] = d[better]
        u[better] = i + t[better]
    return u


def limb_point(u: np.ndarray, chain: list[np.ndarray]) -> np.ndarray:
    """Points (N, 3) at bone-unit coordinates u along the polyline."""
    i = np.clip(np.floor(u).astype(int), 0, len(chain) - 2)
    t = (u - i)[:, None]
    c = np.stack(chain)
    return c[i] + t * (c[i + 1] - c[i])


@dataclass
class GarmentTemplate:
    """One garment type's mesh on the canonical body, with everything datasets need.

    Attributes:
        garment_type: one of :data:`GARMENT_TYPES`.
        vertices: rest garment [m] at the default style on the canonical body (neutral
            shape, canonical pose), shape (V, 3).
        faces: triangles, shape (F, 3), outward-oriented.
        uv: per-vertex UV of the vertex's first panel (main chart), in [0, 1]^2, (V, 2).
        face_uv: per-face-corner UV, (F, 3, 2): seam vertices have one UV per panel.
        vertex_panel: panel of each vertex's main chart, (V,); face_panel: (F,).
        panel_names: names of the panels ("front", "back").
        boundary_names / boundary_loops: named ordered vertex loops (neck, hem, ...).
        attachment: vertex indices attached to the body (waistband of pants, shorts and
            skirt), (A,); empty for tops, which hang on the shoulders.
        skinning_weights: (V, J) float32, rows sum to 1.
        body_vertex_index: I, nearest body vertex of each garment vertex, (V,); -1 for the skirt.
        body_face / body_bary: embedding of each vertex in a body triangle, (V,), (V, 3);
            -1 / 0 for the skirt.
        segment: which length parameter slides each vertex (SEGMENT_*), (V,).
        grid_shape: (rows, columns) of the skirt's ring grid; (0, 0) otherwise.
        resolution: subdivision level (body-topology) or target vertex count (skirt).
        body_name: body backend the template was cut from.
        default_style: the style ``vertices`` were generated with.
        piece: of sewn types (dress, jumpsuit), which piece each vertex comes from, (V,):
            0 the upper garment (top), 1 the lower (skirt or trousers); seam vertices count
            as the upper's. Empty for single-piece types.
        seam: of sewn types, the ordered waist seam loop (vertex indices) the pieces were
            sewn along, (N,); empty otherwise.
    """

    garment_type: str
    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    face_uv: np.ndarray
    vertex_panel: np.ndarray
    face_panel: np.ndarray
    panel_names: list[str]
    boundary_names: list[str]
    boundary_loops: list[np.ndarray]
    attachment: np.ndarray
    skinning_weights: np.ndarray
    body_vertex_index: np.ndarray
    body_face: np.ndarray
    body_bary: np.ndarray
    segment: np.ndarray
    grid_shape: tuple[int, int] = (0, 0)
    resolution: int = 0
    body_name: str = "anny"
    default_style: dict[str, float] = field(default_factory=dict)
    piece: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    seam: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def vertex_count(self) -> int:
        return int(len(self.vertices))

    @property
    def follows_body_topology(self) -> bool:
        return bool((self.body_vertex_index >= 0).all())

    def boundary(self, name: str) -> np.ndarray:
        """Ordered vertex indices of a named boundary loop."""
        if name not in self.boundary_names:
            raise ValueError(f"template {self.garment_type!r} has no boundary {name!r}; it has {', '.join(self.boundary_names)}")
        return self.boundary_loops[self.boundary_names.index(name)]

    # ------------------------------------------------------------------ io
    def _arrays(self) -> dict[str, np.ndarray]:
        lengths = np.array([len(l) for l in self.boundary_loops], dtype=np.int64)
        return {
            "vertices": np.asarray(self.vertices, np.float32), "faces": np.asarray(self.faces, np.int64),
            "uv": np.asarray(self.uv, np.float32), "face_uv": np.asarray(self.face_uv, np.float32),
            "vertex_panel": np.asarray(self.vertex_panel, np.int64), "face_panel": np.asarray(self.face_panel, np.int64),
            "boundary_concat": np.concatenate(self.boundary_loops).astype(np.int64) if self.boundary_loops else np.zeros(0, np.int64),
            "boundary_lengths": lengths, "attachment": np.asarray(self.attachment, np.int64),
            "skinning_weights": np.asarray(self.skinning_weights, np.float32),
            "body_vertex_index": np.asarray(self.body_vertex_index, np.int64),
            "body_face": np.asarray(self.body_face, np.int64), "body_bary": np.asarray(self.body_bary, np.float32),
            "segment": np.asarray(self.segment, np.int64),
            # sewn types only: single-piece templates keep their arrays (and hashes) without them
            **({"piece": np.asarray(self.piece, np.int64), "seam": np.asarray(self.seam, np.int64)}
               if len(self.seam) else {}),
        }

    def _meta(self) -> dict:
        return {"garment_type": self.garment_type, "panel_names": list(self.panel_names),
                "boundary_names": list(self.boundary_names), "grid_shape": [int(x) for x in self.grid_shape],
                "resolution": int(self.resolution), "body_name": self.body_name,
                "default_style": {k: float(v) for k, v in self.default_style.items()}}

    def content_hash(self) -> str:
        """sha256 (hex) of every array (dtype, shape, bytes) and the metadata, in a fixed order."""
        h = hashlib.sha256()
        for name, arr in sorted(self._arrays().items()):
            a = np.ascontiguousarray(arr)
            h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
            h.update(a.tobytes())
        h.update(json.dumps(self._meta(), sort_keys=True).encode())
        return h.hexdigest()

    def save(self, path: str | Path) -> Path:
        """Writes the template as .npz (arrays + JSON metadata + content hash)."""
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"template path must end in .npz, got {path.name!r}")
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp.npz")
        np.savez_compressed(tmp, meta=np.array(json.dumps(self._meta())), sha256=np.array(self.content_hash()),
                            **self._arrays())
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> "GarmentTemplate":
        """Reads a template written by :meth:`save`; checks its content hash."""
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"garment template file {str(path)!r} does not exist")
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            arrays = {k: z[k] for k in z.files if k not in ("meta", "sha256")}
            stored = str(z["sha256"])
        loops = np.split(arrays.pop("boundary_concat"), np.cumsum(arrays.pop("boundary_lengths"))[:-1])
        tpl = cls(garment_type=meta["garment_type"], boundary_loops=list(loops), panel_names=meta["panel_names"],
                  boundary_names=meta["boundary_names"], grid_shape=tuple(meta["grid_shape"]),
                  resolution=meta["resolution"], body_name=meta["body_name"], default_style=meta["default_style"],
                  **arrays)
        if tpl.content_hash() != stored:
            raise ValueError(f"garment template {str(path)!r} is corrupt: content hash {tpl.content_hash()} "
                             f"differs from the stored {stored}")
        return tpl


# ------------------------------------------------------------------ body-topology cut
def _cut_fields(garment_type: str, joints: dict[str, np.ndarray]):
    """Cuts of a body-topology type as functions (vertices (V,3), parts (V,)) ->
    (field (V,) with the kept side <= 0 [m or bone units], applicable bool (V,))."""
    p = {name: PARTS.index(name) for name in PARTS}
    cuts = []
    if garment_type in UPPER_TYPES:
        neck, collar = joints["neck"], 0.5 * (joints["left_collar"] + joints["right_collar"])
        origin = np.array([neck[0], 0.5 * (neck[1] + collar[1]), neck[2]])
        tilt = np.radians(25.0)
        normal = np.array([0.0, np.cos(tilt), np.sin(tilt)])

        def neck_cut(v, part):
            plane = (v - origin) @ normal
            hole = 0.10 - np.linalg.norm((v - neck)[:, [0, 2]], axis=1)
            return np.minimum(plane, hole), np.isin(part, [p["torso"], p["head"]])

        y_top = joints["spine2"][1]
        y_hip = 0.5 * (joints["left_hip"][1] + joints["right_hip"][1])
        y_hem = y_top - TORSO_CUT[2] * (y_top - y_hip)
        if garment_type == "dress":  # the upper piece ends at the waist seam
            y_hem = joints["spine1"][1] - WAIST_BELOW_SPINE1_M

        def hem_cut(v, part):
            return y_hem - v[:, 1], np.isin(part, [p["torso"], p["legs"]])

        cuts += [neck_cut] if garment_type == "jumpsuit" else [neck_cut, hem_cut]
    if garment_type in ARMHOLE_TYPES:
        for side in (1, -1):
            chain = [joints[n] for n in _chain("arm", side)]
            bone = float(np.linalg.norm(chain[1] - chain[0]))

            def armhole_cut(v, part, chain=chain, side=side, bone=bone):
                u = limb_coordinate(v, chain)
                return (u - CLOTH3D.top_armhole_u) * bone, np.isin(part, [p["arms"], p["hands"]]) & (np.sign(v[:, 0]) == side)

            cuts.append(armhole_cut)
    if garment_type not in UPPER_TYPES:
        y_waist = joints["spine1"][1] - WAIST_BELOW_SPINE1_M

        def waist_cut(v, part):
            return v[:, 1] - y_waist, np.isin(part, [p["torso"], p["arms"], p["hands"]])

        cuts.append(waist_cut)
    if garment_type not in LIMB_CUTS:
        return cuts
    kind, _, _, u_max = LIMB_CUTS[garment_type]
    limb_parts = [p["arms"], p["hands"]] if kind == "arm" else [p["legs"], p["feet"]]
    for side in (1, -1):
        chain = [joints[n] for n in _chain(kind, side)]

        bone = np.linalg.norm(chain[int(min(u_max, 1.999))] - chain[int(min(u_max, 1.999)) + 1])

        def limb_cut(v, part, chain=chain, side=side, bone=bone):
            u = limb_coordinate(v, chain)  # bone units; times the bone length: ~metres near the cut
            return (u - u_max) * bone, np.isin(part, limb_parts) & (np.sign(v[:, 0]) == side)

        cuts.append(limb_cut)
    return cuts


def _allowed_parts(garment_type: str) -> list[int]:
    names = ("torso", "arms", "legs") if garment_type in UPPER_TYPES else ("torso", "legs")
    return [PARTS.index(n) for n in names]


def _name_loops(garment_type: str, v: np.ndarray, loops: list[np.ndarray]) -> tuple[list[str], list[np.ndarray]]:
    expected = BOUNDARY_NAMES[garment_type]
    if len(loops) != len(expected):
        raise RuntimeError(f"{garment_type} template has {len(loops)} boundary loops, expected {len(expected)} "
                           f"({', '.join(expected)})")
    centre = np.array([v[l].mean(0) for l in loops])
    names: list[str | None] = [None] * len(loops)
    side = np.argsort(centre[:, 0])
    if garment_type == "skirt":
        order = np.argsort(-centre[:, 1])
        names[order[0]], names[order[1]] = "waist", "hem"
    elif garment_type in ("tshirt", "shirt", "top", "dress"):
        sleeve = "sleeve" if garment_type in ("tshirt", "shirt") else "armhole"
        names[side[-1]], names[side[0]] = f"left_{sleeve}", f"right_{sleeve}"
        mid = [i for i in range(4) if names[i] is None]
        hi, lo = sorted(mid, key=lambda i: -centre[i, 1])
        names[hi], names[lo] = "neck", "hem"
    elif garment_type == "jumpsuit":
        low = sorted(range(5), key=lambda i: centre[i, 1])[:2]  # the two leg hems are lowest
        left_hem = max(low, key=lambda i: centre[i, 0])
        names[left_hem], names[[i for i in low if i != left_hem][0]] = "left_hem", "right_hem"
        upper = [i for i in range(5) if names[i] is None]
        by_x = sorted(upper, key=lambda i: centre[i, 0])
        names[by_x[-1]], names[by_x[0]], names[by_x[1]] = "left_armhole", "right_armhole", "neck"
    else:
        names[side[-1]], names[side[0]] = "left_hem", "right_hem"
        names[[i for i in range(3) if names[i] is None][0]] = "waist"
    order = [names.index(n) for n in expected]
    return list(expected), [loops[i] for i in order]


_REGION_CACHE: dict[tuple, tuple] = {}


def _body_region(garment_type: str, body, level: int):
    """Cached :func:`_body_region_uncached` (per body object, type and level)."""
    key = (id(body), body.name, garment_type, int(level))
    if key not in _REGION_CACHE:
        if len(_REGION_CACHE) > 16:
            _REGION_CACHE.clear()
        _REGION_CACHE[key] = _body_region_uncached(garment_type, body, level)
    return tuple(np.array(a, copy=True) for a in _REGION_CACHE[key])


def _body_region_uncached(garment_type: str, body, level: int):
    """Cuts, cleans, regularises and subdivides the body region.

    Returns (vertices (V, 3) on the canonical body [m], faces (F, 3), body_face (V,),
    body_bary (V, 3): each vertex's closest point on the body (its embedding),
    coarse_face (F,): the level-0 face each face lies in, coarse_bary (F, 3, 3): its
    corners' barycentrics in that level-0 face (UV charts are made at level 0)).
    """
    v0, joints = body_joints(body, body.shape_default)
    f0 = np.asarray(body.faces, dtype=np.int64)
    v, f = v0, f0
    part = np.asarray(body.vertex_parts, dtype=np.int64)
    for cut in _cut_fields(garment_type, joints):
        values, applicable = cut(v, part)
        fld = np.where(applicable, values, np.minimum(values, -1.0))
        v, f, _, _, (src, _) = mesh_ops.cut_by_field(v, f, fld, snap=CUT_SNAP_M)
        part = part[np.where(fld[src[:, 0]] <= 0, src[:, 0], src[:, 1])]
    allowed = np.isin(part, _allowed_parts(garment_type))
    f = f[allowed[f].all(1)]
    f = f[mesh_ops.clean_submesh(f, len(v))]
    # Short edges (cut points next to body vertices, thin body triangles) make stiff,
    # unstable cloth: collapse them, clean again, drop unused vertices.
    lengths = np.linalg.norm(v[mesh_ops.unique_edges(f)[0][:, 0]] - v[mesh_ops.unique_edges(f)[0][:, 1]], axis=1)
    f, _ = mesh_ops.collapse_short_edges(v, f, SHORT_EDGE_FRACTION * float(np.median(lengths)))
    f = f[mesh_ops.clean_submesh(f, len(v))]
    f, used = mesh_ops.remove_unused_vertices(f, len(v))
    v = v[used]
    region_index = np.nonzero(np.isin(np.asarray(body.vertex_parts)[f0], _allowed_parts(garment_type)).all(1))[0]
    region_faces = f0[region_index]
    query = mesh_ops.ClosestPointQuery(v0, region_faces)
    boundary = np.zeros(len(v), dtype=bool)
    for loop in mesh_ops.boundary_loops(f):
        boundary[loop] = True
    v = mesh_ops.smooth_vertex_values(v, f, iterations=3, lam=0.5, fixed=boundary)  # tangential regularisation
    v[~boundary] = query.query(v[~boundary])[0]
    # Projection can pull neighbours together in creases (armpits): collapse again.
    f, _ = mesh_ops.collapse_short_edges(v, f, SHORT_EDGE_FRACTION * float(np.median(lengths)))
    f = f[mesh_ops.clean_submesh(f, len(v))]
    f, used = mesh_ops.remove_unused_vertices(f, len(v))
    v = v[used]
    coarse_face = np.arange(len(f))
    coarse_bary = np.tile(np.eye(3)[None], (len(f), 1, 1))
    for _ in range(level):
        v, f, parent, coarse_bary = mesh_ops.midpoint_subdivide(v, f, coarse_bary)
        coarse_face = coarse_face[parent]
        v = query.query(v)[0]
    closest, face, bary, _ = query.query(v)
    return closest, f, region_index[face], bary, coarse_face, coarse_bary


def embedded_points(body_vertices: np.ndarray, body_faces: np.ndarray, body_face: np.ndarray,
                    body_bary: np.ndarray) -> np.ndarray:
    """Barycentric points on a body mesh: (..., Vb, 3) vertices -> (..., V, 3) [m]."""
    tri = np.asarray(body_vertices)[..., body_faces[body_face], :]  # (..., V, 3, 3)
    return np.einsum("vk,...vkd->...vd", body_bary, tri)


def template_surface(template: GarmentTemplate, body, *, shape=None) -> np.ndarray:
    """Zero-offset garment surface (V, 3) [m] on the canonical body of ``shape``: the
    body-surface points a body-topology garment is embedded at (for the skirt: its
    default-style vertices)."""
    if not template.follows_body_topology:
        return apply_style(template, StyleParams(template.garment_type, template.default_style), body, shape=shape)
    bv, _ = body_joints(body, body.shape_default if shape is None else shape)
    return embedded_points(bv, body.faces, template.body_face, template.body_bary)


def _segments(garment_type: str, part_of_vertex: np.ndarray, side_of_vertex: np.ndarray) -> np.ndarray:
    seg = np.full(len(part_of_vertex), SEGMENT_NONE, dtype=np.int64)
    if garment_type not in LIMB_CUTS:  # top: only its torso slides; dress's upper piece: nothing
        if garment_type == "top":
            seg[np.isin(part_of_vertex, [PARTS.index("torso"), PARTS.index("legs")])] = SEGMENT_TORSO
        return seg
    kind = LIMB_CUTS[garment_type][0]
    limb = PARTS.index("arms") if kind == "arm" else PARTS.index("legs")
    seg[(part_of_vertex == limb) & (side_of_vertex > 0)] = SEGMENT_LEFT
    seg[(part_of_vertex == limb) & (side_of_vertex < 0)] = SEGMENT_RIGHT
    if garment_type in ("tshirt", "shirt"):
        seg[np.isin(part_of_vertex, [PARTS.index("torso"), PARTS.index("legs")])] = SEGMENT_TORSO
    return seg


# ------------------------------------------------------------------------- skirt
def _skirt_grid_shape(target: int) -> tuple[int, int]:
    cols = max(16, 4 * int(round(np.sqrt(target * 2.2) / 4)))
    rows = max(4, int(round(target / cols)))
    return rows, cols


def skirt_vertices(body, shape, style: StyleParams, rows: int, cols: int) -> np.ndarray:
    """Skirt ring-grid vertices (rows * cols, 3) [m] for a style on the canonical body of a shape.

    Ring k lies at height y_k from the waist (k = 0) to the hem; its radius per angle is
    the hull of the body (torso + legs) between the waist and y_k, plus looseness plus
    ``width_profile * k / (rows - 1)``. Angle 0 faces +z; angles increase toward +x.
    """
    _, joints = body_joints(body, shape)
    y_waist = joints["spine1"][1] - WAIST_BELOW_SPINE1_M
    y_hip = 0.5 * (joints["left_hip"][1] + joints["right_hip"][1])
    y_knee = 0.5 * (joints["left_knee"][1] + joints["right_knee"][1])
    lo, hi = SKIRT_CUT
    y_hem = y_hip + (y_knee - y_hip) * (lo + (hi - lo) * style["length"])
    ring_y = y_waist + (y_hem - y_waist) * np.linspace(0.0, 1.0, rows)
    centre, radius, bins = skirt_hull(body, shape, ring_y)
    theta = 2 * np.pi * np.arange(cols) / cols - np.pi
    bin_centres = (np.arange(bins) + 0.5) / bins * 2 * np.pi - np.pi
    t = np.linspace(0.0, 1.0, rows)
    out = np.zeros((rows, cols, 3))
    for k in range(rows):
        r = np.interp(theta, bin_centres, radius[k], period=2 * np.pi)
        r = r + style["looseness"] + style["width_profile"] * t[k]
        out[k, :, 0] = centre[0] + r * np.sin(theta)
        out[k, :, 1] = ring_y[k]
        out[k, :, 2] = centre[2] + r * np.cos(theta)
    return out.reshape(-1, 3)


def skirt_hull(body, shape, ring_y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Hull of the hips and legs below the waist for skirt rings at heights ``ring_y`` (R,) [m]
    (ring 0 at the waist): (centre (3,) of the waist band [m], radius (R, bins) [m] per angle bin
    (bin b spans angles from -pi + 2 pi b / bins, angle 0 facing +z, pi/2 facing +x), bins)."""
    v, joints = body_joints(body, shape)
    part = np.asarray(body.vertex_parts)
    y_waist = joints["spine1"][1] - WAIST_BELOW_SPINE1_M
    rows = len(ring_y)
    # Dense body surface points (twice-subdivided torso/leg faces) for the hull.
    fmask = np.isin(part[body.faces], [PARTS.index("torso"), PARTS.index("legs")]).all(1)
    pts, tri = v, body.faces[fmask]
    for _ in range(2):
        pts, tri, _, _ = mesh_ops.midpoint_subdivide(pts, tri)
    pts = pts[np.unique(tri)]
    band = (np.abs(pts[:, 1] - y_waist) < 0.015)
    centre = pts[band].mean(0) if band.any() else np.array([0.0, y_waist, 0.0])
    rel = pts - centre
    ang = np.arctan2(rel[:, 0], rel[:, 2])  # 0 at +z, +pi/2 at +x
    rad = np.linalg.norm(rel[:, [0, 2]], axis=1)
    bins = 48
    b = np.floor((ang + np.pi) / (2 * np.pi) * bins).astype(int) % bins
    half_band = 0.5 * abs(ring_y[1] - ring_y[0]) + 0.01
    radius = np.zeros((rows, bins))
    for k, y in enumerate(ring_y):
        sel = (pts[:, 1] <= y_waist + 0.005) & (pts[:, 1] >= y - half_band)
        r = np.zeros(bins)
        np.maximum.at(r, b[sel], rad[sel])
        radius[k] = r
    radius = np.maximum.accumulate(radius, axis=0)  # the hull only grows from the waist down
    for k in range(rows):  # fill empty bins, then a circular smoothing
        r = radius[k]
        if (r > 0).any():
            good = np.nonzero(r > 0)[0]
            r = np.interp(np.arange(bins), good, r[good], period=bins)
        for _ in range(3):
            r = np.maximum(r, 0.25 * np.roll(r, 1) + 0.5 * r + 0.25 * np.roll(r, -1))
        radius[k] = r
    return centre, radius, bins


def _skirt_faces(rows: int, cols: int) -> np.ndarray:
    r, c = np.meshgrid(np.arange(rows - 1), np.arange(cols), indexing="ij")
    a = r * cols + c
    b = r * cols + (c + 1) % cols
    cc = (r + 1) * cols + c
    d = (r + 1) * cols + (c + 1) % cols
    # outward normals: angle increases toward +x from +z, rows go down
    return np.concatenate([np.stack([a, cc, b], -1).reshape(-1, 3), np.stack([b, cc, d], -1).reshape(-1, 3)])


def skirt_skinning_weights(body, points: np.ndarray, *, neighbours: int = SKIRT_SKINNING_NEIGHBOURS) -> np.ndarray:
    """Inverse-distance average of the weights of the K nearest torso/leg body vertices, (N, J)."""
    v, _ = body_joints(body, body.shape_default)
    mask = np.isin(body.vertex_parts, [PARTS.index("torso"), PARTS.index("legs")])
    idx = np.nonzero(mask)[0]
    d, nn = cKDTree(v[idx]).query(points, k=neighbours)
    w = 1.0 / np.maximum(d, 1e-6)
    w /= w.sum(1, keepdims=True)
    weights = np.einsum("nk,nkj->nj", w, body.skinning_weights[idx[nn]])
    return (weights / weights.sum(1, keepdims=True)).astype(np.float32)


# ------------------------------------------------------------------------- styles
#: Column grid of the style slide: (columns around the axis, samples along it).
SLIDE_GRID: tuple[int, int] = (240, 300)


def _angle_around(points: np.ndarray, u: np.ndarray, chain: list[np.ndarray]) -> np.ndarray:
    """Angle [rad] (N,) of points around a joint polyline at their bone-unit coordinates u,
    measured from the world forward axis (+z) projected off the local bone direction."""
    c = np.stack(chain)
    i = np.clip(np.floor(u).astype(int), 0, len(chain) - 2)
    d = c[i + 1] - c[i]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0]) - d[:, 2:3] * d
    ref /= np.maximum(np.linalg.norm(ref, axis=1, keepdims=True), 1e-9)
    radial = points - limb_point(u, chain)
    return np.arctan2(np.einsum("ij,ij->i", radial, np.cross(d, ref)), np.einsum("ij,ij->i", radial, ref))


def _slide(surface: np.ndarray, member: np.ndarray, u: np.ndarray, chain: list[np.ndarray], u_anchor: float,
           u_max: float, u_cut: float, *, length: float) -> tuple[np.ndarray, np.ndarray]:
    """Moves a segment's rows toward its anchor so the hem at u_max lands at u_cut, on the
    segment's own surface. Returns (new positions (V, 3) [m], new coordinates u (V,)).

    The segment (a tube around the joint polyline ``chain``; u in bone units, ``length``
    [m] per unit) is parameterized by (angle around the axis, u). Along every column of
    constant angle the rows between the anchor and the hem are spaced uniformly shorter
    *in arc length* (not in u): sliding by u alone piles rows up where the surface turns
    away from the axis (the lumbar curve above the buttocks: rows 0.1-0.8 mm apart,
    which later tore in the drape). Each moved vertex is put at its new (angle, u) on the
    piecewise-linear original surface, so rows never cross or collapse."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

    theta = _angle_around(surface, u, chain)
    radius = float(np.median(np.linalg.norm(surface - limb_point(u, chain), axis=1)[member > 0.5]))
    src = np.nonzero((member > 0.5) & (u >= u_anchor - 0.05))[0]
    plane_t, plane_u = [theta[src]], [u[src]]
    idx = [src]
    for sign in (1.0, -1.0):  # periodic in the angle: copies of the points near the seam
        near = sign * theta[src] > np.pi - 0.6
        plane_t.append(theta[src][near] - sign * 2.0 * np.pi)
        plane_u.append(u[src][near])
        idx.append(src[near])
    plane = np.stack([np.concatenate(plane_t) * radius, np.concatenate(plane_u) * length], 1)
    xyz = surface[np.concatenate(idx)]
    linear, nearest = LinearNDInterpolator(plane, xyz), NearestNDInterpolator(plane, xyz)

    def surface_at(t: np.ndarray, uu: np.ndarray) -> np.ndarray:
        q = np.stack([t.ravel() * radius, uu.ravel() * length], 1)
        out = linear(q)
        bad = ~np.isfinite(out).all(1)
        if bad.any():
            out[bad] = nearest(q[bad])
        return out

    nt, nu = SLIDE_GRID
    tg = np.linspace(-np.pi, np.pi, nt + 1)
    ug = np.linspace(u_anchor, u_max, nu + 1)
    grid = surface_at(*np.meshgrid(tg, ug, indexing="ij")).reshape(nt + 1, nu + 1, 3)
    arc = np.concatenate([np.zeros((nt + 1, 1)), np.cumsum(np.linalg.norm(np.diff(grid, axis=1), axis=2), 1)], 1)
    column_scale = np.array([np.interp(u_cut, ug, a) for a in arc]) / np.maximum(arc[:, -1], 1e-9)

    move = np.nonzero((member > 0) & (u > u_anchor))[0]
    ft = (theta[move] + np.pi) / (2.0 * np.pi) * nt
    j0 = np.clip(np.floor(ft).astype(int), 0, nt - 1)
    fu = np.clip((u[move] - u_anchor) / (u_max - u_anchor) * nu, 0.0, nu)
    k = np.clip(np.floor(fu).astype(int), 0, nu - 1)
    u_col = np.zeros(len(move))
    for j, weight in ((j0, 1.0 - (ft - j0)), (j0 + 1, ft - j0)):
        a = arc[j]  # (M, nu + 1) arc length along each vertex's column
        s = a[np.arange(len(move)), k] + (fu - k) * (a[np.arange(len(move)), k + 1] - a[np.arange(len(move)), k])
        s = s + np.maximum(u[move] - u_max, 0.0) * length  # hem vertices a little past u_max
        target = s * column_scale[j]
        kk = np.clip((a <= target[:, None]).sum(1) - 1, 0, nu - 1)
        lo, hi = a[np.arange(len(move)), kk], a[np.arange(len(move)), kk + 1]
        u_col += weight * (ug[kk] + (target - lo) / np.maximum(hi - lo, 1e-12) * (ug[1] - ug[0]))
    u_new = u.copy()
    u_new[move] = u[move] + member[move] * (u_col - u[move])
    out = surface.copy()
    # Vertices fully inside the segment go to their new place on its surface; the blend
    # zone (partial membership, e.g. the armpit) is only translated along the axis.
    inside = move[member[move] > 0.5]
    out[inside] = surface_at(theta[inside], u_new[inside])
    blend = move[member[move] <= 0.5]
    out[blend] += limb_point(u_new[blend], chain) - limb_point(u[blend], chain)
    return out, u_new


def apply_style(template: GarmentTemplate, style: StyleParams, body, *, shape=None) -> np.ndarray:
    """Garment vertices [m] (V, 3) of ``style`` on the canonical body of ``shape``
    (default neutral), with the template's (fixed) topology."""
    if style.garment_type != template.garment_type:
        raise ValueError(f"style is for {style.garment_type!r} but the template is a {template.garment_type!r}")
    shape = body.shape_default if shape is None else np.asarray(shape, dtype=np.float32)
    gt = template.garment_type
    if gt == "skirt":
        rows, cols = template.grid_shape
        return skirt_vertices(body, shape, style, rows, cols).astype(np.float32)
    if gt == "dress":

        return dress_vertices(template, style, body, shape)
    return styled_body_surface(gt, style, body, shape, template.faces, template.body_face, template.body_bary,
                               template.segment).astype(np.float32)


def profile_offset(style: StyleParams, s: np.ndarray) -> np.ndarray:
    """Seed 004's sleeve/leg width profile as an outward offset [m] at positions s (N,) along
    the limb (0 at the anchor, 1 at the longest cut): constant or tapering, widening past
    ``widen_at`` (see :mod:`simulate.garment.style`)."""
    s = np.asarray(s, np.float64)
    offset = style["looseness"] * (1.0 - style.get("taper") * s) + style.get("widen") * np.maximum(s - style.get("widen_at"), 0.0)
    return np.maximum(offset, CLOTH3D.min_offset_m)


def styled_body_surface(gt: str, style: StyleParams, body, shape, faces: np.ndarray, body_face: np.ndarray,
                        body_bary: np.ndarray, segment: np.ndarray) -> np.ndarray:
    """A body-topology garment of style ``style`` (V, 3) [m] on the canonical body of ``shape``:
    the embedded surface with hems and cuffs slid to their lengths, offset outward by the
    looseness and width profiles, kept outside the body."""
    bv, joints = body_joints(body, shape)
    surf = embedded_points(bv, body.faces, body_face, body_bary)
    extra = np.zeros(len(surf))

    def membership(mask: np.ndarray) -> np.ndarray:
        return np.clip(mesh_ops.smooth_vertex_values(mask.astype(np.float64)[:, None], faces, iterations=8)[:, 0], 0, 1)

    if gt in ("tshirt", "shirt", "top"):
        y_top = joints["spine2"][1]
        y_hip = 0.5 * (joints["left_hip"][1] + joints["right_hip"][1])
        height = y_top - y_hip
        anchor, lo, hi = TORSO_CUT
        u = (y_top - surf[:, 1]) / height
        member = membership(segment == SEGMENT_TORSO)
        spine = [joints["spine2"], 0.5 * (joints["left_hip"] + joints["right_hip"])]  # u = 1 at hip height
        surf, _ = _slide(surf, member, u, spine, anchor, hi, lo + (hi - lo) * style["length"],
                         length=float(np.linalg.norm(spine[1] - spine[0])))
    limbs = [] if gt not in LIMB_CUTS else [(SEGMENT_LEFT, 1), (SEGMENT_RIGHT, -1)]
    if limbs:
        kind, anchor, lo, hi = LIMB_CUTS[gt]
        u_cut = lo + (hi - lo) * style["sleeve_length" if kind == "arm" else "leg_length"]
        profiled = style.get("taper") > 0.0 or style.get("widen") > 0.0
    for seg_id, side in limbs:
        chain = [joints[n] for n in _chain(kind, side)]
        member = membership(segment == seg_id)
        u = limb_coordinate(surf, chain)
        surf, u_new = _slide(surf, member, u, chain, anchor, hi, u_cut,
                             length=float(np.mean([np.linalg.norm(b - a) for a, b in zip(chain[:-1], chain[1:])])))
        ramp = np.clip((u_new - anchor) / max(u_cut - anchor, 1e-9), 0.0, 1.0)
        extra += member * ramp * style.values.get("width_profile", 0.0)
        if profiled:
            position = np.clip((u_new - anchor) / (hi - anchor), 0.0, 1.0)
            extra += member * (profile_offset(style, position) - style["looseness"])
    edges, _ = mesh_ops.unique_edges(faces)
    edge = float(np.median(np.linalg.norm(surf[edges[:, 1]] - surf[edges[:, 0]], axis=1)))
    normals = mesh_ops.smooth_normals(surf, faces, iterations=max(10, int(np.ceil((OFFSET_NORMAL_RADIUS_M / edge) ** 2))))
    body_query = mesh_ops.ClosestPointQuery(bv, body.faces)
    offset = safe_offsets(surf, normals, style["looseness"] + extra, faces, body_query)
    verts = unfold_offset(surf + normals * offset[:, None], surf, faces)
    return relax_outside(verts, faces, body_query)


def unfold_offset(points: np.ndarray, surface: np.ndarray, faces: np.ndarray, *, rounds: int = 10) -> np.ndarray:
    """Smooths away the places where offsetting ``surface`` (V, 3) [m] to ``points`` folded
    or collapsed triangles: faces turned more than 60 degrees from their surface face or
    shrunk below UNFOLD_AREA_FRACTION of its area (offsets larger than a concavity's
    radius, e.g. a loose hem over the lumbar curve, cross each other there). Those faces'
    vertices and two rings around them are Laplacian-smoothed, repeatedly; boundary
    vertices (hems, cuffs) only along their boundary, so the openings do not pull in."""
    n_vert = len(points)
    adj = mesh_ops.vertex_adjacency(faces, n_vert)
    laplacian = mesh_ops.uniform_laplacian(faces, n_vert, boundary_aware=True)

    def area_normal(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
        a = np.linalg.norm(c, axis=1)
        return a, c / np.maximum(a, 1e-15)[:, None]

    a0, n0 = area_normal(surface)
    out = np.asarray(points, dtype=np.float64).copy()
    for _ in range(rounds):
        a, n = area_normal(out)
        bad = (np.einsum("ij,ij->i", n, n0) < 0.5) | (a < UNFOLD_AREA_FRACTION * a0)
        if not bad.any():
            break
        region = np.zeros(n_vert)
        region[faces[bad].ravel()] = 1.0
        for _ in range(2):
            region = np.maximum(region, (adj @ region > 0).astype(np.float64))
        free = (region > 0.5)[:, None]
        for _ in range(5):
            out += np.where(free, 0.5 * (laplacian @ out), 0.0)
    return out


def safe_offsets(surface: np.ndarray, normals: np.ndarray, offset: np.ndarray, faces: np.ndarray,
                 body_query: mesh_ops.ClosestPointQuery, *, rounds: int = 8) -> np.ndarray:
    """Per-vertex offsets [m] (V,) no larger than requested, shrunk where moving along
    the normal runs toward another part of the body (armpits, crotch, between the legs):
    there the offset point is closer to the body than SAFE_OFFSET_RATIO times the offset,
    so two facing surfaces (inner thighs) would cross each other beyond half their gap.
    The result is smoothed (never increased) so neighbouring rows stay evenly spaced."""
    d = np.asarray(offset, dtype=np.float64).copy()
    for _ in range(rounds):
        sd = body_query.query(surface + normals * d[:, None])[3]
        bad = sd < SAFE_OFFSET_RATIO * d
        if not bad.any():
            break
        d[bad] *= 0.6
        d = np.minimum(d, mesh_ops.smooth_vertex_values(d[:, None], faces, iterations=3)[:, 0])
    return d


def relax_outside(points: np.ndarray, faces: np.ndarray, body_query: mesh_ops.ClosestPointQuery, *,
                  rounds: int = 4) -> np.ndarray:
    """Pushes garment vertices out of the body (:func:`push_outside`), then relaxes the
    pushed places (and two rings around them) by Laplacian smoothing, repeatedly, so
    concave places (armpits, crotch) get no collapsed slivers."""
    adj = mesh_ops.vertex_adjacency(faces, len(points))
    out = np.asarray(points, dtype=np.float64)
    for _ in range(rounds):
        pushed = push_outside(out, body_query)
        moved = np.linalg.norm(pushed - out, axis=1) > 1e-7
        out = pushed
        if not moved.any():
            break
        region = moved.astype(np.float64)
        for _ in range(2):
            region = np.maximum(region, (adj @ region > 0).astype(np.float64))
        out = mesh_ops.smooth_vertex_values(out, faces, iterations=5, lam=0.5, fixed=region < 0.5)
    # No final push: it would collapse neighbours onto one crease point again; what the
    # smoothing left inside (millimetres, in creases) is resolved by the drape.
    return out


def push_outside(points: np.ndarray, body_query: mesh_ops.ClosestPointQuery, *,
                 clearance: float = PUSH_CLEARANCE_M) -> np.ndarray:
    """Moves points that are inside the body or closer than ``clearance`` [m] to the body
    surface point nearest them plus ``clearance`` along that face's normal (offsets in
    concave places such as armpits and the crotch otherwise cross the body)."""
    closest, face, _, sd = body_query.query(points)
    out = np.asarray(points, dtype=np.float64).copy()
    bad = sd < clearance
    if bad.any():
        out[bad] = closest[bad] + body_query.normals[face[bad]] * clearance
    return out


# ------------------------------------------------------------------------- builder
def subdivision_level_for(garment_type: str, body, resolution: int) -> int:
    """Subdivision level (0-2) whose vertex count is nearest ``resolution`` in log scale."""
    base_faces = _body_region(garment_type, body, 0)[1]
    v0 = len(np.unique(base_faces))
    e0 = len(mesh_ops.unique_edges(base_faces)[0])
    f0 = len(base_faces)
    counts = [v0, v0 + e0]
    counts.append(counts[1] + 2 * e0 + 3 * f0)  # V2 = V1 + E1, E1 = 2 E0 + 3 F0
    return int(np.argmin([abs(np.log(c / resolution)) for c in counts]))


def make_template(garment_type: str, body, *, resolution: int | None = None,
                  style: StyleParams | dict | str | None = None) -> GarmentTemplate:
    """Builds the template of a garment type on ``body``'s canonical body.

    Args:
        garment_type: one of :data:`GARMENT_TYPES`.
        body: a BodyModel (anny by default in the project).
        resolution: target vertex count (default :data:`DEFAULT_RESOLUTION`); body-topology
            garments use the nearest of subdivision levels 0-2 (see ``template.resolution``).
        style: style of the template's rest ``vertices`` (default: the type's defaults).
    Raises:
        ValueError for an unknown type, a non-positive resolution or a bad style.
    """
    from simulate.garment import uv as uv_mod

    check_garment_type(garment_type)
    if resolution is None:
        resolution = DEFAULT_RESOLUTION[garment_type]
    if int(resolution) != resolution or resolution < 64:
        raise ValueError(f"resolution must be an integer vertex count >= 64, got {resolution!r}")
    if not isinstance(style, StyleParams):
        style = StyleParams.parse(garment_type, style) if style is None or isinstance(style, str) \
            else StyleParams(garment_type, style)
    if garment_type in ("dress", "jumpsuit"):

        return make_sewn_template(garment_type, body, int(resolution), style)
    if garment_type == "skirt":
        rows, cols = _skirt_grid_shape(int(resolution))
        faces = _skirt_faces(rows, cols)
        nv = rows * cols
        segment = np.zeros(nv, dtype=np.int64)
        tpl = GarmentTemplate(
            garment_type=garment_type, vertices=np.zeros((nv, 3), np.float32), faces=faces,
            uv=np.zeros((nv, 2), np.float32), face_uv=np.zeros((len(faces), 3, 2), np.float32),
            vertex_panel=np.zeros(nv, np.int64), face_panel=np.zeros(len(faces), np.int64), panel_names=[],
            boundary_names=["waist", "hem"], boundary_loops=[], attachment=np.zeros(0, np.int64),
            skinning_weights=np.zeros((nv, body.joint_count), np.float32),
            body_vertex_index=np.full(nv, -1, np.int64), body_face=np.full(nv, -1, np.int64),
            body_bary=np.zeros((nv, 3), np.float32), segment=segment, grid_shape=(rows, cols),
            resolution=int(resolution), body_name=body.name, default_style=dict(style.values))
        tpl.vertices = apply_style(tpl, style, body)
        loops = mesh_ops.boundary_loops(faces)
        names, loops = _name_loops(garment_type, tpl.vertices, loops)
        tpl.boundary_names, tpl.boundary_loops = names, loops
        tpl.attachment = np.arange(2 * cols, dtype=np.int64)  # waistband: the top two rings
        tpl.skinning_weights = skirt_skinning_weights(body, tpl.vertices)
    else:
        level = subdivision_level_for(garment_type, body, int(resolution))
        surf, faces, body_face, body_bary, coarse_face, coarse_bary = _body_region(garment_type, body, level)
        bv, joints = body_joints(body, body.shape_default)
        corner = np.argmax(body_bary, axis=1)
        nearest_in_face = body.faces[body_face, corner]
        part = np.asarray(body.vertex_parts)[nearest_in_face]
        index = cKDTree(bv).query(surf)[1].astype(np.int64)
        weights = np.einsum("vk,vkj->vj", body_bary, body.skinning_weights[body.faces[body_face]])
        weights = (weights / weights.sum(1, keepdims=True)).astype(np.float32)
        segment = _segments(garment_type, part, np.sign(surf[:, 0]))
        tpl = GarmentTemplate(
            garment_type=garment_type, vertices=surf.astype(np.float32), faces=faces,
            uv=np.zeros((len(surf), 2), np.float32), face_uv=np.zeros((len(faces), 3, 2), np.float32),
            vertex_panel=np.zeros(len(surf), np.int64), face_panel=np.zeros(len(faces), np.int64),
            panel_names=[], boundary_names=[], boundary_loops=[], attachment=np.zeros(0, np.int64),
            skinning_weights=weights, body_vertex_index=index, body_face=body_face.astype(np.int64),
            body_bary=body_bary.astype(np.float32), segment=segment, grid_shape=(0, 0), resolution=level,
            body_name=body.name, default_style=dict(style.values))
        names, loops = _name_loops(garment_type, surf, mesh_ops.boundary_loops(faces))
        tpl.boundary_names, tpl.boundary_loops = names, loops
        if garment_type in ("pants", "shorts"):
            y_waist = joints["spine1"][1] - WAIST_BELOW_SPINE1_M
            tpl.attachment = np.nonzero(surf[:, 1] > y_waist - 0.02)[0].astype(np.int64)
        tpl.vertices = apply_style(tpl, style, body)
    if garment_type == "skirt":
        uv_mod.build_uv(tpl)
    else:
        # Charts of the level-0 body region, carried to finer levels by the subdivision's
        # barycentrics: the same pattern at every resolution.
        v0, f0 = _body_region(garment_type, body, 0)[:2]
        face_uv0, panel0, names = uv_mod.compute_uv(v0, f0, garment_type)
        face_uv = np.einsum("fkc,fcd->fkd", coarse_bary, face_uv0[coarse_face])
        uv_mod.assign_uv(tpl, face_uv, panel0[coarse_face], names)
    return tpl


def generate_garment(garment_type: str, style: StyleParams | dict | str | None, body, *, shape=None,
                     template=None, resolution: int | None = None):
    """Vertices [m] (V, 3) of a garment of one style on the canonical body of ``shape``.

    The topology is that of the type's template (fixed across styles): shorter lengths
    slide hem rows up along the body instead of deleting vertices.

    Args:
        garment_type: one of :data:`GARMENT_TYPES`.
        style: StyleParams, a {name: value} dict, a "name=value,..." string, or None.
        body: the BodyModel the template was built on.
        shape: body shape (S,) (default: the body's neutral shape).
        template: a GarmentTemplate of this type (default: built with ``resolution``).
    """
    if not isinstance(style, StyleParams):
        style = StyleParams.parse(garment_type, style) if isinstance(style, str) or style is None \
            else StyleParams(garment_type, style)
    if style.garment_type != garment_type:
        raise ValueError(f"style is for {style.garment_type!r} but garment_type is {garment_type!r}")
    if template is None:
        kwargs = {} if resolution is None else {"resolution": resolution}
        template = make_template(garment_type, body, **kwargs)
    elif template.garment_type != garment_type:
        raise ValueError(f"template is a {template.garment_type!r}, expected {garment_type!r}")
    return apply_style(template, style, body, shape=shape)


__all__ = ["GarmentTemplate", "make_template", "apply_style", "GARMENT_TYPES", "STYLE_SPECS", "DEFAULT_RESOLUTION",
           "BOUNDARY_NAMES", "embedded_points", "body_joints", "skirt_skinning_weights", "generate_garment"]


# -- Sewn garments: the dress and the jumpsuit ------------------------------------------------
#
# Dresses (top + skirt) and jumpsuits (top + trousers) sewn at the waist into one mesh
# (seed 004, Sec. 3.2: "a final step automatically sews them together").
#
# Jumpsuit: the top (neck, armholes) and the trousers (leg cuts) are cut out of the canonical
# body as one region, which the waist level set then splits into the upper and the lower
# piece (:func:`simulate.garment.mesh_ops.cut_by_field` on both sides of the same field, so both
# pieces' waist loops are the same cut points); the pieces are sewn along those loops with
# :func:`simulate.garment.mesh_ops.sew_loops`. The sewn mesh is body-topology (every vertex is
# embedded in a body triangle) and is styled like trousers (leg length, looseness, width profile).
#
# Dress: the upper piece is a sleeveless top cut at the waist; the skirt is a ring grid whose
# first ring is the top's waist loop (one column per loop vertex, at the loop vertices' angles
# around the waist), its other rings down to the sampled hem on the hull of hips and legs plus
# looseness plus flare; the skirt is sewn to the top along that ring. The upper piece's vertices
# come first in the mesh, then the skirt's rows below the seam.
#
# Both keep per-vertex ``piece`` (0 upper, 1 lower) and the ordered ``seam`` loop on the template.

#: Largest distance [m] between matched seam vertices: the loops are built to coincide.
SEAM_TOLERANCE_M = 1.0e-6
#: Share of the median edge length within which a vertex is snapped onto the jumpsuit's waist
#: cut (no sliver triangles along the seam), capped at ``CUT_SNAP_M``.
SEAM_SNAP_FRACTION = 0.3
#: Share of a dress's vertices (at the requested resolution) given to its upper piece.
DRESS_UPPER_SHARE = 0.5


def _waist_height(joints) -> float:

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

    bv, _ = body_joints(body, body.shape_default)
    corner = np.argmax(body_bary, axis=1)
    part = np.asarray(body.vertex_parts)[body.faces[body_face, corner]]
    index = cKDTree(bv).query(surf)[1].astype(np.int64)
    weights = np.einsum("vk,vkj->vj", body_bary, body.skinning_weights[body.faces[body_face]])
    weights = (weights / weights.sum(1, keepdims=True)).astype(np.float32)
    return index, weights, _segments(garment_type, part, np.sign(surf[:, 0]))


def _region_query(garment_type: str, body):

    bv, _ = body_joints(body, body.shape_default)
    f0 = np.asarray(body.faces, dtype=np.int64)
    region_index = np.nonzero(np.isin(np.asarray(body.vertex_parts)[f0], _allowed_parts(garment_type)).all(1))[0]
    return mesh_ops.ClosestPointQuery(bv, f0[region_index]), region_index


def make_sewn_template(garment_type: str, body, resolution: int, style: StyleParams):
    """The template of a dress or jumpsuit (see the module docstring); ``resolution`` is the
    target vertex count, ``style`` the style of its rest ``vertices``."""
    from simulate.garment import uv as uv_mod

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

    return _skirt_faces(rows, cols)


def dress_vertices(template, style: StyleParams, body, shape=None) -> np.ndarray:
    """Vertices (V, 3) [m] of a dress of ``style`` on the canonical body of ``shape`` (default
    neutral): the upper piece styled as a top cut at the waist; skirt ring k (k = 0 the seam) of
    column c at the height of seam vertex c moved toward the hem by k / (rows - 1), its radius
    around the waist centre the larger of the seam vertex's and the hull's (plus looseness),
    plus ``flare`` times the ring's depth below the seam over the longest skirt's."""

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
