"""Per-frame quality metrics that the dataset filters use (and evaluation reports):

- **distortion**: triangle area ratio against the rest garment (seed 001 D.6 drops a
  sample when any triangle shrinks by more than 75 % or grows by more than 100 %);
- **penetration**: signed distance of each garment vertex along the normal of its
  nearest body face; below -1 mm counts as a collision (HOOD-style metric). The nearest face
  comes from Warp's closest-point query on one mesh per frame; the side is checked against the
  pseudo-normal of the closest feature (``simulate.contact.closest.point_side``), since the
  nearest face's normal alone calls points inside off sharp edges and corners of the body
  surface (beside the head of the closed anny body, 38 mm outside read as 8 mm deep) and past
  the open cuts of a culled body. Body contact and ``BodyCollider.signed_distance`` measure the
  Euclidean distance instead (``simulate.contact.closest`` says which query serves what, and why);
- **self-intersection**: garment edges that pierce non-adjacent garment triangles;
- non-finite positions.

One :class:`QualityMeter` per garment template/body topology. It measures the frames of a
batch together (a few launches, one device round trip per metric): one Warp mesh per frame
slot, allocated once and refit for every later batch.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from simulate.contact.closest import closest_point_barycentric, face_points, point_side
from simulate.contact.crossing import as_vec3d, segment_hits_triangle

wp.set_module_options({"enable_backward": False})

#: Default collision depth [m]: signed distance below -1 mm is a collision.
COLLISION_DEPTH_M = 1e-3


@wp.kernel
def query_body_signed_distance(
    # Body: one mesh per frame
    mesh_ids: wp.array(dtype=wp.uint64),
    # Garment: frames packed one after another
    points: wp.array(dtype=wp.vec3),
    points_per_frame: int,
    max_distance: float,
    # Out:
    distance_out: wp.array(dtype=float),
    closest_out: wp.array(dtype=wp.vec3),
    normal_out: wp.array(dtype=wp.vec3),
):
    """Signed distance [m] of each point along the normal of its nearest body face (the one
    implementation of the collision metric, also used by learn.common.collision).

    The side is checked against the closest feature's pseudo-normal (``point_side``): where the
    nearest face's normal puts an outside point inside (a sharp corner of the surface, a point past
    an open cut) or an inside point outside, the distance is the Euclidean one to the closest
    point with the pseudo-normal's sign. ``normal_out`` is the nearest face's unit normal."""
    tid = wp.tid()
    mesh_id = mesh_ids[tid // points_per_frame]
    p = points[tid]
    query = wp.mesh_query_point_no_sign(mesh_id, p, max_distance)
    if query.result:
        zero = wp.vec3(0.0)
        a, b, c = face_points(mesh_id, query.face, zero)
        bary = closest_point_barycentric(p, a, b, c)
        closest = a * bary[0] + b * bary[1] + c * bary[2]
        normal = wp.normalize(wp.cross(b - a, c - a))
        along = wp.dot(p - closest, normal)
        side = point_side(mesh_id, zero, query.face, bary, p, closest)
        if along * side < 0.0:
            along = side * wp.length(p - closest)
        distance_out[tid] = along
        closest_out[tid] = closest
        normal_out[tid] = normal
    else:
        # farther than max_distance from the body: certainly not colliding
        distance_out[tid] = max_distance
        closest_out[tid] = p
        normal_out[tid] = wp.vec3(0.0, 0.0, 0.0)


@wp.func
def edge_triangle_crossing(mesh_id: wp.uint64, i0: int, i1: int, face: int) -> bool:
    """Whether garment edge (i0, i1) crosses garment triangle ``face`` that it does not touch."""
    mesh = wp.mesh_get(mesh_id)
    j0 = mesh.indices[face * 3 + 0]
    j1 = mesh.indices[face * 3 + 1]
    j2 = mesh.indices[face * 3 + 2]
    if j0 == i0 or j0 == i1 or j1 == i0 or j1 == i1 or j2 == i0 or j2 == i1:
        return False
    return segment_hits_triangle(mesh.points[i0], mesh.points[i1], mesh.points[j0], mesh.points[j1], mesh.points[j2])


@wp.kernel
def count_edge_triangle_intersections(
    # Garment: one mesh per frame, all of one topology
    mesh_ids: wp.array(dtype=wp.uint64),
    edges: wp.array(dtype=wp.vec2i),
    edge_count: int,
    # Out: crossings per frame (zeroed by the caller)
    hits_out: wp.array(dtype=int),
):
    """Counts (edge, triangle) crossings among non-adjacent elements, frames x edges threads."""
    tid = wp.tid()
    frame = tid // edge_count
    e = tid - frame * edge_count
    mesh_id = mesh_ids[frame]
    mesh = wp.mesh_get(mesh_id)
    i0 = edges[e][0]
    i1 = edges[e][1]
    p = mesh.points[i0]
    q = mesh.points[i1]
    query = wp.mesh_query_aabb(mesh_id, wp.min(p, q), wp.max(p, q))
    face = int(0)
    count = int(0)
    while wp.mesh_query_aabb_next(query, face):
        if edge_triangle_crossing(mesh_id, i0, i1, face):
            count += 1
    if count > 0:
        wp.atomic_add(hits_out, frame, count)


@wp.kernel
def list_edge_triangle_intersections(
    mesh_ids: wp.array(dtype=wp.uint64),
    edges: wp.array(dtype=wp.vec2i),
    edge_count: int,
    frames: wp.array(dtype=wp.int32),
    capacity: int,
    # Out:
    counter: wp.array(dtype=wp.int32),
    events_out: wp.array(dtype=wp.vec3i),
):
    """The crossings themselves, (frame, edge, face) per row in any order, for the frames listed in
    ``frames`` (threads: len(frames) x edges); rows past ``capacity`` are counted, not written."""
    tid = wp.tid()
    k = tid // edge_count
    e = tid - k * edge_count
    frame = frames[k]
    mesh_id = mesh_ids[frame]
    mesh = wp.mesh_get(mesh_id)
    i0 = edges[e][0]
    i1 = edges[e][1]
    p = mesh.points[i0]
    q = mesh.points[i1]
    query = wp.mesh_query_aabb(mesh_id, wp.min(p, q), wp.max(p, q))
    face = int(0)
    while wp.mesh_query_aabb_next(query, face):
        if edge_triangle_crossing(mesh_id, i0, i1, face):
            slot = wp.atomic_add(counter, 0, 1)
            if slot < capacity:
                events_out[slot] = wp.vec3i(frame, e, face)


def intersection_contours(events: np.ndarray, edge_faces: np.ndarray) -> int:
    """Number of intersection contours among (edge, face) crossings of one frame.

    Where the garment passes through itself, the triangles of the two sheets intersect pairwise
    along a chain of segments (a contour: a closed loop, or a curve from boundary to boundary);
    each segment is the intersection of one triangle pair (f, g) and ends at crossings of an edge
    of f through g or of an edge of g through f. Crossings that end segments of the same triangle
    pair belong to one contour; the contours are the connected components.

    Args:
        events: (K, 2) int (edge index, face index) of the crossings.
        edge_faces: (E, 2) int, the faces beside each edge (-1 where there is one).
    Returns:
        the number of contours (0 when there is no crossing).
    """
    ev = np.asarray(events, np.int64).reshape(-1, 2)
    if not len(ev):
        return 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    owner = np.asarray(edge_faces, np.int64)[ev[:, 0]]  # (K, 2) faces beside each crossing edge
    base = max(int(ev[:, 1].max()), int(owner.max())) + 1
    rows, keys = [], []
    for side in range(2):  # the crossing ends a segment of the pair (face beside the edge, pierced face)
        f = owner[:, side]
        ok = f >= 0
        rows.append(np.nonzero(ok)[0])
        keys.append(np.minimum(f[ok], ev[ok, 1]) * base + np.maximum(f[ok], ev[ok, 1]))
    rows = np.concatenate(rows)
    keys = np.concatenate(keys)
    _, pair = np.unique(keys, return_inverse=True)
    k = len(ev)
    graph = coo_matrix((np.ones(len(rows)), (rows, k + pair)), shape=(k + pair.max() + 1, k + pair.max() + 1))
    _, label = connected_components(graph, directed=False)
    return int(len(np.unique(label[:k])))


def edge_face_table(faces: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, 2) int64 faces beside each edge of ``edges`` ((E, 2) sorted pairs), -1 where one."""
    f = np.asarray(faces, np.int64)
    n = int(f.max()) + 1
    corner = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    key = np.sort(corner, axis=1) @ np.array([n, 1])
    face = np.tile(np.arange(len(f)), 3)
    order = np.argsort(key, kind="stable")
    key, face = key[order], face[order]
    ekey = np.asarray(edges, np.int64) @ np.array([n, 1])
    first = np.searchsorted(key, ekey, side="left")
    last = np.searchsorted(key, ekey, side="right")
    out = np.full((len(ekey), 2), -1, np.int64)
    out[:, 0] = face[first]
    two = last - first > 1
    out[two, 1] = face[first[two] + 1]
    return out



@wp.kernel
def triangle_area_ratios(
    # Garment: frames packed one after another
    points: wp.array(dtype=wp.vec3),
    points_per_frame: int,
    faces: wp.array(dtype=wp.int32),
    face_count: int,
    # Rest areas [m^2] per frame, packed like the output
    rest_areas: wp.array(dtype=wp.float64),
    # Out:
    ratio_out: wp.array(dtype=wp.float64),
):
    """Area ratio of each triangle against its rest area, in float64 like :func:`triangle_areas`,
    frames x faces threads."""
    tid = wp.tid()
    frame = tid // face_count
    f = tid - frame * face_count
    base = frame * points_per_frame
    a = as_vec3d(points[base + faces[3 * f + 0]])
    b = as_vec3d(points[base + faces[3 * f + 1]])
    c = as_vec3d(points[base + faces[3 * f + 2]])
    n = wp.cross(b - a, c - a)
    area = wp.float64(0.5) * wp.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    ratio_out[tid] = area / wp.max(rest_areas[tid], wp.float64(1.0e-20))


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Triangle areas [m^2], (..., V, 3) x (F, 3) -> (..., F)."""
    tri = np.asarray(vertices)[..., faces, :]
    return 0.5 * np.linalg.norm(np.cross(tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]), axis=-1)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges (E, 2) of a triangle mesh."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


class MeshSlots:
    """Warp meshes of one topology, one per frame of a batch: slot ``i`` holds frame ``i``.

    A slot's BVH is built from the first geometry it holds and refit for every later one: a tree
    built over all-zero points keeps a meaningless topology whose refit bounds all overlap, and
    every query turns into a brute-force scan (measured 75 ms per frame on an H200 for a
    7k-vertex shirt). Slots are added as batches grow and kept for the next batches.
    """

    def __init__(self, faces: np.ndarray, vertex_count: int, device) -> None:
        self.device = device
        self.vertex_count = int(vertex_count)
        self._indices = wp.array(np.asarray(faces, np.int32).ravel(), dtype=wp.int32, device=device)
        self._points: list[wp.array] = []
        self._meshes: list[wp.Mesh] = []
        self._ids: wp.array | None = None

    def load(self, packed: wp.array, count: int) -> wp.array:
        """Copies ``count`` frames of packed points (count * V,) into the first ``count`` slots
        and refits them; returns their mesh ids, (count,) uint64."""
        v = self.vertex_count
        for i in range(count):
            if i < len(self._meshes):
                wp.copy(self._points[i], packed, src_offset=i * v, count=v)
                self._meshes[i].refit()
            else:
                points = wp.empty(v, dtype=wp.vec3, device=self.device)
                wp.copy(points, packed, src_offset=i * v, count=v)
                self._points.append(points)
                self._meshes.append(wp.Mesh(points, self._indices))
                self._ids = None
        return self.load_ids(count)

    def load_ids(self, count: int) -> wp.array:
        """Mesh ids of the first ``count`` slots as they are, (count,) uint64."""
        if self._ids is None:
            self._ids = wp.array(np.array([m.id for m in self._meshes], dtype=np.uint64), dtype=wp.uint64,
                                 device=self.device)
        return self._ids[:count]


class QualityMeter:
    """Computes the frame metrics for one garment topology against one body topology, for one
    frame (:meth:`measure`) or for a batch of frames in a few launches and one round trip per
    metric (:meth:`measure_batch`, what generate-dataset uses: the frames that finish together).

    Args:
        garment_faces: (F, 3) garment triangles.
        rest_vertices: (V, 3) rest garment [m] (area ratios are taken against it).
        body_faces: (Fb, 3) body triangles (the culled set the garment can touch).
        body_vertex_count: Vb, vertices of the body meshes passed in.
        device: Warp device.
        max_distance: [m] garment vertices farther than this from the body count as this far.
        body_face_groups, garment_part: primary collision bodies (``simulate.body.collision_parts``):
            per part the rows of ``body_faces`` in its mesh, and the part of each garment vertex
            (V,); each vertex's signed distance is then to its own part, as the simulation's
            contact sees it. None: to all of ``body_faces``.
    """

    def __init__(self, garment_faces: np.ndarray, rest_vertices: np.ndarray, body_faces: np.ndarray, body_vertex_count: int,
                 *, device: str = "cpu", max_distance: float = 0.5, body_face_groups: list[np.ndarray] | None = None,
                 garment_part: np.ndarray | None = None) -> None:
        self.device = device
        self.faces = np.asarray(garment_faces, dtype=np.int32)
        self.rest_areas = triangle_areas(rest_vertices, self.faces)
        self.max_distance = max_distance
        self.vertex_count = len(rest_vertices)
        self._body_vertex_count = int(body_vertex_count)
        self._faces = wp.array(self.faces.ravel(), dtype=wp.int32, device=device)
        edges = unique_edges(self.faces)
        self._edges = wp.array(edges.astype(np.int32), dtype=wp.vec2i, device=device)
        self._edge_faces = edge_face_table(self.faces, edges)
        self._garments = MeshSlots(self.faces, self.vertex_count, device)
        self._bodies = MeshSlots(np.asarray(body_faces, np.int32), self._body_vertex_count, device)
        self._buffers: dict[str, wp.array] = {}
        self._parts: list[tuple[np.ndarray, MeshSlots]] = []
        if (body_face_groups is None) != (garment_part is None):
            raise ValueError("body_face_groups and garment_part go together (both or neither)")
        if body_face_groups is not None:
            part = np.asarray(garment_part)
            if part.shape != (self.vertex_count,) or part.min() < 0 or part.max() >= len(body_face_groups):
                raise ValueError(f"garment_part must be ({self.vertex_count},) indices into body_face_groups "
                                 f"({len(body_face_groups)} groups) (got shape {part.shape})")
            bf = np.asarray(body_faces, np.int32)
            for g, rows in enumerate(body_face_groups):
                members = np.nonzero(part == g)[0]
                if len(members):
                    self._parts.append((members, MeshSlots(bf[np.asarray(rows)], self._body_vertex_count, device)))

    def _buffer(self, name: str, size: int, dtype) -> wp.array:
        """A device array of at least ``size`` elements, reused across batches; returns its first ``size``."""
        buf = self._buffers.get(name)
        if buf is None or buf.shape[0] < size:
            buf = wp.empty(max(size, 2 * (0 if buf is None else buf.shape[0])), dtype=dtype, device=self.device)
            self._buffers[name] = buf
        return buf[:size]

    def _upload(self, name: str, array: np.ndarray, dtype) -> wp.array:
        flat = np.ascontiguousarray(array)
        out = self._buffer(name, len(flat), dtype)
        out.assign(flat)
        return out

    def _garment_points(self, garment_vertices: np.ndarray) -> tuple[wp.array, int]:
        x = np.asarray(garment_vertices, np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.vertex_count, 3):
            raise ValueError(f"garment_vertices must have shape (frames, {self.vertex_count}, 3) (got {x.shape})")
        return self._upload("garment", x.reshape(-1, 3), wp.vec3), len(x)

    def signed_distances(self, garment_vertices: np.ndarray, body_vertices: np.ndarray) -> np.ndarray:
        """Per-vertex signed distance [m] along the nearest body face normal: (n, V, 3) garments
        against (n, Vb, 3) bodies -> (n, V)."""
        if self._parts:
            x = np.asarray(garment_vertices, np.float32)
            if x.ndim != 3 or x.shape[1:] != (self.vertex_count, 3):
                raise ValueError(f"garment_vertices must have shape (frames, {self.vertex_count}, 3) (got {x.shape})")
            body = np.asarray(body_vertices, np.float32)
            if body.shape != (len(x), self._body_vertex_count, 3):
                raise ValueError(f"body_vertices must have shape ({len(x)}, {self._body_vertex_count}, 3), one body per "
                                 f"garment frame (got {body.shape})")
            return self._part_signed_distances(x, body)
        points, n = self._garment_points(garment_vertices)
        return self._signed_distances(points, n, body_vertices)

    def _signed_distances(self, points: wp.array, n: int, body_vertices: np.ndarray) -> np.ndarray:
        distance = self._launch_signed_distances(points, n, self._upload_bodies(body_vertices, n))
        return distance.numpy().reshape(n, self.vertex_count)

    def _upload_bodies(self, body_vertices: np.ndarray, n: int) -> wp.array:
        """Bodies (n, Vb, 3) [m] on the device as (n * Vb,) vec3."""
        body = np.asarray(body_vertices, np.float32)
        if body.shape != (n, self._body_vertex_count, 3):
            raise ValueError(f"body_vertices must have shape ({n}, {self._body_vertex_count}, 3), one body per "
                             f"garment frame (got {body.shape})")
        return self._upload("body", body.reshape(-1, 3), wp.vec3)

    def _launch_signed_distances(self, points: wp.array, n: int, bodies: wp.array) -> wp.array:
        """Queues the signed-distance queries against ``bodies`` (:meth:`_upload_bodies`); returns
        the (n * V,) device array they fill."""
        ids = self._bodies.load(bodies, n)
        v = self.vertex_count
        distance = self._buffer("distance", n * v, float)
        closest = self._buffer("closest", n * v, wp.vec3)
        normal = self._buffer("normal", n * v, wp.vec3)
        wp.launch(query_body_signed_distance, dim=n * v, device=self.device,
                  inputs=[ids, points, v, self.max_distance], outputs=[distance, closest, normal])
        return distance

    def _part_signed_distances(self, x: np.ndarray, body: np.ndarray) -> np.ndarray:
        """Signed distances (n, V) [m] of garments (n, V, 3) to their vertices' own parts of bodies (n, Vb, 3)."""
        n = len(x)
        bodies, points = self._upload_bodies(body, n), self._upload_part_points(x)
        return self._read_part_distances(self._launch_part_signed_distances(bodies, points, n), n)

    def _upload_part_points(self, x: np.ndarray) -> list[wp.array]:
        """Each part's garment points (n * k,) on the device."""
        return [self._upload(f"part_points_{g}", np.asarray(x[:, members], np.float32).reshape(-1, 3), wp.vec3)
                for g, (members, _) in enumerate(self._parts)]

    def _launch_part_signed_distances(self, bodies: wp.array, points: list[wp.array], n: int) -> list[wp.array]:
        """Queues every part's queries (``bodies`` from :meth:`_upload_bodies`, ``points`` from
        :meth:`_upload_part_points`); returns each part's (n * k,) distances."""
        distances = []
        for g, ((members, slots), pts) in enumerate(zip(self._parts, points)):
            ids = slots.load(bodies, n)
            k = len(members)
            distance = self._buffer(f"part_distance_{g}", n * k, float)
            closest = self._buffer(f"part_closest_{g}", n * k, wp.vec3)
            normal = self._buffer(f"part_normal_{g}", n * k, wp.vec3)
            wp.launch(query_body_signed_distance, dim=n * k, device=self.device,
                      inputs=[ids, pts, k, self.max_distance], outputs=[distance, closest, normal])
            distances.append(distance)
        return distances

    def _read_part_distances(self, distances: list[wp.array], n: int) -> np.ndarray:
        out = np.empty((n, self.vertex_count), np.float32)
        for (members, _), distance in zip(self._parts, distances):
            out[:, members] = distance.numpy().reshape(n, len(members))
        return out

    def self_intersection_counts(self, garment_vertices: np.ndarray) -> np.ndarray:
        """(edge, triangle) piercings among non-adjacent garment elements per frame: (n, V, 3) -> (n,)."""
        points, n = self._garment_points(garment_vertices)
        return self._self_intersection_counts(points, n)

    def _self_intersection_counts(self, points: wp.array, n: int) -> np.ndarray:
        return self._launch_self_intersection_counts(points, n).numpy().astype(np.int64)

    def _launch_self_intersection_counts(self, points: wp.array, n: int) -> wp.array:
        """Queues the edge-triangle tests; returns the (n,) device array of counts they fill."""
        ids = self._garments.load(points, n)
        hits = self._buffer("hits", n, int)
        hits.zero_()
        e = self._edges.shape[0]
        wp.launch(count_edge_triangle_intersections, dim=n * e, device=self.device,
                  inputs=[ids, self._edges, e], outputs=[hits])
        return hits

    def _contours(self, ids: wp.array, frames: np.ndarray, counts: np.ndarray) -> np.ndarray:
        """Intersection contours of the listed frames (slots of ``ids`` already loaded), whose
        crossing counts are ``counts``: (len(frames),) int64."""
        out = np.zeros(len(frames), np.int64)
        if not len(frames):
            return out
        capacity = int(counts.sum())
        events = self._buffer("events", capacity, wp.vec3i)
        counter = wp.zeros(1, dtype=wp.int32, device=self.device)
        e = self._edges.shape[0]
        wp.launch(list_edge_triangle_intersections, dim=len(frames) * e, device=self.device,
                  inputs=[ids, self._edges, e, wp.array(np.asarray(frames, np.int32), dtype=wp.int32, device=self.device),
                          capacity], outputs=[counter, events])
        rows = events.numpy()[:min(int(counter.numpy()[0]), capacity)]
        for j, f in enumerate(frames):
            out[j] = intersection_contours(rows[rows[:, 0] == f][:, 1:], self._edge_faces)
        return out

    def self_intersection_contours(self, garment_vertices: np.ndarray) -> np.ndarray:
        """Intersection contours per frame (:func:`intersection_contours`): (n, V, 3) -> (n,)."""
        points, n = self._garment_points(garment_vertices)
        counts = self._self_intersection_counts(points, n)
        ids = self._garments.load_ids(n)
        hit = np.nonzero(counts > 0)[0]
        out = np.zeros(n, np.int64)
        out[hit] = self._contours(ids, hit, counts[hit])
        return out

    def area_ratios(self, garment_vertices: np.ndarray, rest_areas: np.ndarray | None = None) -> np.ndarray:
        """Triangle area ratios against the rest areas (F,) or per frame (n, F): (n, V, 3) -> (n, F)."""
        points, n = self._garment_points(garment_vertices)
        return self._area_ratios(points, n, rest_areas)

    def _area_ratios(self, points: wp.array, n: int, rest_areas: np.ndarray | None) -> np.ndarray:
        ratio = self._launch_area_ratios(points, n, self._upload_rest_areas(rest_areas, n))
        return ratio.numpy().reshape(n, len(self.faces))

    def _upload_rest_areas(self, rest_areas: np.ndarray | None, n: int) -> wp.array:
        """Rest areas (F,) or (n, F) [m^2] (None: the constructor's) on the device as (n * F,)."""
        rest = np.asarray(self.rest_areas if rest_areas is None else rest_areas, np.float64)
        return self._upload("rest_areas", np.broadcast_to(rest, (n, len(self.faces))).reshape(-1), wp.float64)

    def _launch_area_ratios(self, points: wp.array, n: int, rest_areas: wp.array) -> wp.array:
        """Queues the area ratios against ``rest_areas`` (:meth:`_upload_rest_areas`); returns the
        (n * F,) device array they fill."""
        f = len(self.faces)
        ratio = self._buffer("ratio", n * f, wp.float64)
        wp.launch(triangle_area_ratios, dim=n * f, device=self.device,
                  inputs=[points, self.vertex_count, self._faces, f, rest_areas], outputs=[ratio])
        return ratio

    def signed_distance(self, garment_vertices: np.ndarray, body_vertices: np.ndarray) -> np.ndarray:
        """Per-vertex signed distance [m] of one frame, (V, 3) against (Vb, 3) -> (V,)."""
        body = np.asarray(body_vertices, np.float32)
        if body.shape != (self._body_vertex_count, 3):
            raise ValueError(f"body_vertices must have shape ({self._body_vertex_count}, 3) (got {body.shape})")
        return self.signed_distances(np.asarray(garment_vertices)[None], body[None])[0]

    def self_intersections(self, garment_vertices: np.ndarray) -> int:
        """Number of (edge, triangle) piercings among non-adjacent garment elements of one frame."""
        return int(self.self_intersection_counts(np.asarray(garment_vertices)[None])[0])

    def measure(self, garment_vertices: np.ndarray, body_vertices: np.ndarray, *, collision_depth: float = COLLISION_DEPTH_M,
                self_intersection: bool = True, rest_areas: np.ndarray | None = None,
                area_bounds: tuple[float, float] = (0.25, 2.0)) -> dict[str, float]:
        """All metrics of one frame: (V, 3) garment, (Vb, 3) body; see :meth:`measure_batch`.

        ``rest_areas`` (F,) [m^2] replaces the constructor's rest areas (e.g. the rest
        geometry of this garment's style when styles share one topology).
        """
        body = np.asarray(body_vertices, np.float32)
        if body.shape != (self._body_vertex_count, 3):
            raise ValueError(f"body_vertices must have shape ({self._body_vertex_count}, 3) (got {body.shape})")
        rest = None if rest_areas is None else np.asarray(rest_areas)[None]
        return self.measure_batch(np.asarray(garment_vertices)[None], body[None], collision_depth=collision_depth,
                                  self_intersection=self_intersection, rest_areas=rest, area_bounds=area_bounds)[0]

    def measure_batch(self, garment_vertices: np.ndarray, body_vertices: np.ndarray, *,
                      collision_depth: float = COLLISION_DEPTH_M, self_intersection: bool = True,
                      rest_areas: np.ndarray | None = None,
                      area_bounds: tuple[float, float] = (0.25, 2.0)) -> list[dict[str, float]]:
        """All metrics of n frames at once: garments (n, V, 3) [m] on bodies (n, Vb, 3) [m].

        ``rest_areas``: (F,) or (n, F) [m^2], replacing the constructor's rest areas (e.g. the rest
        geometry of each frame's style when styles share one topology).

        Returns:
            one dict per frame, with ``finite`` (1/0), ``area_ratio_min``, ``area_ratio_max``,
            ``distorted_fraction`` (share of triangles whose area ratio is outside ``area_bounds``),
            ``penetration_fraction`` (share of vertices deeper than ``collision_depth``),
            ``penetration_max_m`` (deepest vertex, >= 0), ``off_body_fraction`` (share of vertices
            at least ``max_distance`` from their body: a garment that slid or fell off),
            ``self_intersections`` (garment edges
            crossing garment triangles they do not touch, -1 if skipped) and
            ``self_intersection_contours`` (the closed or boundary-to-boundary curves those
            crossings lie on, :func:`intersection_contours`; -1 if skipped). A frame with a non-finite coordinate gets ``finite`` 0 and NaN elsewhere;
            it does not reach the device, so the other frames' metrics are those they would have alone.
        """
        x = np.asarray(garment_vertices, np.float64)
        if x.ndim != 3 or x.shape[1:] != (self.vertex_count, 3):
            raise ValueError(f"garment_vertices must have shape (frames, {self.vertex_count}, 3) (got {x.shape})")
        n = len(x)
        body = np.asarray(body_vertices, np.float32)
        if body.shape != (n, self._body_vertex_count, 3):
            raise ValueError(f"body_vertices must have shape ({n}, {self._body_vertex_count}, 3), one body per "
                             f"garment frame (got {body.shape})")
        rest = np.asarray(self.rest_areas if rest_areas is None else rest_areas, np.float64)
        if rest.shape not in ((len(self.faces),), (n, len(self.faces))):
            raise ValueError(f"rest_areas must have shape ({len(self.faces)},) or ({n}, {len(self.faces)}) (got {rest.shape})")
        rest = np.broadcast_to(rest, (n, len(self.faces)))
        finite = np.isfinite(x).all(axis=(1, 2))
        nan = float("nan")
        out = [{"finite": 0.0, "area_ratio_min": nan, "area_ratio_max": nan, "distorted_fraction": nan,
                "penetration_fraction": nan, "penetration_max_m": nan, "off_body_fraction": nan,
                "self_intersections": -1.0,
                "self_intersection_contours": -1.0} for _ in range(n)]
        good = np.nonzero(finite)[0]
        if len(good) == 0:
            return out
        # every input goes to the device first, then every metric is queued, then the results come
        # back: one wait for the device, not one per metric or per upload (the dataset driver
        # measures while a simulator frame runs, which each wait queues behind; a copy from host
        # memory can wait for the work queued before it)
        points, m = self._garment_points(x[good])
        rest_d = self._upload_rest_areas(rest[good], m)
        bodies = self._upload_bodies(body[good], m)
        part_points = self._upload_part_points(x[good]) if self._parts else None
        ratio_d = self._launch_area_ratios(points, m, rest_d)
        if self._parts:
            part_d = self._launch_part_signed_distances(bodies, part_points, m)
        else:
            d_d = self._launch_signed_distances(points, m, bodies)
        hits_d = self._launch_self_intersection_counts(points, m) if self_intersection else None
        ratio = ratio_d.numpy().reshape(m, len(self.faces))
        d = self._read_part_distances(part_d, m) if self._parts else d_d.numpy().reshape(m, self.vertex_count)
        hits = hits_d.numpy().astype(np.int64) if hits_d is not None else np.full(m, -1)
        contours = np.full(m, -1, np.int64)
        if hits_d is not None:
            contours[:] = 0
            hit = np.nonzero(hits > 0)[0]
            if len(hit):  # the meshes of this batch are still in their slots
                contours[hit] = self._contours(self._garments.load_ids(m), hit, hits[hit])
        distorted = ((ratio < area_bounds[0]) | (ratio > area_bounds[1])).mean(axis=1)
        deep = (d < -collision_depth).mean(axis=1)
        deepest = np.maximum(0.0, -d.min(axis=1).astype(np.float64))
        off_body = (d >= self.max_distance).mean(axis=1)
        for j, i in enumerate(good):
            out[i] = {
                "finite": 1.0,
                "area_ratio_min": float(ratio[j].min()),
                "area_ratio_max": float(ratio[j].max()),
                "distorted_fraction": float(distorted[j]),
                "penetration_fraction": float(deep[j]),
                "penetration_max_m": float(deepest[j]),
                "off_body_fraction": float(off_body[j]),
                "self_intersections": float(hits[j]),
                "self_intersection_contours": float(contours[j]),
            }
        return out
