"""Cloth model (static, packed over worlds), state (positions, velocities) and control.

Every per-particle array is packed over worlds: particles of world ``w`` occupy the range
``world_particle_start[w] : world_particle_start[w] + world_particle_count[w]`` and
``particle_world[i]`` names the world of particle ``i``.  Triangles and bending elements are
packed the same way and sorted by graph colour, so one kernel launch advances all worlds and
the Gauss-Seidel sweep can run colour by colour.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import warp as wp

from simulate.cloth.device_copy import copy_cuda_tensor
from simulate.cloth.fabric import Fabric

__all__ = ["Features", "ClothModel", "ClothState", "ClothControl", "world_colour_offsets"]


@dataclasses.dataclass
class Features:
    """Physics switched on for a scene, fixed at build time (kernels are specialized on it)."""

    bending: bool = True
    """Dihedral bending constraints; when off, no bending kernel launches."""
    friction: bool = True
    """Coulomb friction against the body."""
    self_contact: bool = False
    """Vertex-triangle self-contact (costly; off by default)."""
    attachments: bool | None = None
    """Soft attachment constraints; ``None`` = on iff the builder received attached vertices."""
    body_contact: bool = True
    """Contact with the body collider (forced off when the driver gets no collider)."""


class ClothState:
    """Time-varying cloth state."""

    def __init__(self, particle_q: wp.array, particle_qd: wp.array) -> None:
        self.particle_q = particle_q
        """Particle positions [m], shape (particle_count,), dtype vec3."""
        self.particle_qd = particle_qd
        """Particle velocities [m/s], shape (particle_count,), dtype vec3."""

    def assign(self, other: ClothState) -> None:
        """Copy ``other`` into this state's buffers (no allocation)."""
        wp.copy(self.particle_q, other.particle_q)
        wp.copy(self.particle_qd, other.particle_qd)


class ClothControl:
    """Inputs the caller drives between frames: attachment targets, active worlds, self-contact
    per world. The body a solver collides with is its own argument (``SolverBase.step``'s
    ``contacts``)."""

    def __init__(self, model: ClothModel) -> None:
        device = model.device
        count = max(model.attachment_count, 1)
        targets = np.zeros((count, 3), dtype=np.float32)
        if model.attachment_count:
            targets[:] = model.particle_q_rest[model.attachment_particle_np]
        self.attachment_target = wp.array(targets, dtype=wp.vec3, device=device)
        """Attachment target positions [m], shape (max(attachment_count, 1),); entry ``a`` pulls
        particle ``model.attachment_particle[a]``."""
        self.world_attachment_stiffness = wp.array(
            np.full(model.world_count, model.default_attachment_stiffness, dtype=np.float32), device=device
        )
        """Attachment spring stiffness per world [N/m per attached particle], shape (world_count,)."""
        self.world_attachment_enabled = wp.array(np.ones(model.world_count, dtype=np.int32), device=device)
        """1 where a world's attachments act, 0 once released; shape (world_count,)."""
        self.world_active = wp.array(np.ones(model.world_count, dtype=np.int32), device=device)
        """1 where a world is integrated, 0 where it is frozen (converged or exploded); (world_count,)."""
        self.world_self_contact = wp.array(np.ones(model.world_count, dtype=np.int32), device=device)
        """1 where a world's self-contact (if the solver has it) finds candidates at its next search,
        0 where it is off; (world_count,). See :meth:`set_self_contact`."""
        self._self_contact_host = np.ones(model.world_count, dtype=np.int32)
        self._model = model

    def set_attachment_targets(self, targets, *, check_finite: bool = True) -> None:
        """Set attachment target positions [m], shape (attachment_count, 3): a numpy array, or a
        torch tensor (a CUDA one on a CUDA model is copied without leaving the device).
        ``check_finite`` False skips the finiteness check of a CUDA tensor: reading its answer on
        the host waits for all the device work queued before it (the sequence driver moves the
        targets with every body move, from posed bodies)."""
        if type(targets).__module__.startswith("torch") and targets.is_cuda and self.attachment_target.device.is_cuda:
            import torch

            expected = (self._model.attachment_count, 3)
            if tuple(targets.shape) != expected:
                raise ValueError(f"attachment targets must have shape {expected} (got {tuple(targets.shape)})")
            if check_finite and not bool(torch.isfinite(targets).all()):
                raise ValueError("attachment targets must be finite (got NaN or inf)")
            if self._model.attachment_count:
                copy_cuda_tensor(self.attachment_target, targets)
            return
        if type(targets).__module__.startswith("torch"):
            targets = targets.detach().cpu().numpy()
        targets = np.asarray(targets, dtype=np.float32)
        expected = (self._model.attachment_count, 3)
        if targets.shape != expected:
            raise ValueError(f"attachment targets must have shape {expected} (got {targets.shape})")
        if not np.all(np.isfinite(targets)):
            raise ValueError("attachment targets must be finite (got NaN or inf)")
        if self._model.attachment_count:
            self.attachment_target.assign(targets)

    def release_attachments(self, worlds: np.ndarray | list[int] | None = None) -> None:
        """Switch attachments off for ``worlds`` (all worlds when None)."""
        enabled = self.world_attachment_enabled.numpy()
        enabled[self._world_index(worlds)] = 0
        self.world_attachment_enabled.assign(enabled)

    def enable_attachments(self, worlds: np.ndarray | list[int] | None = None) -> None:
        """Switch attachments back on for ``worlds`` (all worlds when None)."""
        enabled = self.world_attachment_enabled.numpy()
        enabled[self._world_index(worlds)] = 1
        self.world_attachment_enabled.assign(enabled)

    def set_self_contact(self, enabled: np.ndarray) -> None:
        """Turns self-contact on (True) or off (False) per world, (world_count,) bools. Only a
        changed mask goes to the device (a captured frame graph reads the array as it is)."""
        mask = np.asarray(enabled)
        if mask.shape != (self._model.world_count,):
            raise ValueError(f"self-contact mask must have shape ({self._model.world_count},) (got {mask.shape})")
        mask = mask.astype(bool).astype(np.int32)
        if not np.array_equal(mask, self._self_contact_host):
            self.world_self_contact.assign(mask)
            self._self_contact_host = mask

    def _world_index(self, worlds: Any) -> np.ndarray:
        count = self._model.world_count
        if worlds is None:
            return np.arange(count)
        index = np.asarray(worlds, dtype=np.int64).reshape(-1)
        if index.size and (index.min() < 0 or index.max() >= count):
            raise ValueError(f"worlds must be indices in [0, {count}) (got {index.tolist()})")
        return index


def world_colour_offsets(colour_offsets: list[int], element_world: np.ndarray, world_count: int) -> np.ndarray:
    """Where each world's elements of each colour lie in elements sorted by colour, then world.

    Args:
        colour_offsets: colour c spans elements ``colour_offsets[c]`` .. ``colour_offsets[c + 1]``.
        element_world: world of each element, shape (E,), non-decreasing within a colour.
        world_count: worlds W.
    Returns:
        int32 (C, W + 1): world w's elements of colour c are ``[c, w]`` .. ``[c, w + 1]``; one
        row of zeros (empty ranges) when there are no elements.
    """
    rows = []
    worlds = np.arange(world_count + 1)
    for a, b in zip(colour_offsets[:-1], colour_offsets[1:]):
        wid = np.asarray(element_world[a:b])
        if np.any(np.diff(wid) < 0):
            raise ValueError(f"elements of colour {len(rows)} are not sorted by world")
        rows.append(a + np.searchsorted(wid, worlds, side="left"))
    if not rows:
        return np.zeros((1, world_count + 1), dtype=np.int32)
    return np.asarray(rows, dtype=np.int32)


class ClothModel:
    """Static cloth description for ``world_count`` worlds, created by ``ClothBuilder.finalize``.

    Arrays (device ``device``):

    * ``particle_q_rest`` numpy float32 (particle_count, 3) rest/initial positions [m] (host copy)
    * ``particle_mass`` float (particle_count,) lumped masses [kg]
    * ``particle_inv_mass`` float (particle_count,) inverse masses [1/kg], 0 for pinned
    * ``particle_world`` int32 (particle_count,) world of each particle
    * ``particle_radius`` float (particle_count,) half fabric thickness [m]
    * ``particle_body_part`` int32 (particle_count,) primary collision body (the collider's face
      group the particle meets; 0 without parts)
    * ``particle_attachment`` int32 (particle_count,) attachment index or -1
    * ``particle_adj_start`` int32 (particle_count + 1,), ``particle_adj_slot`` int32: CSR list
      of the element slots (``3 t + k`` for triangle corners, ``3 T + 4 b + k`` for bending
      corners) touching each particle, ascending (a particle's triangle slots come first; the
      self-contact search relies on it), used by the Jacobi gather and mass-spring forces
    * ``tri_indices`` int32 (tri_count, 3), ``tri_dm_inv`` mat22 (tri_count,) inverse rest
      frame matrix in the triangle's (warp, weft) frame [1/m], ``tri_area`` float [m^2],
      ``tri_compliance`` vec3 (1/(Y_warp A), 1/(Y_weft A), 1/(G A)) [1/N m], ``tri_world`` int32,
      ``tri_jacobi_scale`` float (1 / most triangles at a corner; the Jacobi multiplier share)
    * ``bend_indices`` int32 (bend_count, 4) (opposite 0, opposite 1, edge 0, edge 1),
      ``bend_rest_angle`` float [rad], ``bend_compliance`` float [1/(N m)], ``bend_world`` int32,
      ``bend_jacobi_scale`` float
    * ``world_damping`` float (world_count,) [1/s], ``world_friction`` float (world_count,)
    * ``attachment_particle`` int32 (attachment_count,)

    Host metadata: ``tri_colour_offsets`` / ``bend_colour_offsets`` (colour c spans
    ``offsets[c]:offsets[c+1]``), ``world_particle_start`` / ``world_particle_count`` (numpy),
    ``fabrics`` (per world), ``skinning_weights`` (per world, (V_w, J) or None).
    """

    def __init__(self) -> None:
        self.device: wp.Device | None = None
        self.world_count = 0
        self.particle_count = 0
        self.tri_count = 0
        self.bend_count = 0
        self.attachment_count = 0
        self.features = Features()
        self.gravity = (0.0, -9.81, 0.0)
        """Gravity acceleration [m/s^2] (y is up)."""
        self.default_attachment_stiffness = 1.0e3
        self.fabrics: list[Fabric] = []
        self.skinning_weights: list[np.ndarray | None] = []
        self.world_particle_start = np.zeros(0, dtype=np.int64)
        self.world_particle_count = np.zeros(0, dtype=np.int64)
        self.world_faces: list[np.ndarray] = []
        """Per world, the triangle indices local to the world (F_w, 3) as given to add_garment."""
        self.tri_colour_offsets: list[int] = [0]
        self.bend_colour_offsets: list[int] = [0]
        self.particle_q_rest_np = np.zeros((0, 3), dtype=np.float32)
        self.attachment_particle_np = np.zeros(0, dtype=np.int32)
        self.tri_indices_np = np.zeros((0, 3), dtype=np.int32)
        self.particle_mass_np = np.zeros(0, dtype=np.float32)
        self.particle_inv_mass_np = np.zeros(0, dtype=np.float32)

    @property
    def particle_q_rest(self) -> np.ndarray:
        """Rest/initial particle positions [m], numpy (particle_count, 3)."""
        return self.particle_q_rest_np

    def state(self) -> ClothState:
        """A new state at the rest positions with zero velocity."""
        q = wp.array(self.particle_q_rest_np, dtype=wp.vec3, device=self.device)
        qd = wp.zeros(self.particle_count, dtype=wp.vec3, device=self.device)
        return ClothState(q, qd)

    def control(self) -> ClothControl:
        """A new control with attachment targets at the rest positions, attachments enabled."""
        return ClothControl(self)

    def world_slice(self, world: int) -> slice:
        """Particle index range of ``world``."""
        if not 0 <= world < self.world_count:
            raise ValueError(f"world must be in [0, {self.world_count}) (got {world})")
        start = int(self.world_particle_start[world])
        return slice(start, start + int(self.world_particle_count[world]))

    def world_element_offsets(self) -> tuple[np.ndarray, np.ndarray]:
        """``world_colour_offsets`` of the triangles and of the bending elements, (C, W + 1) each
        (computed once)."""
        if not hasattr(self, "_world_element_offsets"):
            self._world_element_offsets = tuple(
                world_colour_offsets(offsets, world.numpy()[:count], self.world_count)
                for offsets, world, count in ((self.tri_colour_offsets, self.tri_world, self.tri_count),
                                              (self.bend_colour_offsets, self.bend_world, self.bend_count)))
        return self._world_element_offsets

    def copy_world_garment(self, dst: int, src: int) -> None:
        """Gives world ``dst`` world ``src``'s garment: rest shape (triangle rest frames and areas,
        rest dihedral angles, rest positions), fabric (compliances, masses, thickness, damping,
        friction) and skinning weights, copied in place on the device (a captured frame graph
        keeps reading the same arrays). Both worlds must have the same triangles in the same
        element order and attach the same particles (``ValueError`` otherwise); each world keeps
        its own attachment slots, whose targets the caller sets (``ClothControl``; the sequence
        driver sets them from the world's current task).  Positions, velocities and contacts are
        the caller's (``QuasiStaticSimulator.adopt_garment``)."""
        if dst == src:
            return
        n = int(self.world_particle_count[src])
        if (int(self.world_particle_count[dst]) != n or not np.array_equal(self.world_faces[dst], self.world_faces[src])):
            raise ValueError(f"world {dst} can take world {src}'s garment only with the same triangles "
                             f"({int(self.world_particle_count[dst])} and {n} particles)")
        if self.attachment_count:
            att = self.particle_attachment.numpy()
            if not np.array_equal(att[self.world_slice(dst)] >= 0, att[self.world_slice(src)] >= 0):
                raise ValueError(f"worlds {dst} and {src} attach different particles: no garment swap")
        tri_offsets, bend_offsets = self.world_element_offsets()
        d0, s0 = int(self.world_particle_start[dst]), int(self.world_particle_start[src])
        for offsets, indices, arrays in (
                (tri_offsets, self.tri_indices_np, (self.tri_dm_inv, self.tri_compliance, self.tri_area)),
                (bend_offsets, self.bend_indices_np, (self.bend_rest_angle, self.bend_compliance))):
            for a, b, k, m in zip(offsets[:, dst], offsets[:, src], offsets[:, dst + 1] - offsets[:, dst],
                                  offsets[:, src + 1] - offsets[:, src]):
                a, b, k, m = int(a), int(b), int(k), int(m)
                if k != m or not np.array_equal(indices[a:a + k] - d0, indices[b:b + m] - s0):
                    raise ValueError(f"worlds {dst} and {src} order their elements differently: no garment swap")
                for arr in arrays:
                    if k:
                        wp.copy(arr, arr, dest_offset=a, src_offset=b, count=k)
        for arr in (self.particle_mass, self.particle_inv_mass, self.particle_radius, self.particle_body_part):
            wp.copy(arr, arr, dest_offset=d0, src_offset=s0, count=n)
        for arr in (self.world_damping, self.world_friction):
            wp.copy(arr, arr, dest_offset=dst, src_offset=src, count=1)
        for host in (self.particle_q_rest_np, self.particle_mass_np, self.particle_inv_mass_np):
            host[d0:d0 + n] = host[s0:s0 + n]
        self.fabrics[dst] = self.fabrics[src]
        self.skinning_weights[dst] = self.skinning_weights[src]
