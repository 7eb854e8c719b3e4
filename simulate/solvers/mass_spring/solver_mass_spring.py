"""SolverMassSpring: semi-implicit (symplectic) Euler on the same cloth energy as XPBD.

Forces are the negative gradients of the energy in ``simulate.cloth.fabric`` (triangle stretch
and shear springs, dihedral bending springs), plus gravity, mass-proportional damping and
attachment springs.  Contact: position projection onto the per-substep contact plane,
removal of the approaching normal velocity and Coulomb friction on the tangential velocity
relative to the body.

Stable time step: semi-implicit Euler is stable for dt < 2 / omega_max, omega_max^2 the largest
eigenvalue of M^-1 K.  We bound it per particle (Gershgorin) by summing, over the elements at
the particle, each element's own constraint eigenvalue k_e * sum_j |grad_j C_e|^2 / m_j
(evaluated at rest) plus k_attach / m_i; ``stable_dt()`` returns 2 / sqrt(max bound), and
``substeps_for(frame_dt)`` the substeps needed at ``safety`` times that step.  For real fabrics
this is small (cotton with 1 cm edges: ~1e-4 s, i.e. >100 substeps per 60 fps frame), which is
why XPBD is the production solver and this one the second opinion.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from simulate.cloth.model import ClothControl, ClothModel, ClothState
from simulate.solvers.base import SolverBase
from simulate.solvers.mass_spring import kernels

if TYPE_CHECKING:
    from simulate.contact.body_collider import BodyCollider

__all__ = ["SolverMassSpring"]


class SolverMassSpring(SolverBase):
    """Explicit mass-spring cloth solver (second opinion for XPBD)."""

    def __init__(self, model: ClothModel, *, body_contact: bool | None = None, extra_damping: float = 0.0,
                 safety: float = 0.5, contact_detect_every: int = 1) -> None:
        """
        Args:
            model: cloth model.
            body_contact: contact with the body passed to ``step`` (default from model.features).
            extra_damping: damping rate added to each fabric's [1/s].
            safety: fraction of the stable step used by ``substeps_for`` (0, 1].
            contact_detect_every: body queries on every N-th substep (see ``SolverBase``).
        """
        super().__init__(model, body_contact=body_contact, extra_damping=extra_damping,
                         contact_detect_every=contact_detect_every)
        if model.features.self_contact:
            raise ValueError("Features.self_contact is implemented by SolverXPBD only; use solver='xpbd' or "
                             "build the model with Features(self_contact=False)")
        if not 0.0 < safety <= 1.0:
            raise ValueError(f"safety must be in (0, 1] (got {safety!r})")
        self.safety = float(safety)
        slots = 3 * model.tri_count + 4 * model.bend_count
        self.slot_force = wp.zeros(max(slots, 1), dtype=wp.vec3, device=self.device)
        self._integrate_kernel = kernels.make_integrate_kernel(self.attachments)

    def stable_dt(self) -> float:
        """Upper bound [s] of a stable semi-implicit Euler step for this model (see module doc)."""
        m = self.model
        inv_m = m.particle_inv_mass_np.astype(np.float64)
        omega2 = np.zeros(m.particle_count)
        tri = m.tri_indices_np
        if m.tri_count:
            dm = m.tri_dm_inv.numpy().astype(np.float64)
            comp = m.tri_compliance.numpy().astype(np.float64)
            a = np.stack([-(dm[:, 0, 0] + dm[:, 1, 0]), dm[:, 0, 0], dm[:, 1, 0]], 1)
            b = np.stack([-(dm[:, 0, 1] + dm[:, 1, 1]), dm[:, 0, 1], dm[:, 1, 1]], 1)
            w = inv_m[tri]
            per_tri = ((w * a * a).sum(1) / comp[:, 0] + (w * b * b).sum(1) / comp[:, 1]
                       + (w * (a * a + b * b)).sum(1) / comp[:, 2])
            np.add.at(omega2, tri.reshape(-1), np.repeat(per_tri, 3))
        if m.bend_count:
            x = m.particle_q_rest_np.astype(np.float64)
            bi = m.bend_indices_np
            x1, x2, x3, x4 = (x[bi[:, k]] for k in range(4))
            e_len = np.linalg.norm(x4 - x3, axis=1)
            h1 = np.linalg.norm(np.cross(x3 - x1, x4 - x1), axis=1) / e_len
            h2 = np.linalg.norm(np.cross(x4 - x2, x3 - x2), axis=1) / e_len
            # |grad theta| of the opposite vertices is 1/h; edge vertices are bounded by the same sum.
            grad2 = 2.0 * (1.0 / h1 ** 2 + 1.0 / h2 ** 2)
            per_bend = grad2 * inv_m[bi].max(axis=1) / m.bend_compliance.numpy().astype(np.float64)
            np.add.at(omega2, bi.reshape(-1), np.repeat(per_bend, 4))
        if self.attachments:
            omega2[m.attachment_particle_np] += m.default_attachment_stiffness * inv_m[m.attachment_particle_np]
        omega2 *= inv_m > 0
        top = float(omega2.max()) if omega2.size else 0.0
        return math.inf if top <= 0.0 else 2.0 / math.sqrt(top)

    def substeps_for(self, frame_dt: float) -> int:
        """Substeps per frame of ``frame_dt`` [s] that keep dt below ``safety * stable_dt()``."""
        return max(1, math.ceil(frame_dt / (self.safety * self.stable_dt())))

    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl,
             contacts: BodyCollider | None, dt: float, *,
             substep: int = 0) -> None:
        """Advance one substep of ``dt`` [s] from ``state_in`` into ``state_out`` (no allocation)."""
        self._check(state_in, state_out, contacts, dt)
        m = self.model
        dev = self.device
        x = state_in.particle_q
        if m.tri_count:
            wp.launch(kernels.eval_triangle_forces, dim=m.tri_count,
                      inputs=[m.tri_indices, m.tri_dm_inv, m.tri_compliance, x], outputs=[self.slot_force], device=dev)
        if m.bend_count:
            wp.launch(kernels.eval_bending_forces, dim=m.bend_count,
                      inputs=[3 * m.tri_count, m.bend_indices, m.bend_rest_angle, m.bend_compliance, x],
                      outputs=[self.slot_force], device=dev)
        wp.launch(self._integrate_kernel, dim=m.particle_count,
                  inputs=[m.particle_mass, m.particle_inv_mass, m.particle_world, control.world_active,
                          m.world_damping, self.extra_damping, self.gravity, float(dt), m.particle_adj_start,
                          m.particle_adj_slot, self.slot_force, m.particle_attachment, control.attachment_target,
                          control.world_attachment_stiffness, control.world_attachment_enabled,
                          x, state_in.particle_qd],
                  outputs=[state_out.particle_q, state_out.particle_qd], device=dev)
        if self.body_contact:
            self.detect_contacts(state_out.particle_q, contacts, control, substep)
            wp.launch(kernels.resolve_body_contacts, dim=m.particle_count,
                      inputs=[m.particle_inv_mass, m.particle_world, control.world_active, m.world_friction, float(dt),
                              self.contact_active, self.contact_normal, self.contact_offset, self.contact_motion],
                      outputs=[state_out.particle_q, state_out.particle_qd], device=dev)
