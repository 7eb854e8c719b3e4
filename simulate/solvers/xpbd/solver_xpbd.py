"""SolverXPBD: extended position-based dynamics (compliance form) for batched cloth worlds."""

from __future__ import annotations

import warp as wp

from simulate.cloth.model import ClothControl, ClothModel, ClothState
from simulate.solvers import common_kernels as ck
from simulate.solvers.base import SolverBase
from simulate.solvers.xpbd import kernels

__all__ = ["SolverXPBD"]

MODES = ("gauss_seidel", "jacobi")


class SolverXPBD(SolverBase):
    """XPBD with per-substep iterations (Macklin, Mueller, Chentanez 2016).

    Constraints: triangle stretch (two material directions) and shear, dihedral bending,
    attachments (soft, releasable), body contact (hard, one plane per particle found once per
    substep) with Coulomb friction, pinning (inverse mass 0).  Compliance alpha = 1 / (k dt^2).

    ``mode="gauss_seidel"`` sweeps the graph colours computed at finalize (one launch per
    colour, in place); ``mode="jacobi"`` projects all elements from the same positions, each
    element taking the share ``jacobi_relaxation / max_k n_k`` of its step (n_k = elements
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
        gs_relaxation: float = 1.0,
        bending_mode: str | None = None,
        body_contact: bool | None = None,
        extra_damping: float = 0.0,
        self_contact: bool | None = None,
        self_contact_options: dict | None = None,
    ) -> None:
        """
        Args:
            model: cloth model.
            iterations: constraint iterations per substep (>= 1).
            mode: "gauss_seidel" (graph colouring) or "jacobi" (averaged).
            jacobi_relaxation: over-relaxation of the averaged Jacobi correction (0, 2).
            gs_relaxation: successive over-relaxation of the Gauss-Seidel multiplier steps (0, 2).
            bending_mode: sweep of the bending elements, "gauss_seidel" (one launch per bending
                colour) or "jacobi" (one launch, gathered by the particle pass); default = ``mode``.
                Gauss-Seidel triangles with Jacobi bending cut the launches per iteration from
                (triangle colours + bending colours + 1), e.g. 8 + 14 + 1 on a grid, to 8 + 2.
            body_contact: contact with ``control.collider`` (default from model.features).
            extra_damping: damping rate added to each fabric's [1/s].
            self_contact: vertex-triangle self-contact (default from model.features).
            self_contact_options: keyword options of :class:`~simulate.contact.self_contact.SelfContact`
                (thickness, margin, rest_exclusion, relaxation, detect_every).
        """
        super().__init__(model, body_contact=body_contact, extra_damping=extra_damping)
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
        if not 0.0 < gs_relaxation < 2.0:
            raise ValueError(f"gs_relaxation must be in (0, 2) (got {gs_relaxation!r})")
        self.jacobi_relaxation = float(jacobi_relaxation)
        self.gs_relaxation = float(gs_relaxation)
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

            self.self_contact = SelfContact(model, **dict(self_contact_options or {}))
        self.self_delta = self.self_contact.delta if self.self_contact else wp.zeros(1, dtype=wp.vec3, device=dev)
        self._particle_kernel = ck.make_particle_constraints_kernel(
            self._gather, self.body_contact, self.attachments, self.self_contact is not None)
        self._tri_ranges = [(a, b - a) for a, b in zip(model.tri_colour_offsets[:-1], model.tri_colour_offsets[1:])
                            if b > a]
        self._bend_ranges = [(a, b - a) for a, b in
                             zip(model.bend_colour_offsets[:-1], model.bend_colour_offsets[1:]) if b > a]

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float, *,
             substep: int = 0) -> None:
        """Advance one substep of ``dt`` [s] from ``state_in`` into ``state_out`` (no allocation).

        ``substep`` is the substep's index in its frame: self-contact candidates are found again
        on substeps that are multiples of its ``detect_every`` (always with the default 0)."""
        self._check(state_in, state_out, control, dt)
        m = self.model
        dev = self.device
        inv_dt2 = 1.0 / (dt * dt)
        x = state_out.particle_q
        wp.launch(ck.integrate_particles, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, m.particle_world, control.world_active, self.gravity, float(dt),
                          state_in.particle_q, state_in.particle_qd], outputs=[x], device=dev)
        self.detect_contacts(x, control)
        if self.self_contact is not None and substep % self.self_contact.detect_every == 0:
            self.self_contact.detect(state_in.particle_q, control.world_active, state_in.particle_qd, dt)
        self.tri_lambda.zero_()
        self.bend_lambda.zero_()
        if self.attachments:
            self.attachment_lambda.zero_()
        jacobi = self.mode == "jacobi"
        bend_jacobi = self.bending_mode == "jacobi" and m.bend_count > 0
        particle_inputs = None
        for _ in range(self.iterations):
            if jacobi:
                wp.launch(kernels.solve_triangles_jacobi, dim=m.tri_count,
                          inputs=[m.tri_indices, m.tri_dm_inv, m.tri_compliance, m.tri_world, m.tri_jacobi_scale,
                                  m.particle_inv_mass, control.world_active, inv_dt2, self.jacobi_relaxation, x,
                                  self.tri_lambda],
                          outputs=[self.slot_delta], device=dev)
            else:
                for offset, count in self._tri_ranges:
                    wp.launch(kernels.solve_triangles_gs, dim=count,
                              inputs=[offset, m.tri_indices, m.tri_dm_inv, m.tri_compliance, m.tri_world,
                                      m.particle_inv_mass, control.world_active, inv_dt2, self.gs_relaxation,
                                      self.tri_lambda, x],
                              device=dev)
            if bend_jacobi:
                wp.launch(kernels.solve_bending_jacobi, dim=m.bend_count,
                          inputs=[3 * m.tri_count, m.bend_indices, m.bend_rest_angle, m.bend_compliance,
                                  m.bend_world, m.bend_jacobi_scale, m.particle_inv_mass, control.world_active,
                                  inv_dt2, self.jacobi_relaxation, x, self.bend_lambda],
                          outputs=[self.slot_delta], device=dev)
            else:
                for offset, count in self._bend_ranges:
                    wp.launch(kernels.solve_bending_gs, dim=count,
                              inputs=[offset, m.bend_indices, m.bend_rest_angle, m.bend_compliance, m.bend_world,
                                      m.particle_inv_mass, control.world_active, inv_dt2, self.gs_relaxation,
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
        self.finalize_substep(state_in, state_out, control, dt)
