"""Shared parts of the cloth solvers: buffers and launches for contact, friction, velocities."""

from __future__ import annotations

import abc
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from simulate.cloth.model import ClothControl, ClothModel, ClothState
from simulate.solvers import common_kernels as ck

if TYPE_CHECKING:
    from simulate.contact.body_collider import BodyCollider

__all__ = ["SolverBase"]


class SolverBase(abc.ABC):
    """Allocates per-particle contact buffers once; subclasses implement ``step`` (one substep)."""

    def __init__(self, model: ClothModel, *, body_contact: bool | None = None, extra_damping: float = 0.0,
                 contact_detect_every: int = 1) -> None:
        """
        Args:
            model: the cloth model.
            body_contact: contact with the body given to ``step`` (``contacts``); default
                ``model.features.body_contact``.
            extra_damping: velocity damping rate added to every fabric's damping [1/s].
            contact_detect_every: query the body for contact planes on substeps ``0, N, 2N, ...`` of
                each frame and carry the planes along with the body's motion in between (1 = every
                substep).  The collider then needs to be at a substep's pose only on those substeps.
        """
        if not (np.isfinite(extra_damping) and extra_damping >= 0.0):
            raise ValueError(f"extra_damping must be a finite number >= 0 [1/s] (got {extra_damping!r})")
        if int(contact_detect_every) != contact_detect_every or contact_detect_every < 1:
            raise ValueError(f"contact_detect_every must be an integer >= 1 (got {contact_detect_every!r})")
        self.contact_detect_every = int(contact_detect_every)
        self.model = model
        self.device = model.device
        feats = model.features
        self.body_contact = feats.body_contact if body_contact is None else bool(body_contact)
        self.friction = bool(feats.friction and self.body_contact)
        self.attachments = bool(feats.attachments and model.attachment_count > 0)
        self.extra_damping = float(extra_damping)
        self.gravity = wp.vec3(*model.gravity)
        n = max(model.particle_count, 1)
        dev = self.device
        self.contact_active = wp.zeros(n, dtype=wp.int32, device=dev)
        """1 where a particle has a contact plane this substep, shape (particle_count,)."""
        self.contact_normal = wp.zeros(n, dtype=wp.vec3, device=dev)
        """Outward body normal of the contact plane, shape (particle_count,)."""
        self.contact_offset = wp.zeros(n, dtype=float, device=dev)
        """Plane offset [m]: the constraint is dot(normal, x) >= offset."""
        self.contact_motion = wp.zeros(n, dtype=wp.vec3, device=dev)
        """Body displacement at the contact point during this substep [m]."""
        self.contact_depth = wp.zeros(n, dtype=float, device=dev)
        """Normal correction applied by the contact this substep [m] (friction budget)."""
        self.attachment_lambda = wp.zeros(max(model.attachment_count, 1), dtype=wp.vec3, device=dev)
        self._finalize_kernel = ck.make_finalize_kernel(self.friction)
        self._bound_args: list | None = None
        """Self-contact displacement bounds the finalize keeps to (searched positions, d_min,
        fraction, min separation), set by a solver that keeps to them; None otherwise."""

    @abc.abstractmethod
    def step(self, state_in: ClothState, state_out: ClothState, control: ClothControl,
             contacts: BodyCollider | None, dt: float, *, substep: int = 0) -> None:
        """Advances every active world (``control.world_active``) by one substep: reads positions and
        velocities from ``state_in``, writes them to ``state_out`` (a different buffer: the caller
        swaps the two). ``dt``: substep length [s]; ``substep``: its index within the frame, which
        decides whether the body is queried for contact planes (``queries_body``) and, with
        self-contact, whether candidate triangles are searched afresh. ``contacts``: the body
        collider, positioned by the driver for this substep (None without body contact)."""

    def garment_changed(self, dst: int, src: int) -> None:
        """World ``dst`` now holds world ``src``'s garment (``ClothModel.copy_world_garment``):
        update whatever the solver derived from the model's per-world data at construction.
        Nothing here: the base buffers are per particle, and a solver that reads the model's
        element arrays at every step (mass-spring) sees the new garment as it is. A substep
        chosen from the model's stable step stays stable: ``src``'s garment was in the model
        already."""

    def positions_set(self, start: int, count: int) -> None:
        """The caller set particles ``start`` .. ``start + count`` to new positions at rest
        (``QuasiStaticSimulator.set_positions``): forget whatever the solver carried over from
        their past substeps, so they step as in a solver built at those positions.  Nothing here:
        the base solvers carry nothing between substeps beyond the state."""

    def _check(self, state_in: ClothState, state_out: ClothState, contacts: BodyCollider | None, dt: float) -> None:
        if not dt > 0.0:
            raise ValueError(f"dt must be > 0 [s] (got {dt!r})")
        if self.body_contact and contacts is None:
            raise ValueError("body_contact is on but contacts is None: pass the BodyCollider to step() or build "
                             "the solver with body_contact=False")
        if state_in is state_out:
            raise ValueError("state_in and state_out must be different ClothState buffers (double buffering)")

    def queries_body(self, substep: int) -> bool:
        """Whether ``substep`` of a frame queries the body for contact planes (the others move the
        last query's planes with the body); the driver moves and refits the body only for these."""
        return substep % self.contact_detect_every == 0

    def detect_contacts(self, x: wp.array, contacts: BodyCollider | None, control: ClothControl,
                        substep: int = 0) -> None:
        """Find one contact plane per particle at positions ``x`` (skipped without body contact).

        On a ``substep`` of the frame that is not a multiple of ``contact_detect_every`` the planes
        of the last query move with the body instead (no query)."""
        if not self.body_contact:
            return
        from simulate.contact import kernels as contact_kernels

        col = contacts
        m = self.model
        if not self.queries_body(substep):
            wp.launch(contact_kernels.advance_body_contacts, dim=m.particle_count,
                      inputs=[m.particle_world, control.world_active, self.contact_active, self.contact_normal,
                              self.contact_motion],
                      outputs=[self.contact_offset, self.contact_depth], device=self.device)
            return
        wp.launch(contact_kernels.detect_body_contacts, dim=m.particle_count,
                  inputs=[col.contact_meshes, col.pose_start, col.pose_end, col.world_offset,
                          float(col.motion_scale), float(col.thickness), float(col.margin),
                          m.particle_world, m.particle_body_part, m.particle_radius, control.world_active, x],
                  outputs=[self.contact_active, self.contact_normal, self.contact_offset, self.contact_motion,
                           self.contact_depth], device=self.device)

    def finalize_substep(self, state_in: ClothState, state_out: ClothState, control: ClothControl, dt: float) -> None:
        """Friction on the substep displacement, then velocities with damping into ``state_out``."""
        m = self.model
        if self._bound_args is None:
            bounds = [self.contact_motion, self.contact_depth, 0.0, 0.0, control.world_self_contact]
        else:
            bounds = [*self._bound_args, control.world_self_contact]
        wp.launch(self._finalize_kernel, dim=m.particle_count,
                  inputs=[m.particle_inv_mass, m.particle_world, control.world_active, m.world_damping,
                          m.world_friction, self.extra_damping, float(dt), self.contact_active, self.contact_normal,
                          self.contact_motion, self.contact_depth, state_in.particle_q, state_in.particle_qd,
                          *bounds, state_out.particle_q],
                  outputs=[state_out.particle_qd], device=self.device)
