"""Reference solver: the static equilibrium of one world of a :class:`ClothModel`, converged to a
stated force residual, on the CPU in float64.

It minimizes exactly the energy the production solvers (XPBD, mass-spring) integrate, read from the
finalized model (so it always matches what they solve):

* per triangle ``t`` with corner weights ``a, b`` from ``tri_dm_inv`` (``f1 = sum_k a_k x_k``,
  ``f2 = sum_k b_k x_k``, as ``common_kernels.triangle_coefficients``) and ``c = tri_compliance[t]``
  (1/(Y A), 1/(Y A), 1/(G A)) [1/N]:
  ``E = (|f1| - 1)^2 / (2 c0) + (|f2| - 1)^2 / (2 c1) + (f1 . f2)^2 / (2 c2)``;
* per bending stencil ``b`` (opposite 0, opposite 1, edge 0, edge 1) with the signed dihedral angle
  ``theta`` of ``common_kernels.bending_angle_grad``:
  ``E = (theta - bend_rest_angle[b])^2 / (2 bend_compliance[b])``;
* gravity ``-sum_i m_i g . x_i`` (``model.gravity``, lumped masses ``model.particle_mass``); pinned
  particles (inverse mass 0) stay at their start positions;
* soft attachments (when the model has them): ``1/2 k |x - target|^2`` per attached particle;
* optionally a body: a one-sided quadratic penalty ``1/2 k_c min(0, gap)^2`` on each particle's
  contact plane (closest body point lifted by the contact distance = collider thickness + particle
  radius along the outward normal, as ``contact.kernels.detect_body_contacts``), with the planes
  found again at every Newton iteration in float64, and, with ``friction="stick"``, tangential
  springs holding the particles in contact at the start at their start positions.

Method: Newton's method on the free particles with a line search on the true energy; convergence
is judged by the true gradient (max over free particles of |dE/dx_i| <= tol_force).

* Hessians: the exact one, used where it is positive definite (quadratic convergence): per
  triangle analytic, per bending stencil Gauss-Newton plus (theta - rest) hess theta with hess theta
  by forward differences of the analytic grad theta; and a projected one, positive semi-definite by
  construction, so that its Newton direction always descends: per triangle the exact 6x6 Hessian in
  (f1, f2) with negative eigenvalues clamped to 0 (this keeps (1 - 1/|f|)(I - n n^T) where
  stretched and drops it where compressed), bending by Gauss-Newton (grad theta grad theta^T / c).
  Contact and stick springs are quadratic in the plane (k_c n n^T, k_c (I - n0 n0^T)).
* Linear solves: the projected Hessian is factored with SuperLU (``scipy.sparse.linalg.splu``,
  symmetric mode, minimum-degree ordering); that factorization preconditions conjugate gradients on
  the exact Hessian, and where they meet negative curvature (buckled, compressed cloth, far from a
  minimum) the projected Newton step is taken instead.
* Contact active set: the one-sided penalty is modelled on the particles the step presses (solved
  again while that set changes), so a Newton step lands new contacts on their planes instead of
  being cut back by the line search.
* Line search: Armijo on the energy (energy changes within float64 rounding count as decrease),
  with secant steps back where a step overshoots the minimum along the line.

Cost: one sparse factorization per Newton iteration (0.5 s for the 7k-vertex t-shirt, 1.3 s for a
10k-vertex sheet on one CPU core) plus numpy element work of similar cost.  Starts near
equilibrium converge in a few iterations; drapes far from it (folds, sliding contact) take tens to
a hundred (the 7k t-shirt from its XPBD canonical drape: 91).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp

from simulate.cloth.model import ClothControl, ClothModel
from simulate.contact.body_collider import BVH_OPTIONS

__all__ = ["ReferenceResult", "solve_equilibrium", "world_energy", "TOL_FORCE_FRACTION", "TOL_FORCE_CONTACT_FLOOR",
           "CONTACT_STIFFNESS"]

TOL_FORCE_FRACTION = 1.0e-6
"""Default force tolerance as a fraction of the lightest free particle's weight m g [-]."""
CONTACT_STIFFNESS = 1.0e5
"""Starting stiffness of the contact penalty and of the stick springs [N/m per particle]: a
particle pressed on the body with 0.01 N (the weight of ~40 particles of a cotton garment at
1.25 cm edges) sinks 0.1 micrometre behind its contact plane. Where the normal forces are larger
(stick springs holding a state far from equilibrium press with up to newtons), the solver raises
it near convergence until the deepest compression is below ``max_compression`` (1 micrometre by
default): the result then lies within that distance of the contact surface, never deeper."""
TOL_FORCE_CONTACT_FLOOR = 1.0e-8
"""Smallest default force tolerance with a body [N]: ten times the float64 rounding of a penalty
force, k_c * 1e-16 m at k_c = 1e7 N/m."""
_STIFFEN_AT = 1.0e3
"""Residual, in tolerances, below which the penalty compression is checked (and k_c raised)."""
_ACTIVE_SET_ROUNDS = 4
"""Newton solves per iteration at most while the set of particles the step presses on the body changes."""
_CG_TOLERANCE = 1.0e-8
"""Relative residual (preconditioner norm) at which a Newton system's PCG stops [-]."""
_CG_ITERATIONS = 30
"""PCG iterations per Newton system at most."""
_SHIFTS = (1.0e-12, 1.0e-10, 1.0e-8, 1.0e-6, 1.0e-4)
"""Diagonal shifts of the projected Hessian (relative to its mean diagonal), cumulative, tried
until it factors."""
_LINE_SEARCH_TRIALS = 30
"""Energy evaluations per line search at most."""
_HELD_GAP = 1.0e-4
"""Particles the previous step pressed stay in the next step's active-set guess while this close
to their contact plane [m]."""
_EPS_LENGTH = 1.0e-9
"""|f| below which a triangle direction exerts no stretch force (as ``common_kernels._EPS``)."""


@dataclasses.dataclass
class ReferenceResult:
    """Outcome of :func:`solve_equilibrium` (SI units)."""

    iterations: int
    """Newton iterations taken."""
    residual: float
    """Final max over free particles of |dE/dx_i| [N] (the true gradient, contact planes at the result)."""
    tol_force: float
    """Force tolerance the residual was held to [N]."""
    energy: float
    """Energy at the result [J]: the model's (gravity potential measured from the origin) plus the
    contact penalty and stick springs."""
    converged: bool
    """Residual <= tol_force (and contact compression <= max_compression) within max_iterations."""
    seconds: float
    """Wall time of the solve [s]."""
    residual_history: list[float] = dataclasses.field(default_factory=list)
    """Residual [N] of every evaluated state: the start, each iteration's result (twice where the
    penalty was stiffened there)."""
    factorizations: int = 0
    """Sparse factorizations (SuperLU) done."""
    cg_iterations: int = 0
    """Preconditioned conjugate-gradient iterations done (one Hessian product and solve each)."""
    contact_count: int = 0
    """Particles pressed on the body at the result (behind their contact plane)."""
    max_compression: float = 0.0
    """Deepest particle behind its contact plane at the result [m] (the penalty's compression)."""
    contact_stiffness: float = 0.0
    """Penalty (and stick spring) stiffness used at the end [N/m]; 0 without a body."""
    stick_count: int = 0
    """Particles held tangentially (friction="stick"): those in contact at the start."""
    friction_violations: int = 0
    """Stick particles whose tangential force exceeds mu times their normal force (+ tol_force)."""
    friction_violation_share: float = 0.0
    """friction_violations / stick_count (0 when no particle sticks)."""


# ----------------------------------------------------------------------------- model terms
class _WorldTerms:
    """Element data of one world in float64 and local particle numbering; energy, gradient and
    (projected) Hessian blocks of the elastic, gravity and attachment terms."""

    def __init__(self, model: ClothModel, world: int, control: ClothControl | None) -> None:
        sl = model.world_slice(world)
        self.count = sl.stop - sl.start
        tri_world = model.tri_world.numpy()[:model.tri_count]
        sel = tri_world == world
        self.tri = model.tri_indices_np[sel].astype(np.int64) - sl.start  # (T, 3)
        dm = model.tri_dm_inv.numpy()[:model.tri_count][sel].astype(np.float64)  # (T, 2, 2)
        a1, a2, b1, b2 = dm[:, 0, 0], dm[:, 1, 0], dm[:, 0, 1], dm[:, 1, 1]
        # coef[t, 0] = a (f1 weights), coef[t, 1] = b (f2 weights), as triangle_coefficients.
        self.coef = np.stack([np.stack([-(a1 + a2), a1, a2], 1), np.stack([-(b1 + b2), b1, b2], 1)], 1)
        self.tri_c = model.tri_compliance.numpy()[:model.tri_count][sel].astype(np.float64)  # (T, 3)
        if model.bend_count:
            bsel = model.bend_world.numpy()[:model.bend_count] == world
            self.bend = model.bend_indices_np[bsel].astype(np.int64) - sl.start  # (B, 4)
            self.bend_rest = model.bend_rest_angle.numpy()[:model.bend_count][bsel].astype(np.float64)
            self.bend_c = model.bend_compliance.numpy()[:model.bend_count][bsel].astype(np.float64)
        else:
            self.bend = np.zeros((0, 4), np.int64)
            self.bend_rest = self.bend_c = np.zeros(0)
        self.mass = model.particle_mass_np[sl].astype(np.float64)
        self.free = model.particle_inv_mass_np[sl] > 0.0
        self.gravity = np.asarray(model.gravity, np.float64)
        self.att = np.zeros(0, np.int64)
        self.att_target = np.zeros((0, 3))
        self.att_k = 0.0
        if model.features.attachments and model.attachment_count:
            att = model.attachment_particle_np.astype(np.int64)
            mine = (att >= sl.start) & (att < sl.stop)
            if control is None:
                targets, k, enabled = model.particle_q_rest[att], model.default_attachment_stiffness, True
            else:
                targets = control.attachment_target.numpy()[:model.attachment_count]
                k = float(control.world_attachment_stiffness.numpy()[world])
                enabled = bool(control.world_attachment_enabled.numpy()[world])
            if enabled and mine.any():
                self.att = att[mine] - sl.start
                self.att_target = np.asarray(targets, np.float64)[mine]
                self.att_k = float(k)

    # energy terms -------------------------------------------------------------------------
    def triangles(self, x: np.ndarray, hessian: str | None):
        """Stretch + shear: energy [J], corner gradients (T, 3, 3) [N] and, for ``hessian`` "exact" or
        "projected" (negative eigenvalues of each triangle's Hessian in (f1, f2) clamped to 0),
        element Hessians (T, 81) [N/m] (flattened (corner, axis, corner, axis) blocks)."""
        coef, c = self.coef, self.tri_c
        f = np.einsum("tik,tkd->tid", coef, x[self.tri])  # (T, 2, 3): f1, f2
        length = np.linalg.norm(f, axis=2)  # (T, 2)
        ok = length > _EPS_LENGTH
        n = np.where(ok[..., None], f / np.where(ok, length, 1.0)[..., None], 0.0)
        strain = np.where(ok, length - 1.0, 0.0)
        s = np.einsum("td,td->t", f[:, 0], f[:, 1])
        energy = float(np.sum((length - 1.0) ** 2 / (2.0 * c[:, :2])) + np.sum(s * s / (2.0 * c[:, 2])))
        dedf = n * (strain / c[:, :2])[..., None] + (s / c[:, 2])[:, None, None] * f[:, ::-1]  # (T, 2, 3)
        grad = np.einsum("tik,tid->tkd", coef, dedf)
        if hessian is None:
            return energy, grad, None
        t_count = len(f)
        eye = np.eye(3)
        h = np.zeros((t_count, 2, 3, 2, 3))
        nn = n[..., :, None] * n[..., None, :]  # (T, 2, 3, 3)
        w = np.where(ok, 1.0 - 1.0 / np.where(ok, length, 1.0), 0.0)  # transverse factor, < 0 in compression
        for i in range(2):
            h[:, i, :, i, :] = (nn[:, i] + w[:, i, None, None] * (eye - nn[:, i])) / c[:, i, None, None]
        g6 = f[:, ::-1].reshape(t_count, 6)  # d(f1 . f2)/d(f1, f2) = (f2, f1)
        shear = g6[:, :, None] * g6[:, None, :]
        shear[:, 0:3, 3:6] += s[:, None, None] * eye
        shear[:, 3:6, 0:3] += s[:, None, None] * eye
        h = h.reshape(t_count, 6, 6) + shear / c[:, 2, None, None]
        if hessian == "projected":
            vals, vecs = np.linalg.eigh(h)
            h = np.einsum("tij,tj,tkj->tik", vecs, np.maximum(vals, 0.0), vecs)
        # Chain rule through the linear map x -> (f1, f2): K[k a, l b] = sum_ij coef[i k] H[i a, j b] coef[j l].
        k = np.einsum("tik,tiajb,tjl->tkalb", coef, h.reshape(t_count, 2, 3, 2, 3), coef)
        return energy, grad, k.reshape(t_count, 81)

    @staticmethod
    def _dihedral(x1: np.ndarray, x2: np.ndarray, x3: np.ndarray, x4: np.ndarray):
        """Signed dihedral angles of stencils (opp0, opp1, edge0, edge1), all (B, 3) [m], as
        ``bending_angle_grad``: ok (B,) bool (not degenerate), theta (B,) [rad], grad theta (B, 4, 3) [1/m]."""
        n1 = np.cross(x3 - x1, x4 - x1)
        n2 = np.cross(x4 - x2, x3 - x2)
        e = x4 - x3
        n1_len = np.linalg.norm(n1, axis=1)
        n2_len = np.linalg.norm(n2, axis=1)
        e_len = np.linalg.norm(e, axis=1)
        ok = (n1_len >= 1e-12) & (n2_len >= 1e-12) & (e_len >= 1e-9)
        e_hat = e / np.where(ok, e_len, 1.0)[:, None]
        # acos(n1^ . n2^) signed by (n2 x n1) . e^, written as an atan2 that keeps full precision near flat.
        theta = np.arctan2(np.einsum("ij,ij->i", np.cross(n2, n1), e_hat), np.einsum("ij,ij->i", n1, n2))
        q1 = n1 / np.where(ok, n1_len * n1_len, 1.0)[:, None]
        q2 = n2 / np.where(ok, n2_len * n2_len, 1.0)[:, None]
        dot = lambda u, v: np.einsum("ij,ij->i", u, v)[:, None]  # noqa: E731
        d = np.stack([q1 * e_len[:, None], q2 * e_len[:, None],
                      q1 * dot(x1 - x4, e_hat) + q2 * dot(x2 - x4, e_hat),
                      q1 * dot(x3 - x1, e_hat) + q2 * dot(x3 - x2, e_hat)], axis=1)
        return ok, theta, d

    def bending(self, x: np.ndarray, hessian: str | None):
        """Bending: energy [J], corner gradients (B, 4, 3) [N] and, for ``hessian`` "projected", the
        Gauss-Newton Hessians grad theta grad theta^T / c, for "exact" those plus
        (theta - rest) hess theta / c (hess theta by forward differences of grad theta), (B, 144) [N/m]."""
        if not len(self.bend):
            return 0.0, np.zeros((0, 4, 3)), (None if hessian is None else np.zeros((0, 144)))
        xs = [x[self.bend[:, k]] for k in range(4)]
        ok, theta, d = self._dihedral(*xs)
        dtheta = np.where(ok, theta - self.bend_rest, 0.0)
        energy = float(np.sum(dtheta * dtheta / (2.0 * self.bend_c)))
        grad = d * (dtheta / self.bend_c)[:, None, None]
        if hessian is None:
            return energy, grad, None
        flat = np.where(ok[:, None], d.reshape(-1, 12), 0.0)
        k = flat[:, :, None] * flat[:, None, :]
        if hessian == "exact":
            # Forward differences of grad theta with a step of 1e-6 of the hinge edge: truncation
            # ~1e-6 and rounding ~1e-10 of hess theta, enough for Newton's quadratic convergence.
            step = 1.0e-6 * np.linalg.norm(xs[3] - xs[2], axis=1)
            second = np.zeros_like(k)
            for j in range(12):
                corner, axis = divmod(j, 3)
                moved = list(xs)
                moved[corner] = xs[corner].copy()
                moved[corner][:, axis] += step
                second[:, :, j] = (self._dihedral(*moved)[2] - d).reshape(-1, 12) / step[:, None]
            k += dtheta[:, None, None] * 0.5 * (second + second.transpose(0, 2, 1))
        k /= self.bend_c[:, None, None]
        return energy, grad, k.reshape(-1, 144)

    def particles(self, x: np.ndarray, x_ref: np.ndarray):
        """Gravity (relative to ``x_ref``) and attachments: energy [J], gradient (V, 3) [N],
        diagonal Hessian blocks (V, 3, 3) [N/m]."""
        grad = -self.mass[:, None] * self.gravity[None, :]
        energy = -float(np.sum(self.mass * ((x - x_ref) @ self.gravity)))
        hess = np.zeros((self.count, 3, 3))
        if len(self.att):
            delta = x[self.att] - self.att_target
            energy += 0.5 * self.att_k * float(np.sum(delta * delta))
            grad[self.att] += self.att_k * delta
            hess[self.att] += self.att_k * np.eye(3)
        return energy, grad, hess

    def gather(self, tri_grad: np.ndarray, bend_grad: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """Adds corner gradients (T, 3, 3) and (B, 4, 3) into per-particle ``grad`` (V, 3) [N]."""
        idx = np.concatenate([self.tri.reshape(-1), self.bend.reshape(-1)])
        vals = np.concatenate([tri_grad.reshape(-1, 3), bend_grad.reshape(-1, 3)])
        for d in range(3):
            grad[:, d] += np.bincount(idx, weights=vals[:, d], minlength=self.count)
        return grad


def world_energy(model: ClothModel, world: int, positions: np.ndarray, *,
                 control: ClothControl | None = None) -> tuple[float, np.ndarray]:
    """The cloth model's energy of one world's state and its gradient (no body contact).

    Args:
        model: a finalized ClothModel.
        world: world index.
        positions: the world's particle positions [m], (V_w, 3).
        control: attachment targets, stiffness and switch (default: targets at the rest positions,
            ``model.default_attachment_stiffness``, enabled).
    Returns:
        energy [J] (stretch + shear + bending + attachments + gravity potential measured from the
        origin) and its gradient dE/dx [N], (V_w, 3) float64, pinned particles included.
    """
    terms = _WorldTerms(model, world, control)
    x = np.asarray(positions, np.float64)
    if x.shape != (terms.count, 3):
        raise ValueError(f"positions must have shape ({terms.count}, 3) (got {x.shape})")
    e_tri, g_tri, _ = terms.triangles(x, None)
    e_bend, g_bend, _ = terms.bending(x, None)
    e_part, grad, _ = terms.particles(x, np.zeros_like(x))
    return e_tri + e_bend + e_part, terms.gather(g_tri, g_bend, grad)


# ----------------------------------------------------------------------------- body contact
@wp.kernel(enable_backward=False)
def _closest_face(mesh: wp.uint64, points: wp.array(dtype=wp.vec3), max_dist: wp.array(dtype=float),
                  face_out: wp.array(dtype=wp.int32), sign_out: wp.array(dtype=float)):
    """Closest body face within max_dist (-1 if none) and the inside/outside sign of the point."""
    i = wp.tid()
    res = wp.mesh_query_point_sign_normal(mesh, points[i], max_dist[i])
    face_out[i] = -1
    if res.result:
        face_out[i] = res.face
        sign_out[i] = res.sign


def _closest_points(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest points [m] (N, 3) of triangles (a, b, c) to points p, all (N, 3) (Ericson 5.1.5)."""
    dot = lambda u, v: np.einsum("ij,ij->i", u, v)  # noqa: E731
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        denom = 1.0 / (va + vb + vc)
    inside = a + ab * (vb * denom)[:, None] + ac * (vc * denom)[:, None]
    conds = [(d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (vc <= 0) & (d1 >= 0) & (d3 <= 0),
             (d6 >= 0) & (d5 <= d6), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
             (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)]
    choices = [a, b, a + ab * t_ab[:, None], c, a + ac * t_ac[:, None], b + (c - b) * t_bc[:, None]]
    out = inside
    for cond, choice in zip(reversed(conds), reversed(choices)):  # the first matching region wins
        out = np.where(cond[:, None], choice, out)
    return out


class _Body:
    """A body mesh: float64 contact planes of particles from a Warp BVH query (CPU).

    With ``face_groups`` (primary collision bodies, ``BodyCollider``), particle i meets only the
    faces of group ``part[i]``."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, reach: np.ndarray, margin: float,
                 face_groups: list[np.ndarray] | None = None, part: np.ndarray | None = None) -> None:
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.reach = reach
        self.device = wp.get_device("cpu")
        groups = [np.arange(len(self.faces))] if face_groups is None else [np.asarray(g, np.int64) for g in face_groups]
        self.groups = groups
        self.part = np.zeros(len(reach), np.int64) if part is None or face_groups is None else \
            np.where((np.asarray(part) >= 0) & (np.asarray(part) < len(groups)), np.asarray(part), 0).astype(np.int64)
        points = wp.array(self.vertices.astype(np.float32), dtype=wp.vec3, device=self.device)
        self.meshes = [wp.Mesh(points=points, indices=wp.array(self.faces[g].reshape(-1).astype(np.int32), dtype=wp.int32,
                                                                device=self.device), **BVH_OPTIONS) for g in groups]
        self.max_dist = (reach + margin).astype(np.float32)
        tri = self.vertices[self.faces]
        normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        self.face_normal = normal / np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)

    def planes(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contact planes ``n . x >= offset`` of particles at ``x`` (V, 3) [m]: active (V,) bool
        (a body face within reach + margin), outward unit normal (V, 3), offset (V,) [m]."""
        count = len(x)
        face = np.full(count, -1, np.int64)
        sign = np.zeros(count)
        for g, (rows, mesh) in enumerate(zip(self.groups, self.meshes)):
            sel = np.nonzero(self.part == g)[0]
            if not len(sel):
                continue
            f_g = wp.zeros(len(sel), dtype=wp.int32, device=self.device)
            s_g = wp.zeros(len(sel), dtype=float, device=self.device)
            wp.launch(_closest_face, dim=len(sel), device=self.device,
                      inputs=[mesh.id, wp.array(x[sel].astype(np.float32), dtype=wp.vec3, device=self.device),
                              wp.array(self.max_dist[sel], dtype=float, device=self.device)], outputs=[f_g, s_g])
            local = f_g.numpy()
            face[sel] = np.where(local >= 0, rows[np.maximum(local, 0)], -1)
            sign[sel] = s_g.numpy()
        active = face >= 0
        normal = np.zeros((count, 3))
        offset = np.zeros(count)
        if active.any():
            f = self.faces[face[active]]
            p = x[active]
            closest = _closest_points(p, self.vertices[f[:, 0]], self.vertices[f[:, 1]], self.vertices[f[:, 2]])
            delta = p - closest
            dist = np.linalg.norm(delta, axis=1)
            # Outward normal: along the point's offset from the body, or the face normal on the surface.
            n = np.where((dist > 1e-12)[:, None], delta / np.maximum(dist, 1e-300)[:, None] * sign[active, None],
                         self.face_normal[face[active]])
            normal[active] = n
            offset[active] = np.einsum("ij,ij->i", n, closest) + self.reach[active]
        return active, normal, offset


# ----------------------------------------------------------------------------- Hessian assembly
class _Assembler:
    """Sparse pattern of the Hessian over the free particles' coordinates; sums element blocks
    into CSC data with one bincount."""

    def __init__(self, terms: _WorldTerms) -> None:
        free_index = np.full(terms.count, -1, np.int64)
        free_index[terms.free] = np.arange(int(terms.free.sum()))
        self.size = 3 * int(terms.free.sum())
        rows, cols = [], []
        for elems in (terms.tri, terms.bend, np.arange(terms.count)[:, None]):
            k = elems.shape[1]
            # Entry (corner k, axis a) x (corner l, axis b) of each element block, in the order
            # of the flattened (k, a, l, b) blocks.
            p = free_index[elems]  # (E, k)
            dof = (3 * p[:, :, None] + np.arange(3)).reshape(len(elems), 3 * k)  # (E, 3k)
            ok = (p >= 0)[:, :, None].repeat(3, 2).reshape(len(elems), 3 * k)
            r = np.where(ok[:, :, None] & ok[:, None, :], dof[:, :, None], -1)
            rows.append(r.reshape(-1))
            cols.append(np.broadcast_to(dof[:, None, :], r.shape).reshape(-1))
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        self.keep = rows >= 0
        key = rows[self.keep] * self.size + cols[self.keep]
        unique, self.slot = np.unique(key, return_inverse=True)
        self.nnz = len(unique)
        self.indices = (unique % self.size).astype(np.int32)  # row index within each column (symmetric)
        self.indptr = np.searchsorted(unique // self.size, np.arange(self.size + 1)).astype(np.int32)
        self.diag = np.searchsorted(unique, np.arange(self.size) * (self.size + 1))
        # CSC slots of each free particle's own 3x3 block (row-major), for per-particle terms.
        dof = 3 * free_index[terms.free][:, None] + np.arange(3)
        block = (dof[:, :, None] * self.size + dof[:, None, :]).reshape(-1, 9)
        self.particle_slot = np.full((terms.count, 9), -1, np.int64)
        self.particle_slot[terms.free] = np.searchsorted(unique, block)

    def add_particle_blocks(self, data: np.ndarray, particles: np.ndarray, blocks: np.ndarray) -> None:
        """Adds 3x3 blocks (P, 3, 3) [N/m] on the diagonal of distinct free ``particles`` (P,) to ``data``."""
        data[self.particle_slot[particles].reshape(-1)] += blocks.reshape(-1)

    def data(self, blocks: list[np.ndarray]) -> np.ndarray:
        """CSC values (nnz,) [N/m] of the Hessian from element blocks (in the pattern's order)."""
        vals = np.concatenate([b.reshape(-1) for b in blocks])[self.keep]
        return np.bincount(self.slot, weights=vals, minlength=self.nnz)

    def matrix(self, data: np.ndarray) -> sp.csc_matrix:
        """The Hessian with CSC values ``data`` [N/m]."""
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))


# ----------------------------------------------------------------------------- solver
def _pcg(matvec, rhs: np.ndarray, precondition, tol: float, max_iter: int) -> tuple[np.ndarray | None, int, bool]:
    """Preconditioned conjugate gradients for H d = -rhs, H given by ``matvec``.

    Returns (d, iterations, converged): converged once the preconditioned residual has dropped by
    ``tol`` (else d is the last iterate, still a descent direction); d is None at the first
    direction of non-positive curvature (H is then not positive definite).
    """
    d = np.zeros_like(rhs)
    r = -rhs
    z = precondition(r)
    p = z
    rz = float(r @ z)
    rz0 = rz
    for k in range(max_iter):
        hp = matvec(p)
        curvature = float(p @ hp)
        if not curvature > 0.0:
            return None, k + 1, False
        a = rz / curvature
        d += a * p
        r -= a * hp
        z = precondition(r)
        rz_new = float(r @ z)
        if rz_new <= tol * tol * rz0:
            return d, k + 1, True
        p = z + (rz_new / rz) * p
        rz = rz_new
    return d, max_iter, False


def solve_equilibrium(
    model: ClothModel,
    world: int,
    start_positions: np.ndarray,
    *,
    control: ClothControl | None = None,
    body_vertices: np.ndarray | None = None,
    body_faces: np.ndarray | None = None,
    body_face_groups: list[np.ndarray] | None = None,
    contact_thickness: float = 2.0e-3,
    friction: str | None = None,
    contact_tolerance: float = 1.0e-4,
    contact_stiffness: float = CONTACT_STIFFNESS,
    max_compression: float = 1.0e-6,
    tol_force: float | None = None,
    max_iterations: int = 200,
    max_step: float = 0.01,
) -> tuple[np.ndarray, ReferenceResult]:
    """Static equilibrium of one world: positions where the model's energy is stationary.

    Args:
        model: a finalized ClothModel (any device: its arrays are read back to the host).
        world: world index.
        start_positions: the world's start positions [m], (V_w, 3); pinned particles stay there,
            and Newton starts from here, so the result is the equilibrium nearest to it.
        control: attachment targets / stiffness / switch (see :func:`world_energy`).
        body_vertices, body_faces: the body mesh [m], (Vb, 3) and (Fb, 3), or None (no contact).
            Faces must be outward-wound; unreferenced vertices are ignored.
        body_face_groups: primary collision bodies: per part, rows of ``body_faces``; particle i
            meets the part ``model.particle_body_part`` names (as ``BodyCollider``). None: all faces.
        contact_thickness: collider thickness [m]; particle i keeps contact_thickness + its
            radius (half the fabric thickness) from the body, as ``BodyCollider`` does.
        friction: "stick" (default with a body): particles within ``contact_tolerance`` of their
            contact plane at the start (or behind it) are held by tangential springs (stiffness
            = the penalty stiffness) at their start positions in that plane: the equilibrium
            nearest the given contact state. The result counts those whose tangential force
            exceeds mu = ``model.world_friction[world]`` times their normal force (plus
            tol_force). "none": frictionless.
        contact_tolerance: gap to the contact plane below which a start particle sticks [m].
        contact_stiffness: starting penalty stiffness k_c [N/m] (see :data:`CONTACT_STIFFNESS`).
            A particle pressed with normal force N sits N / k_c behind its contact plane; when
            near convergence the deepest such compression exceeds ``max_compression``, k_c is
            raised to make it half that and Newton goes on.
        max_compression: largest accepted penalty compression [m].
        tol_force: converged when max_i |dE/dx_i| <= tol_force [N] over free particles. Default:
            TOL_FORCE_FRACTION (1e-6) of the lightest free particle's weight m |g|, and with a
            body at least TOL_FORCE_CONTACT_FLOOR (1e-8 N, ten times the float64 rounding of a
            contact force k_c * 1e-16 m at k_c = 1e7 N/m).
        max_iterations: Newton iterations at most.
        max_step: largest particle displacement of one Newton step [m]; contact planes are looked
            for within 2 max_step beyond the contact distance, so no particle passes a body face
            unseen in one step.
    Returns:
        positions [m] (V_w, 3) float64 and a :class:`ReferenceResult`.
    Raises:
        ValueError for bad shapes or options.
    """
    t0 = time.perf_counter()
    terms = _WorldTerms(model, world, control)
    x = np.array(start_positions, dtype=np.float64)
    if x.shape != (terms.count, 3) or not np.all(np.isfinite(x)):
        raise ValueError(f"start_positions must be finite with shape ({terms.count}, 3) (got {x.shape})")
    if not terms.free.any():
        raise ValueError(f"world {world} has no free particle")
    body = None
    if body_vertices is not None:
        if body_faces is None:
            raise ValueError("body_faces is required with body_vertices")
        friction = "stick" if friction is None else friction
        if friction not in ("stick", "none"):
            raise ValueError(f"friction must be 'stick' or 'none' (got {friction!r})")
        radius = model.particle_radius.numpy()[model.world_slice(world)].astype(np.float64)
        part = model.particle_body_part.numpy()[model.world_slice(world)]
        body = _Body(body_vertices, body_faces, contact_thickness + radius, 2.0 * max_step, body_face_groups, part)
    if tol_force is None:
        weight = float(terms.mass[terms.free].min()) * (float(np.linalg.norm(terms.gravity)) or 9.81)
        tol_force = max(TOL_FORCE_FRACTION * weight, TOL_FORCE_CONTACT_FLOOR if body is not None else 0.0)
    if not (np.isfinite(tol_force) and tol_force > 0.0):
        raise ValueError(f"tol_force must be a number > 0 [N] (got {tol_force!r})")
    k_c = float(contact_stiffness)
    mu = float(model.world_friction.numpy()[world])
    free = terms.free
    x_ref = x.copy()  # gravity potential relative to the start: small numbers, little cancellation
    assembler = _Assembler(terms)

    # Stick springs: the particles in contact at the start, their start points and plane normals.
    stick = np.zeros(0, np.int64)
    stick_x0 = stick_n = np.zeros((0, 3))
    if body is not None and friction == "stick":
        active, normal, offset = body.planes(x)
        gap = np.einsum("ij,ij->i", normal, x) - offset
        stick = np.nonzero(active & (gap < contact_tolerance) & free)[0]
        stick_x0, stick_n = x[stick].copy(), normal[stick]
    stick_proj = np.eye(3)[None] - stick_n[:, :, None] * stick_n[:, None, :]  # (S, 3, 3)

    def contact_terms(x, planes):
        """Penalty + stick springs: energy [J], gradient (V, 3) [N]."""
        grad = np.zeros_like(x)
        if body is None:
            return 0.0, grad
        active, normal, offset = planes
        gap = np.einsum("ij,ij->i", normal, x) - offset
        depth = np.where(active & (gap < 0.0), gap, 0.0)
        energy = 0.5 * k_c * float(np.sum(depth * depth))
        grad += (k_c * depth)[:, None] * normal
        if len(stick):
            slide = np.einsum("sij,sj->si", stick_proj, x[stick] - stick_x0)
            energy += 0.5 * k_c * float(np.sum(slide * slide))
            grad[stick] += k_c * slide
        return energy, grad

    def evaluate(x, planes):
        """Energy [J] (gravity relative to the start), gradient (V, 3) [N] (0 at pinned particles)
        and the energy's magnitude (the scale of its float64 rounding) [J]."""
        e_tri, g_tri, _ = terms.triangles(x, None)
        e_bend, g_bend, _ = terms.bending(x, None)
        e_part, grad, _ = terms.particles(x, x_ref)
        e_con, g_con = contact_terms(x, planes)
        grad = terms.gather(g_tri, g_bend, grad + g_con)
        grad[~free] = 0.0
        scale = abs(e_tri) + abs(e_bend) + abs(e_part) + abs(e_con)
        return e_tri + e_bend + e_part + e_con, grad, scale

    def hessian(x, kind):
        """CSC values [N/m] of the Hessian without the contact penalty, "exact" or "projected"."""
        h_part = terms.particles(x, x_ref)[2]
        if len(stick):
            h_part[stick] += k_c * stick_proj
        return assembler.data([terms.triangles(x, kind)[2], terms.bending(x, kind)[2], h_part])

    counts = {"factorizations": 0, "cg": 0}
    # After the exact Hessian met negative curvature, the next attempt waits 1, 2, 4, 8 iterations.
    exact_wait = {"wait": 0, "skip": 0}

    def factorize(h_proj):
        """SuperLU factors of the projected Hessian (CSC values), with diagonal shifts added in
        place until it factors (the projection can leave flat unstretched cloth singular); None if
        it never does."""
        diag_mean = float(np.mean(h_proj[assembler.diag]))
        for shift in _SHIFTS:
            h_proj[assembler.diag] += shift * diag_mean
            try:
                lu = spla.splu(assembler.matrix(h_proj), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                               options={"SymmetricMode": True})
            except RuntimeError:  # exactly singular
                continue
            counts["factorizations"] += 1
            return lu
        return None

    def newton_step(x, grad, planes, held):
        """Newton direction (V, 3) [m], or None if no Hessian factors.

        Solves with PCG on the exact Hessian, preconditioned by a SuperLU factorization of the
        projected one; where PCG meets negative curvature, with that factorization directly (the
        projected Hessian is positive definite: a descent direction). The contact penalty is
        modelled for the particles ``held`` (V,) bool and for those the step itself presses (an
        active-set loop: the one-sided penalty as 1/2 k_c (gap + n . d)^2 on that set).
        """
        use_exact = exact_wait["wait"] == 0
        exact_wait["wait"] = max(0, exact_wait["wait"] - 1)
        exact = hessian(x, "exact") if use_exact else None
        projected = hessian(x, "projected")
        if body is not None:
            active, normal, offset = planes
            gap = np.einsum("ij,ij->i", normal, x) - offset
            held = held & active & free
            nn = k_c * normal[:, :, None] * normal[:, None, :]
        step = np.zeros_like(x)
        for _ in range(_ACTIVE_SET_ROUNDS):
            h_proj, rhs = projected.copy(), grad.copy()
            h_exact = exact.copy() if use_exact else None
            if body is not None:
                for data in (h_exact, h_proj):
                    if data is not None:
                        assembler.add_particle_blocks(data, np.nonzero(held)[0], nn[held])
                lifted = held & (gap >= 0.0)  # the penalty is in grad already where gap < 0
                rhs[lifted] += (k_c * gap[lifted])[:, None] * normal[lifted]
            b = rhs[free].reshape(-1)
            lu = factorize(h_proj)
            if lu is None:
                return None
            d = None
            if use_exact:
                d, cg, _ = _pcg(assembler.matrix(h_exact).dot, b, lu.solve, _CG_TOLERANCE, _CG_ITERATIONS)
                counts["cg"] += cg
                if d is None:
                    use_exact = False
                    exact_wait["skip"] = min(2 * exact_wait["skip"], 8) or 1
                    exact_wait["wait"] = exact_wait["skip"]
                else:
                    exact_wait["skip"] = 0
            if d is None:
                d = -lu.solve(b)
            if not np.all(np.isfinite(d)):
                return None
            step[free] = d.reshape(-1, 3)
            if body is None:
                break
            predicted = active & free & (gap + np.einsum("ij,ij->i", normal, step) < 0.0)
            if np.array_equal(predicted, held):
                break
            held = predicted
        return step

    def line_search(x, step, energy, slope, noise, alpha_max, planes):
        """A step length along ``step`` with sufficient decrease of the true energy (Armijo; energy
        changes within the float64 ``noise`` [J] count as decrease) and, where it overshoots the
        minimum along the line, a directional derivative back below 0.9 |slope| (found by secant
        steps on the derivative). Returns (alpha, x + alpha step), or (0, None) if none decreases."""
        alpha = alpha_max
        best = (0.0, None)
        for _ in range(_LINE_SEARCH_TRIALS):
            trial = x + alpha * step
            e_new, g_new, _ = evaluate(trial, planes)
            if not (e_new <= energy + 1.0e-4 * alpha * slope or abs(e_new - energy) <= noise):
                alpha *= 0.5
                continue
            best = (alpha, trial)
            dphi = float(np.sum(g_new * step))
            if dphi <= 0.9 * abs(slope):
                break  # still descending, or nearly at the minimum along the line
            # Past the minimum along the line: secant on the derivative between 0 and alpha.
            alpha *= min(0.9, max(0.1, -slope / (dphi - slope)))
        return best

    def residual(grad):
        return float(np.sqrt(np.max(np.einsum("ij,ij->i", grad, grad))))

    history: list[float] = []
    converged = False
    iteration = 0
    held = np.zeros(terms.count, bool)
    while True:
        planes = body.planes(x) if body is not None else None
        energy, grad, scale = evaluate(x, planes)
        res = residual(grad)
        history.append(res)
        if body is not None and res <= _STIFFEN_AT * tol_force:
            # Near convergence the normal forces are known: stiffen the penalty so that the deepest
            # compression becomes half the limit (compression scales as 1 / k_c at fixed forces).
            active, normal, offset = planes
            compression = float(np.max(np.where(active, offset - np.einsum("ij,ij->i", normal, x), 0.0), initial=0.0))
            if compression > max_compression:
                if iteration >= max_iterations:
                    break
                k_c *= 2.0 * compression / max_compression
                continue
        if res <= tol_force:
            converged = True
            break
        if iteration >= max_iterations:
            break
        iteration += 1
        if body is not None:
            # Active-set guess: the pressed particles and those the last step pressed that are still close.
            active, normal, offset = planes
            gap = np.einsum("ij,ij->i", normal, x) - offset
            held = active & ((gap < 0.0) | (held & (gap < _HELD_GAP)))
        step = newton_step(x, grad, planes, held)
        slope = float(np.sum(grad * step)) if step is not None else 0.0
        if not slope < 0.0 and body is not None:
            step = newton_step(x, grad, planes, np.zeros(terms.count, bool))  # plain Newton descends
            slope = float(np.sum(grad * step)) if step is not None else 0.0
        if not slope < 0.0:
            break  # no descent direction: reported as not converged
        if body is not None:
            held = active & (np.einsum("ij,ij->i", normal, x + step) - offset < 0.0)
        alpha_max = min(1.0, max_step / max(float(np.sqrt(np.max(np.einsum("ij,ij->i", step, step)))), 1e-300))
        alpha, trial = line_search(x, step, energy, slope, 1.0e-12 * scale, alpha_max, planes)
        if trial is None:
            break
        x = trial

    compression, contact_count, violations = 0.0, 0, 0
    if body is not None:
        active, normal, offset = planes
        gap = np.einsum("ij,ij->i", normal, x) - offset
        press = active & (gap < 0.0)
        contact_count = int(press.sum())
        compression = float(np.max(np.where(press, -gap, 0.0), initial=0.0))
        if len(stick):
            normal_force = k_c * np.where(press, -gap, 0.0)[stick]
            slide = np.einsum("sij,sj->si", stick_proj, x[stick] - stick_x0)
            tangential = k_c * np.linalg.norm(slide, axis=1)
            violations = int(np.sum(tangential > mu * normal_force + tol_force))
    energy_abs = energy - float(np.sum(terms.mass * (x_ref @ terms.gravity)))
    result = ReferenceResult(
        iterations=iteration, residual=history[-1], tol_force=float(tol_force), energy=energy_abs,
        converged=converged, seconds=time.perf_counter() - t0, residual_history=history,
        factorizations=counts["factorizations"], cg_iterations=counts["cg"],
        contact_count=contact_count, max_compression=compression,
        contact_stiffness=k_c if body is not None else 0.0, stick_count=len(stick),
        friction_violations=violations, friction_violation_share=violations / len(stick) if len(stick) else 0.0)
    return x, result
