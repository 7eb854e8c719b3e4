"""SolverXPBD: extended position-based dynamics (compliance form) for batched cloth worlds."""

from __future__ import annotations

import functools
import hashlib
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from simulate.cloth.model import ClothControl, ClothModel, ClothState, world_colour_offsets
from simulate.solvers import common_kernels as ck
from simulate.solvers.base import SolverBase
from simulate.solvers.xpbd import kernels

if TYPE_CHECKING:
    from simulate.contact.body_collider import BodyCollider

__all__ = ["SolverXPBD"]

MODES = ("gauss_seidel", "jacobi")
GS_SWEEPS = ("world_blocks", "colour_launches")
GS_STEP = 1.0
"""Share of each Gauss-Seidel multiplier step taken (the kernels' ``relaxation``, which the Jacobi
sweep scales per element): the full step."""
SHARED_TILE_MAX_BYTES = 160 * 1024
"""On CUDA, world blocks keep their positions in shared memory when a world's tile (12 bytes per
particle, rounded up to 64 particles) is at most this (13,600 particles; an H100/H200 SM has
228 KB); larger worlds sweep in global memory."""
_shared_kernel = functools.cache(kernels.make_elements_gs_shared_kernel)
"""One shared-memory sweep kernel per tile size (Warp compiles each once)."""


def local_topology(world_offsets: np.ndarray, indices: np.ndarray, element_world: np.ndarray,
                   world_start: np.ndarray) -> tuple[np.ndarray, np.ndarray, bool]:
    """Element corners as indices local to their world, one table for all worlds when they can share it.

    Args:
        world_offsets: ``world_colour_offsets`` of the elements, int (C, W + 1).
        indices: element corners, global particle indices, (E, K).
        element_world: world of each element, (E,).
        world_start: first particle of each world, (W,).
    Returns:
        (shift (C, W) int32, local (R, K) int32, shared): element ``t`` of colour ``c`` in world ``w``
        has the world-local corners ``local[t - shift[c, w]]``. ``shared``: every world has the same
        local corners in the same order within each colour (one garment topology, coloured alike),
        and ``local`` holds them once (R = E / W); otherwise ``local`` has a row per element and
        ``shift`` is 0.
    """
    world_offsets = np.asarray(world_offsets, np.int64)
    colours, worlds = world_offsets.shape[0], world_offsets.shape[1] - 1
    indices = np.asarray(indices, np.int64)
    if indices.ndim != 2 or len(indices) != len(element_world):
        raise ValueError(f"indices must have shape ({len(element_world)}, K), one row per element (got {indices.shape})")
    local = indices - np.asarray(world_start, np.int64)[np.asarray(element_world, np.int64)][:, None]
    counts = np.diff(world_offsets, axis=1)
    shared = worlds > 0 and bool((counts == counts[:, :1]).all())
    rows = []
    for c in range(colours if shared else 0):
        n = int(counts[c, 0])
        block = local[world_offsets[c, 0]:world_offsets[c, worlds]].reshape(worlds, n, indices.shape[1])
        if not (block == block[:1]).all():
            shared = False
            break
        rows.append(block[0])
    if not shared:
        return np.zeros((colours, max(worlds, 1)), np.int32), local.astype(np.int32), False
    starts = np.concatenate([[0], np.cumsum(counts[:, 0])[:-1]])
    shift = world_offsets[:, :worlds] - starts[:, None]
    return shift.astype(np.int32), np.concatenate(rows).astype(np.int32).reshape(-1, indices.shape[1]), True


def shared_element_data(tri_offsets: np.ndarray, tri_data: list[np.ndarray], bend_offsets: np.ndarray,
                        bend_data: list[np.ndarray], inv_mass: np.ndarray, world_start: np.ndarray,
                        world_count: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Which world's copy of its element data each world may read: the first world with equal values.

    Valid for worlds that share one local topology (``local_topology``): the same element counts
    per colour and the same corners in the same order, so element ``k`` of colour ``c`` plays the
    same part in every world. Two worlds then share data when, colour by colour, every element
    array (rest shape, compliance, rest angle) and every inverse mass is equal bit for bit.

    Args:
        tri_offsets, bend_offsets: ``world_colour_offsets`` of triangles and bending elements, (C, W + 1).
        tri_data, bend_data: per-element arrays of each kind, each with one row per element.
        inv_mass: particle inverse masses, (N,).
        world_start, world_count: each world's first particle and particle count, (W,).
    Returns:
        (tri_dshift (C, W), bend_dshift (C', W), data_start (W,), source (W,)), int32: world ``w``
        reads element ``t`` of colour ``c`` at ``t - dshift[c, w]`` and the inverse mass of its
        local particle ``j`` at ``data_start[w] + j``, both in world ``source[w]``.
    """
    world_start = np.asarray(world_start, np.int64)
    world_count = np.asarray(world_count, np.int64)
    tri_offsets = np.asarray(tri_offsets, np.int64)
    bend_offsets = np.asarray(bend_offsets, np.int64)
    worlds = len(world_start)

    def rows(offsets: np.ndarray, w: int) -> np.ndarray:
        return np.concatenate([np.arange(offsets[c, w], offsets[c, w + 1]) for c in range(offsets.shape[0])]
                              + [np.zeros(0, np.int64)])

    def values(w: int) -> list[np.ndarray]:
        tr, br = rows(tri_offsets, w), rows(bend_offsets, w)
        return ([np.ascontiguousarray(a[tr]) for a in tri_data] + [np.ascontiguousarray(a[br]) for a in bend_data]
                + [np.ascontiguousarray(inv_mass[world_start[w]:world_start[w] + world_count[w]])])

    first: dict[bytes, tuple[int, list[np.ndarray]]] = {}
    source = np.arange(worlds)
    for w in range(worlds):
        mine = values(w)
        digest = hashlib.blake2b(digest_size=16)
        for part in mine:
            digest.update(part.tobytes())
        k, theirs = first.setdefault(digest.digest(), (w, mine))
        if k != w and all(np.array_equal(a, b) for a, b in zip(mine, theirs)):  # equal, not only a digest match
            source[w] = k
    tri_dshift = tri_offsets[:, :worlds] - tri_offsets[:, source]
    bend_dshift = bend_offsets[:, :worlds] - bend_offsets[:, source]
    return (tri_dshift.astype(np.int32), bend_dshift.astype(np.int32), world_start[source].astype(np.int32),
            source.astype(np.int32))


class SolverXPBD(SolverBase):
    """XPBD with per-substep iterations (Macklin, Mueller, Chentanez 2016).

    Constraints: triangle stretch (two material directions) and shear, dihedral bending,
    attachments (soft, releasable), body contact (hard, one plane per particle found once per
    substep) with Coulomb friction, pinning (inverse mass 0).  Compliance alpha = 1 / (k dt^2).

    ``mode="gauss_seidel"`` sweeps the graph colours computed at finalize, in place: by default
    (``gs_sweep="world_blocks"``) one launch per iteration with one thread block per world and a
    block barrier between colours, or one launch per colour (``"colour_launches"``; same result,
    3,300 launches per frame on the 7.7k t-shirt at 10 x 10).  ``mode="jacobi"`` projects all
    elements from the same positions, each element taking the share ``jacobi_relaxation / max_k n_k`` of its step (n_k = elements
    of its kind at its corner k), and sums the corrections per particle.  Both are
    deterministic (no float atomics).
    """

    def __init__(
        self,
        model: ClothModel,
        *,
        iterations: int = 10,
        mode: str = "gauss_seidel",
        jacobi_relaxation: float = 1.0,
        bending_mode: str | None = None,
        body_contact: bool | None = None,
        extra_damping: float = 0.0,
        self_contact: bool | None = None,
        self_contact_options: dict | None = None,
        gs_sweep: str = "world_blocks",
        gs_block_dim: int = 256,
        gs_shared: bool | None = None,
        contact_detect_every: int = 1,
        share_element_data: bool = True,
        untangle: bool | dict = False,
    ) -> None:
        """
        Args:
            model: cloth model.
            iterations: constraint iterations per substep (>= 1).
            mode: "gauss_seidel" (graph colouring) or "jacobi" (averaged).
            jacobi_relaxation: over-relaxation of the averaged Jacobi correction (0, 2).
            bending_mode: sweep of the bending elements, "gauss_seidel" (one launch per bending
                colour) or "jacobi" (one launch, gathered by the particle pass); default = ``mode``.
                Gauss-Seidel triangles with Jacobi bending cut the launches per iteration from
                (triangle colours + bending colours + 1), e.g. 8 + 14 + 1 on a grid, to 8 + 2.
            body_contact: contact with the body passed to ``step`` (default from model.features).
            extra_damping: damping rate added to each fabric's [1/s].
            self_contact: vertex-triangle self-contact (default from model.features).
            self_contact_options: keyword options of :class:`~simulate.contact.self_contact.SelfContact`
                (thickness, margin, rest_exclusion, relaxation, detect_every).
            gs_sweep: how the Gauss-Seidel colours are launched: "world_blocks" (one launch per
                iteration, a block per world) or "colour_launches" (one launch per colour).
            gs_block_dim: threads per world block (CUDA; CPU runs one lane per block).
            gs_shared: world blocks sweep the positions in a shared-memory tile (True) or in global
                memory (False); None = on CUDA when the tile fits ``SHARED_TILE_MAX_BYTES``.  On
                CPU both give the same result at the same speed, and each tile size is a kernel
                of its own to compile.
            contact_detect_every: body queries on every N-th substep of a frame, the planes moved
                with the body in between (see ``SolverBase``).
            share_element_data: the shared-memory sweep reads one copy of the element data of worlds
                that repeat a garment (``shared_element_data``); same result, less memory traffic.
            untangle: after each substep's iterations, before its velocities, one step of
                intersection contour minimization (:class:`~simulate.contact.untangle.Untangler`;
                a dict gives its keyword options) in worlds whose ``control.world_self_contact``
                is on.
        """
        super().__init__(model, body_contact=body_contact, extra_damping=extra_damping,
                         contact_detect_every=contact_detect_every)
        if int(iterations) != iterations or iterations < 1:
            raise ValueError(f"iterations must be an integer >= 1 (got {iterations!r})")
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES} (got {mode!r})")
        if not 0.0 < jacobi_relaxation < 2.0:
            raise ValueError(f"jacobi_relaxation must be in (0, 2) (got {jacobi_relaxation!r})")
        self.iterations = int(iterations)
        self.mode = mode
        self.bending_mode = mode if bending_mode is None else bending_mode
        if self.bending_mode not in MODES:
            raise ValueError(f"bending_mode must be one of {MODES} (got {bending_mode!r})")
        if gs_sweep not in GS_SWEEPS:
            raise ValueError(f"gs_sweep must be one of {GS_SWEEPS} (got {gs_sweep!r})")
        if int(gs_block_dim) != gs_block_dim or not 32 <= gs_block_dim <= 1024 or gs_block_dim % 32:
            raise ValueError(f"gs_block_dim must be a multiple of 32 in [32, 1024] (got {gs_block_dim!r})")
        self.gs_sweep = gs_sweep
        self.gs_block_dim = int(gs_block_dim)
        self.jacobi_relaxation = float(jacobi_relaxation)
        dev = self.device
        self.tri_lambda = wp.zeros(max(model.tri_count, 1), dtype=wp.vec3, device=dev)
        self.bend_lambda = wp.zeros(max(model.bend_count, 1), dtype=float, device=dev)
        # Slots of elements swept by Jacobi; others stay zero, so the gather may read all of them.
        self._gather = mode == "jacobi" or (self.bending_mode == "jacobi" and model.bend_count > 0)
        slots = 3 * model.tri_count + 4 * model.bend_count if self._gather else 0
        self.slot_delta = wp.zeros(max(slots, 1), dtype=wp.vec3, device=dev)
        use_self = model.features.self_contact if self_contact is None else bool(self_contact)
        self.self_contact = None
        if use_self:
            from simulate.contact.self_contact import SelfContact

            self.self_contact = SelfContact(model, **{"bounds": False, **dict(self_contact_options or {})})  # pushes only
        self.self_delta = self.self_contact.delta if self.self_contact else wp.zeros(1, dtype=wp.vec3, device=dev)
        self.bounds = bool(self.self_contact is not None and self.self_contact.bounds)
        """Whether each particle keeps within its self-contact displacement bound (after every
        iteration and after friction), so no new crossing forms."""
        if self.bounds:
            sc = self.self_contact
            self._bound_args = [sc.x_searched, sc.d_min, sc.bound_fraction, sc.min_separation]
            self._finalize_kernel = ck.make_finalize_kernel(self.friction, True)
        self.untangler = None
        if not isinstance(untangle, (bool, dict)):
            raise ValueError(f"untangle must be a bool or a dict of Untangler options (got {untangle!r})")
        if untangle:
            from simulate.contact.untangle import Untangler

            self.untangler = Untangler(model, **({} if untangle is True else untangle),
                                       share_mesh_of=self.self_contact)
        self._no_candidates = wp.full(1, -1, dtype=wp.int32, device=dev)  # the tiled kernel's arguments
        self._no_side = wp.ones(1, dtype=float, device=dev)  # without self-contact
        self._particle_kernel = ck.make_particle_constraints_kernel(
            self._gather, self.body_contact, self.attachments, self.self_contact is not None)
        self._tri_ranges = [(a, b - a) for a, b in zip(model.tri_colour_offsets[:-1], model.tri_colour_offsets[1:])
                            if b > a]
        self._bend_ranges = [(a, b - a) for a, b in
                             zip(model.bend_colour_offsets[:-1], model.bend_colour_offsets[1:]) if b > a]
        self._world_blocks = mode == "gauss_seidel" and gs_sweep == "world_blocks"
        self._fused = False
        self.element_data_source = None
        self.shared_topology = False
        """Whether the shared-memory sweep reads one table of world-local element corners that
        every world shares (``local_topology``)."""
        if self._world_blocks:
            w = model.world_count
            tri_world = model.tri_world.numpy()[:model.tri_count]
            bend_world = model.bend_world.numpy()[:model.bend_count]
            tri_offsets = world_colour_offsets(model.tri_colour_offsets, tri_world, w)
            bend_gs = self.bending_mode == "gauss_seidel" and model.bend_count > 0
            bend_offsets = world_colour_offsets(model.bend_colour_offsets if bend_gs else [0],
                                                bend_world if bend_gs else np.zeros(0), w)
            self._tri_world_offsets = wp.array(tri_offsets, dtype=wp.int32, device=dev)
            self._bend_world_offsets = wp.array(bend_offsets, dtype=wp.int32, device=dev)
            tile = 64 * -(-int(np.max(model.world_particle_count)) // 64)
            if gs_shared is None:
                gs_shared = dev.is_cuda and 12 * tile <= SHARED_TILE_MAX_BYTES
            # The whole substep in one launch when the particle pass has no Jacobi gather: its
            # attachments, body contact and self-contact pushes run between the sweeps in the tile.
            self._fused = bool(gs_shared and not self._gather)
            self._shared_kernel = (_shared_kernel(tile, self._fused, self.body_contact and self._fused,
                                                  self.attachments and self._fused,
                                                  self.self_contact is not None and self._fused,
                                                  self.bounds and self._fused)
                                   if gs_shared else None)
            if gs_shared:  # where each world's tile starts and how much of it is the world's
                self._world_start = wp.array(model.world_particle_start, dtype=wp.int32, device=dev)
                self._world_count = wp.array(model.world_particle_count, dtype=wp.int32, device=dev)
                self._local_topology = []  # (shift, local) of triangles, then of bending elements
                shared_both = True
                for offsets, indices, world in ((tri_offsets, model.tri_indices_np, tri_world),
                                                (bend_offsets, model.bend_indices_np, bend_world)):
                    shift, local, shared = local_topology(offsets, indices, world, model.world_particle_start)
                    if len(local) == 0:  # Warp kernels need a non-empty array argument
                        local = np.zeros((1, indices.shape[1]), np.int32)
                    self._local_topology += [wp.array(shift, dtype=wp.int32, device=dev),
                                             wp.array(local, dtype=wp.int32, device=dev)]
                    shared_both &= shared
                self.shared_topology = shared_both
                starts = np.asarray(model.world_particle_start, np.int32)
                if shared_both and share_element_data:
                    tri_dshift, bend_dshift, data_start, source = shared_element_data(
                        tri_offsets, [model.tri_dm_inv.numpy()[:model.tri_count],
                                      model.tri_compliance.numpy()[:model.tri_count]],
                        bend_offsets, [model.bend_rest_angle.numpy()[:model.bend_count],
                                       model.bend_compliance.numpy()[:model.bend_count]],
                        np.asarray(model.particle_inv_mass_np), starts, model.world_particle_count)
                else:
                    tri_dshift = np.zeros_like(tri_offsets[:, :w])
                    bend_dshift = np.zeros_like(bend_offsets[:, :w])
                    data_start, source = starts, np.arange(w, dtype=np.int32)
                self.element_data_source = source
                self._element_data_np = (tri_dshift, bend_dshift, np.asarray(data_start, np.int32))
                self._colour_offsets_np = (tri_offsets, bend_offsets)
                """World whose element data (rest shapes, compliances, inverse masses) each world's
                tiled sweep reads (``shared_element_data``); each world's own without sharing."""
                self._element_data = [wp.array(tri_dshift, dtype=wp.int32, device=dev),
                                      wp.array(bend_dshift, dtype=wp.int32, device=dev),
                                      wp.array(data_start, dtype=wp.int32, device=dev)]

    def garment_changed(self, dst: int, src: int) -> None:
        """World ``dst`` now holds world ``src``'s garment: the tiled sweep reads the element data
        ``src`` reads (``shared_element_data``; the same values as ``dst``'s own copy, one copy in
        L2), and the self-contact search excludes ``dst``'s pairs by ``src``'s rest shape."""
        source = self.element_data_source
        if source is not None:
            tri_dshift, bend_dshift, data_start = self._element_data_np
            starts = np.asarray(self.model.world_particle_start, np.int32)

            def read_from(w: int, k: int) -> None:
                """World ``w`` reads world ``k``'s element data (the same values)."""
                for shift, offsets in ((tri_dshift, self._colour_offsets_np[0]),
                                       (bend_dshift, self._colour_offsets_np[1])):
                    shift[:, w] = offsets[:, w] - offsets[:, k]  # w's k-th element of colour c at k's
                data_start[w] = starts[k]
                source[w] = k

            # worlds that read dst's copy keep their garment: the first of them serves the others now
            readers = [w for w in range(len(source)) if w != dst and source[w] == dst]
            for w in readers:
                read_from(w, readers[0])
            read_from(dst, int(source[src]))
            for arr, host in zip(self._element_data, self._element_data_np):
                arr.assign(host)
        if self.self_contact is not None:
            n = int(self.model.world_particle_count[src])
            wp.copy(self.self_contact.rest, self.self_contact.rest, dest_offset=int(self.model.world_particle_start[dst]),
                    src_offset=int(self.model.world_particle_start[src]), count=n)

    @property
    def element_data_copies(self) -> int | None:
        """Copies of element data the tiled sweep reads (the batch's distinct garments when worlds
        share them); None without the shared-memory sweep."""
        return None if self.element_data_source is None else len(np.unique(self.element_data_source))

    def _block_args(self, control: ClothControl, inv_dt2: float) -> list:
        """The world-block kernels' model arguments, up to the relaxation."""
        m = self.model
        return [self._tri_world_offsets, m.tri_indices, m.tri_dm_inv, m.tri_compliance, self._bend_world_offsets,
                m.bend_indices, m.bend_rest_angle, m.bend_compliance, m.particle_inv_mass, control.world_active,
                inv_dt2, GS_STEP]

    def _shared_args(self, control: ClothControl, inv_dt2: float) -> list:
        """The shared-memory kernel's model arguments, up to the relaxation."""
        m = self.model
        tri_shift, tri_local, bend_shift, bend_local = self._local_topology
        return [self._world_start, self._world_count, self._tri_world_offsets, tri_shift, tri_local, m.tri_dm_inv,
                m.tri_compliance, self._bend_world_offsets, bend_shift, bend_local, m.bend_rest_angle,
                m.bend_compliance, m.particle_inv_mass, *self._element_data, control.world_active, inv_dt2,
                GS_STEP]

    def _particle_pass_args(self, control: ClothControl) -> list:
        """The shared-memory kernel's particle-pass arguments (attachments, body contact, then
        self-contact)."""
        sc = self.self_contact
        if sc is None:
            self_args = [self._no_candidates, self._no_side, 0.0, 0.0, self.self_delta]
        else:
            self_args = [sc.candidate, sc.side, sc.thickness, sc.relaxation, sc.delta]
        if self.bounds:
            self_args += self._bound_args
        else:
            self_args += [self.contact_normal, self.contact_depth, 0.0, 0.0]
        return [self.model.particle_attachment, control.attachment_target, control.world_attachment_stiffness,
                control.world_attachment_enabled, self.attachment_lambda, self.contact_active, self.contact_normal,
                self.contact_offset, self.contact_depth, self.model.tri_indices, *self_args,
                control.world_self_contact]

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl,
             contacts: BodyCollider | None, dt: float, *,
             substep: int = 0) -> None:
        """Advance one substep of ``dt`` [s] from ``state_in`` into ``state_out`` (no allocation).

        ``substep`` is the substep's index in its frame: body contact planes and self-contact
        candidates are found again on substeps that are multiples of ``contact_detect_every`` and
        of the self-contact's ``detect_every`` (always with the default 0)."""
        self._check(state_in, state_out, contacts, dt)
        m = self.model
        dev = self.device
        inv_dt2 = 1.0 / (dt * dt)
        x = state_out.particle_q
        wp.launch(ck.integrate_particles, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, m.particle_world, control.world_active, self.gravity, float(dt),
                          state_in.particle_q, state_in.particle_qd], outputs=[x], device=dev)
        self.detect_contacts(x, contacts, control, substep)
        if self.self_contact is not None and substep % self.self_contact.detect_every == 0:
            self.self_contact.detect(state_in.particle_q, control.world_active, state_in.particle_qd, dt,
                                     world_self_contact=control.world_self_contact)
        self.tri_lambda.zero_()
        self.bend_lambda.zero_()
        if self.attachments:
            self.attachment_lambda.zero_()
        jacobi = self.mode == "jacobi"
        bend_jacobi = self.bending_mode == "jacobi" and m.bend_count > 0
        if self._fused:
            # Every iteration's sweep and particle pass in one launch, positions in shared memory.
            wp.launch_tiled(self._shared_kernel, dim=[m.world_count],
                            inputs=[*self._shared_args(control, inv_dt2),
                                    self.iterations, *self._particle_pass_args(control), self.tri_lambda,
                                    self.bend_lambda, x],
                            block_dim=self.gs_block_dim, device=dev)
            if self.untangler is not None and substep % self.untangler.every == 0:
                self.untangler.apply(x, control.world_active, control.world_self_contact)
            self.finalize_substep(state_in, state_out, control, dt)
            return
        particle_inputs = None
        for _ in range(self.iterations):
            if jacobi:
                wp.launch(kernels.solve_triangles_jacobi, dim=m.tri_count,
                          inputs=[m.tri_indices, m.tri_dm_inv, m.tri_compliance, m.tri_world, m.tri_jacobi_scale,
                                  m.particle_inv_mass, control.world_active, inv_dt2, self.jacobi_relaxation, x,
                                  self.tri_lambda],
                          outputs=[self.slot_delta], device=dev)
            elif self._world_blocks:
                # Triangles, then bending unless it is swept by Jacobi (its offsets are empty then).
                if self._shared_kernel is not None:  # one iteration; the particle kernel follows
                    wp.launch_tiled(self._shared_kernel, dim=[m.world_count],
                                    inputs=[*self._shared_args(control, inv_dt2), 1,
                                            *self._particle_pass_args(control), self.tri_lambda, self.bend_lambda, x],
                                    block_dim=self.gs_block_dim, device=dev)
                else:
                    wp.launch_tiled(kernels.solve_elements_gs_world_blocks, dim=[m.world_count],
                                    inputs=[*self._block_args(control, inv_dt2), self.tri_lambda, self.bend_lambda, x],
                                    block_dim=self.gs_block_dim, device=dev)
            else:
                for offset, count in self._tri_ranges:
                    wp.launch(kernels.solve_triangles_gs, dim=count,
                              inputs=[offset, m.tri_indices, m.tri_dm_inv, m.tri_compliance, m.tri_world,
                                      m.particle_inv_mass, control.world_active, inv_dt2, GS_STEP,
                                      self.tri_lambda, x],
                              device=dev)
            if bend_jacobi:
                wp.launch(kernels.solve_bending_jacobi, dim=m.bend_count,
                          inputs=[3 * m.tri_count, m.bend_indices, m.bend_rest_angle, m.bend_compliance,
                                  m.bend_world, m.bend_jacobi_scale, m.particle_inv_mass, control.world_active,
                                  inv_dt2, self.jacobi_relaxation, x, self.bend_lambda],
                          outputs=[self.slot_delta], device=dev)
            elif not self._world_blocks:
                for offset, count in self._bend_ranges:
                    wp.launch(kernels.solve_bending_gs, dim=count,
                              inputs=[offset, m.bend_indices, m.bend_rest_angle, m.bend_compliance, m.bend_world,
                                      m.particle_inv_mass, control.world_active, inv_dt2, GS_STEP,
                                      self.bend_lambda, x],
                              device=dev)
            if self.self_contact is not None:
                self.self_contact.project(x, control.world_active)
            if particle_inputs is None:
                particle_inputs = [
                    m.particle_inv_mass, m.particle_world, control.world_active, inv_dt2,
                    m.particle_adj_start, m.particle_adj_slot, self.slot_delta,
                    self.self_delta,
                    m.particle_attachment, control.attachment_target, control.world_attachment_stiffness,
                    control.world_attachment_enabled, self.attachment_lambda,
                    self.contact_active, self.contact_normal, self.contact_offset, self.contact_depth,
                    x,
                ]
            wp.launch(self._particle_kernel, dim=m.particle_count, inputs=particle_inputs, device=dev)
            if self.bounds:
                wp.launch(ck.clamp_to_bounds, dim=m.particle_count,
                          inputs=[m.particle_inv_mass, m.particle_world, control.world_active,
                                  control.world_self_contact, *self._bound_args, x], device=dev)
        if self.untangler is not None and substep % self.untangler.every == 0:  # before the velocities, which carry the step on (Untangler)
            self.untangler.apply(x, control.world_active, control.world_self_contact)
        self.finalize_substep(state_in, state_out, control, dt)
