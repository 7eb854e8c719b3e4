"""SolverVBD: vertex block descent on the implicit-Euler incremental potential, batched over worlds."""

from __future__ import annotations

import functools
import hashlib
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from simulate.cloth.model import ClothControl, ClothModel, ClothState
from simulate.solvers.base import SolverBase
from simulate.solvers.vbd import kernels

if TYPE_CHECKING:
    from simulate.contact.body_collider import BodyCollider

__all__ = ["SolverVBD", "colour_vertices"]

SHARED_TILE_MAX_BYTES = 200 * 1024
"""On CUDA a world's float64 positions sweep in a shared-memory tile when it fits (24 bytes per
particle, rounded up to 64 particles: up to 8,500 particles per world; an H100/H200 SM has 228 KB)."""
FRICTION_SLIP_SPEED = 1.0e-3
"""Body friction's static-to-sliding scale [m/s]: a vertex whose tangential load stays below mu N
creeps slower than this (``kernels.friction_terms``; the slip scale is this times the substep)."""
_sweep_kernel = functools.cache(kernels.make_vbd_sweep_kernel)


def colour_vertices(faces: np.ndarray, bend_indices: np.ndarray, vertex_count: int) -> np.ndarray:
    """Greedy colouring of a garment's vertices: two vertices that share a triangle or a bending
    stencil never share a colour, so a colour's vertices can take their Newton steps in parallel.

    Args:
        faces: triangles (F, 3), world-local vertex indices.
        bend_indices: bending stencils (E, 4), world-local, or empty.
        vertex_count: V.
    Returns:
        colour per vertex, int32 (V,); colours are 0 .. C-1, vertices in index order take the
        smallest colour none of their coloured neighbours has.
    """
    pairs = [faces[:, [a, b]] for a in range(3) for b in range(3) if a != b]
    if len(bend_indices):
        pairs += [bend_indices[:, [a, b]] for a in range(4) for b in range(4) if a != b]
    edges = np.unique(np.concatenate(pairs).astype(np.int64), axis=0)
    start = np.searchsorted(edges[:, 0], np.arange(vertex_count + 1))
    neighbours = edges[:, 1]
    colour = np.full(vertex_count, -1, dtype=np.int64)
    for v in range(vertex_count):
        used = colour[neighbours[start[v]:start[v + 1]]]
        taken = np.zeros(len(used) + 2, dtype=bool)
        taken[used[(used >= 0) & (used < len(taken))]] = True
        colour[v] = int(np.argmin(taken))
    return colour.astype(np.int32)


class SolverVBD(SolverBase):
    """Vertex Block Descent (Chen, Macklin, Pan et al. 2024) on the model's energy.

    Each substep minimizes the implicit-Euler incremental potential (inertia + triangle stretch
    and shear + dihedral bending + attachment springs) by ``iterations`` sweeps of per-vertex
    Newton steps, colour by colour, starting from ``x + dt v`` plus the share of ``dt^2 g`` the
    particle fell by in its last substep (VBD's adaptive initialization; 0 below half of g).  Body contact is a hard plane per
    particle (found once per substep at the inertial target, as in XPBD) applied after each
    vertex step.  Coulomb friction is a force in the same vertex step (``kernels.friction_terms``):
    mu times the normal force the plane carries, against the tangential slip relative to the
    body, so it competes with the elastic forces of that step and a cloth slips where its load
    exceeds mu N (``tests/test_friction.py``: Coulomb's incline).

    Unlike XPBD's per-substep multipliers, nothing here is reset between substeps: a cloth at rest
    starts each substep where it is and moves only where its forces do not balance, so the rest
    state is the model's static equilibrium at any iteration count, and fewer iterations only
    make the approach to it slower.  Positions are kept in float64 inside the solver (the state
    holds their float32 rounding): a stiff vertex's step near rest is below float32's resolution.
    A substep is three launches: the prediction, one sweep kernel for all colours of every world
    (one thread block per world, a barrier between colours) and the velocity update; with
    self-contact, the search (every ``detect_every`` substeps; on every ``search_every``-th of
    those every world's BVH search, on the others a search only in worlds that moved farther than
    half the skin and a refresh of the others' lists) comes before the sweep.
    """

    def __init__(
        self,
        model: ClothModel,
        *,
        iterations: int = 5,
        body_contact: bool | None = None,
        extra_damping: float = 0.0,
        block_dim: int = 256,
        shared: bool | None = None,
        contact_detect_every: int = 1,
        self_contact: bool | None = None,
        self_contact_options: dict | None = None,
        self_contact_stiffness: float = 1.0e4,
        untangle: bool | dict = False,
    ) -> None:
        """
        Args:
            model: cloth model.
            iterations: sweeps over all colours per substep (>= 1).
            body_contact: contact with the body passed to ``step`` (default from model.features).
            extra_damping: damping rate added to each fabric's [1/s].
            block_dim: threads per world block (CUDA; CPU runs one lane per block).
            shared: sweep each world's positions in a shared-memory tile (True) or in global memory
                (False); None = on CUDA when the largest world fits ``SHARED_TILE_MAX_BYTES``.  Same
                result either way.
            contact_detect_every: body queries on every N-th substep of a frame (see ``SolverBase``).
            self_contact: cloth self-contact (default from model.features): each particle's Newton
                step carries a penalty holding it ``thickness`` off its candidate triangle
                (:class:`~simulate.contact.self_contact.SelfContact`, searched at the substep's
                start), and is kept within its displacement bound (vertex-triangle and edge-edge
                distances at the search), so no new intersection forms.
            self_contact_options: keyword options of ``SelfContact`` (thickness, margin,
                rest_exclusion, detect_every, bounds, bound_fraction, directional_bounds: the bound
                as a half-space along the direction away from the nearest pair plus a ball, so
                pressed layers may part and slide; ``SimSettings.self_contact_directional_bounds``;
                search_every and skin: every world searches on every N-th self-contact substep of a
                frame, in between only worlds that moved farther than half the skin, the others
                refresh their lists; ``SimSettings.self_contact_search_every``).
            self_contact_stiffness: penalty stiffness [N/m] holding a particle ``thickness`` off
                its self-contact triangle (in each Newton step; 1e4 N/m: a vertex pressed by 1 mN
                gives 0.1 um).
            untangle: after each substep, one step of intersection contour minimization
                (:class:`~simulate.contact.untangle.Untangler`; a dict gives its keyword options) in
                worlds whose ``control.world_self_contact`` is on; the step counts into the velocities.
        """
        super().__init__(model, body_contact=body_contact, extra_damping=extra_damping,
                         contact_detect_every=contact_detect_every)
        if int(iterations) != iterations or iterations < 1:
            raise ValueError(f"iterations must be an integer >= 1 (got {iterations!r})")
        if int(block_dim) != block_dim or not 32 <= block_dim <= 1024 or block_dim % 32:
            raise ValueError(f"block_dim must be a multiple of 32 in [32, 1024] (got {block_dim!r})")
        if not (np.isfinite(self_contact_stiffness) and self_contact_stiffness > 0.0):
            raise ValueError(f"self_contact_stiffness must be > 0 [N/m] (got {self_contact_stiffness!r})")
        self.self_contact_stiffness = float(self_contact_stiffness)
        use_self = model.features.self_contact if self_contact is None else bool(self_contact)
        self.self_contact = None
        if use_self:
            from simulate.contact.self_contact import SelfContact

            self.self_contact = SelfContact(model, **{**dict(self_contact_options or {}), "pairs": True})
        if not isinstance(untangle, (bool, dict)):
            raise ValueError(f"untangle must be a bool or a dict of Untangler options (got {untangle!r})")
        self.untangler = None
        if untangle:
            from simulate.contact.untangle import Untangler

            self.untangler = Untangler(model, **({} if untangle is True else untangle),
                                       share_mesh_of=self.self_contact)
        self.iterations = int(iterations)
        self.block_dim = int(block_dim)
        dev = self.device
        w = model.world_count
        starts = np.asarray(model.world_particle_start, np.int64)
        counts = np.asarray(model.world_particle_count, np.int64)
        tri_world = model.tri_world.numpy()[:model.tri_count]
        bend_world = model.bend_world.numpy()[:model.bend_count]
        colours: list[np.ndarray] = []
        cache: dict[bytes, np.ndarray] = {}
        for k in range(w):
            faces = model.tri_indices_np[tri_world == k] - starts[k]
            bend = model.bend_indices_np[bend_world == k] - starts[k]
            digest = hashlib.blake2b(np.ascontiguousarray(np.sort(faces, axis=0)).tobytes()
                                     + np.ascontiguousarray(np.sort(bend, axis=0)).tobytes()
                                     + int(counts[k]).to_bytes(8, "little"), digest_size=16).digest()
            if digest not in cache:
                cache[digest] = colour_vertices(faces, bend, int(counts[k]))
            colours.append(cache[digest])
        colour = np.concatenate(colours) if colours else np.zeros(0, np.int32)
        world = np.asarray(model.particle_world_np, np.int64)
        order = np.lexsort((np.arange(len(colour)), world, colour))  # by colour, then world, then index
        ncol = int(colour.max()) + 1 if len(colour) else 1
        keys = colour[order].astype(np.int64) * (w + 1) + world[order]
        grid = np.arange(ncol)[:, None] * (w + 1) + np.arange(w + 1)[None, :]
        offsets = np.searchsorted(keys, grid).astype(np.int32)  # (C, W + 1)
        self.colour_count = ncol
        """Vertex colours (block barriers per sweep)."""
        self._vertex_order = wp.array(order.astype(np.int32), dtype=wp.int32, device=dev)
        self._vertex_offsets = wp.array(offsets, dtype=wp.int32, device=dev)
        self._world_start = wp.array(starts.astype(np.int32), dtype=wp.int32, device=dev)
        self._world_count = wp.array(counts.astype(np.int32), dtype=wp.int32, device=dev)
        bending = bool(model.features.bending and model.bend_count > 0)
        tile = 64 * -(-int(counts.max()) // 64)
        if shared is None:
            shared = dev.is_cuda and 24 * tile <= SHARED_TILE_MAX_BYTES
        self.shared = bool(shared)
        """Whether the sweep keeps each world's positions in shared memory."""
        self._kernel = _sweep_kernel(tile if self.shared else 0, bending, self.attachments, self.body_contact,
                                     self.self_contact is not None, self.friction)
        if self.self_contact is None:  # placeholders for the kernel's self-contact arguments
            ids = wp.full((1, 1), -1, dtype=wp.int32, device=dev)
            radii = wp.zeros((1, 1), dtype=float, device=dev)
            ints = wp.zeros(1, dtype=wp.int32, device=dev)
            self._sc_pairs = [ids, radii, ints, ints, ints, wp.zeros(1, dtype=float, device=dev), ids, radii,
                              wp.zeros(1, dtype=wp.vec2i, device=dev), wp.zeros(2, dtype=wp.int32, device=dev), ints, 0.0]
            self._sc_bounds = [wp.zeros(1, dtype=wp.vec3, device=dev), wp.zeros(1, dtype=float, device=dev), 0.0, 0.0,
                               wp.zeros(1, dtype=wp.vec3, device=dev), wp.zeros(1, dtype=float, device=dev),
                               wp.zeros(1, dtype=float, device=dev), 0.0]
        else:
            sc = self.self_contact
            self._sc_pairs = [sc.vt_tri, sc.vt_radius, sc.tv_start, sc.tv_count, sc.tv_vertex, sc.tv_radius, sc.ee_edge,
                              sc.ee_radius, sc.edges,
                              sc.edge_adj_start, sc.edge_adj, self.self_contact_stiffness]
            from simulate.contact.self_contact import BOUND_CONE_SLOPE

            self._sc_bounds = [sc.x_searched, sc.d_min, sc.bound_fraction if sc.bounds else 0.0, sc.min_separation,
                               sc.bound_normal, sc.d_side, sc.d_ball,
                               BOUND_CONE_SLOPE if sc.directional_bounds else 0.0]
        n = max(model.particle_count, 1)
        self.x64 = wp.array(model.particle_q_rest_np.astype(np.float64), dtype=wp.vec3d, device=dev)
        """The solver's positions [m] in float64, shape (particle_count,); the state's float32
        positions are their rounding (see ``kernels.make_vbd_sweep_kernel``)."""
        self._x64_prev = wp.zeros(n, dtype=wp.vec3d, device=dev)
        self._target = wp.zeros(n, dtype=wp.vec3, device=dev)
        self._predicted = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.gravity_share = wp.ones(n, dtype=float, device=dev)
        """Share of gravity (0..1) each particle's last substep accelerated it by, shape
        (particle_count,); the next substep starts at x + dt v + share dt^2 g."""

    def positions_set(self, start: int, count: int) -> None:
        """Set particles start a fresh history: the share of gravity of their first substep is 1,
        as in a new solver (see ``SolverBase.positions_set``)."""
        self.gravity_share[start:start + count].fill_(1.0)

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl,
             contacts: BodyCollider | None, dt: float, *,
             substep: int = 0) -> None:
        """Advance one substep of ``dt`` [s] from ``state_in`` into ``state_out`` (no allocation).

        ``substep`` is the substep's index in its frame (body contact queries on multiples of
        ``contact_detect_every``)."""
        self._check(state_in, state_out, contacts, dt)
        m = self.model
        dev = self.device
        wp.launch(kernels.predict_particles, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, m.particle_world, control.world_active, self.gravity, float(dt),
                          state_in.particle_q, state_in.particle_qd, self.gravity_share, self.x64],
                  outputs=[self._x64_prev, self._target, self._predicted, state_out.particle_q], device=dev)
        self.detect_contacts(self._predicted, contacts, control, substep)
        sc = self.self_contact
        if sc is not None:
            if substep % sc.detect_every == 0:
                sc.detect(state_in.particle_q, control.world_active, state_in.particle_qd, dt,
                          world_self_contact=control.world_self_contact,
                          refresh=(substep // sc.detect_every) % sc.search_every != 0)
        try:
            wp.launch_tiled(self._kernel, dim=[m.world_count],
                            inputs=[self._world_start, self._world_count, self._vertex_offsets, self._vertex_order,
                                    m.particle_inv_mass, m.particle_adj_start, m.particle_adj_slot, int(m.tri_count),
                                    m.tri_indices, m.tri_dm_inv, m.tri_compliance, m.bend_indices, m.bend_rest_angle,
                                    m.bend_compliance, control.world_active, 1.0 / (dt * dt), self.iterations,
                                    m.particle_attachment, control.attachment_target,
                                    control.world_attachment_stiffness, control.world_attachment_enabled,
                                    self.contact_active, self.contact_normal, self.contact_offset, self.contact_motion,
                                    m.world_friction, FRICTION_SLIP_SPEED * float(dt), self._x64_prev, self._target,
                                    *self._sc_pairs, *self._sc_bounds, control.world_self_contact, self.x64],
                            block_dim=self.block_dim, device=dev)
        except RuntimeError as err:
            if "too many resources" not in str(err):
                raise
            # the sweep's registers per thread times block_dim exceed the SM's (one H100: 512
            # threads fail with self-contact on)
            raise ValueError(f"SolverVBD block_dim={self.block_dim}: the sweep kernel needs more registers per "
                             f"block than {dev} has; expected 256 or fewer threads per world block") from None
        wp.launch(kernels.finalize_particles_vbd, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, m.particle_world, control.world_active, m.world_damping,
                          self.extra_damping, self.gravity, float(dt), self._x64_prev, state_in.particle_qd,
                          self.x64],
                  outputs=[state_out.particle_q, state_out.particle_qd, self.gravity_share], device=dev)
        if self.untangler is not None and substep % self.untangler.every == 0:
            self.untangler.apply(state_out.particle_q, control.world_active, control.world_self_contact, x64=self.x64,
                                 v=state_out.particle_qd, dt=dt)
