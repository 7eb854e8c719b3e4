"""Fabric presets: the material parameters of the cloth model, in SI units.

A :class:`Fabric` describes a woven or knitted sheet as a thin orthotropic membrane with
bending resistance.  The cloth energy used by both solvers (see
``simulate/solvers/xpbd/kernels.py``) is, per triangle of rest area ``A`` with deformation
gradient columns ``f1, f2`` (the deformed warp and weft directions of the triangle's rest
frame, see ``simulate.cloth.builder.material_directions``: the warp runs up the garment's
pattern panel, the weft across it):

    E = 1/2 * A * (Y_warp * (|f1| - 1)^2 + Y_weft * (|f2| - 1)^2)
      + 1/2 * shear_stiffness * A * (f1 . f2)^2

with ``Y_warp = stretch_stiffness`` and ``Y_weft = weft_stiffness`` (the warp value when None),
and per interior edge ``e`` with adjacent rest areas ``A1, A2`` and dihedral angle ``theta``
(discrete shells, Grinspun et al. 2003, normalized so that a cylinder of curvature kappa on an
equilateral mesh stores 1/2 * bending_stiffness * kappa^2 per unit area in every direction;
on right-triangle grids bending across the diagonals is ~3x stiffer than along the axes):

    E = 1/2 * bending_stiffness * |e|^2 / (A1 + A2) * (theta - theta_rest)^2

So ``stretch_stiffness`` / ``weft_stiffness`` are membrane Young's moduli times thickness along
the warp / weft [N/m] (Poisson ratio 0, as is usual for woven fabric: a strip cut along the warp
and hung by one end stretches rho g L^2 / (2 Y_warp), one cut along the weft rho g L^2 /
(2 Y_weft)), ``shear_stiffness`` an in-plane shear modulus times thickness [N/m] and
``bending_stiffness`` a flexural rigidity [N m] (isotropic here).

Preset values (SI):

=========  ========  =======  =======  =====  =======  =======  ========  =========
name       density   warp     weft     shear  bending  damping  friction  thickness
           [kg/m^2]  [N/m]    [N/m]    [N/m]  [N m]    [1/s]    [-]       [m]
=========  ========  =======  =======  =====  =======  =======  ========  =========
silk       0.07      1.0e3    0.7e3    10     2.0e-6   0.5      0.30      2.0e-4
cotton     0.18      3.0e3    1.5e3    30     1.0e-5   0.5      0.50      5.0e-4
denim      0.35      8.0e3    4.0e3    80     6.0e-5   0.5      0.60      1.0e-3
leather    0.70      2.0e4    2.0e4    300    5.0e-4   0.5      0.70      1.5e-3
=========  ========  =======  =======  =====  =======  =======  ========  =========

Where the numbers come from (representative values inside published ranges, not a fit to
one measured sample):

* density: areal weights of common fabrics (silk habotai/charmeuse 40-90 g/m^2, cotton
  shirting/jersey 120-200 g/m^2, denim 10-14 oz/yd^2 = 340-475 g/m^2, garment leather
  0.5-0.9 kg/m^2).
* stretch, shear, bending: Kawabata KES-F measurements as reported in the cloth-simulation
  literature (e.g. the measured materials of Wang, O'Brien and Ramamoorthi 2011, "Data-driven
  elastic models for cloth", used by ArcSim, measured separately along warp, weft and bias;
  Breen/House/Wozny 1994).  Kawabata bending rigidity B in gf cm^2/cm
  converts as 1 gf cm^2/cm = 9.81e-5 N m (light silk ~0.02, cotton shirting ~0.1, denim ~0.6,
  leather several); shear rigidity G in gf/(cm deg) converts as 1 gf/(cm deg) = 56 N/m per
  radian (fabrics 0.2-5); initial tensile stiffness of woven fabrics is 1e3-1e4 N/m and
  leather is stiffer.  Woven cloth is far softer in shear than in stretch, which these
  presets keep.
* warp against weft: woven fabrics are usually stiffer along the warp (the stronger, set
  yarns, woven under loom tension), by a factor of ~1.3-3 in the initial tensile stiffness of
  KES-F tests (the extension EMT at 500 gf/cm is typically the larger in the weft).  Silk
  habotai is a near-balanced plain weave (ratio 1.4 here), cotton shirting and denim (a
  warp-faced twill) take 2.  Leather is not woven: the same value in both directions.
* friction: cloth-on-skin Coulomb coefficients 0.3-0.7 (silk smooth, leather grippy).
* damping: a mass-proportional velocity damping rate standing in for air drag and
  internal friction; it is not a measured quantity (the quasi-static driver adds its own).
* thickness: caliper thickness of the fabric; the cloth mid-surface keeps half of it plus
  the collider's contact thickness away from the body.
"""

from __future__ import annotations

import dataclasses
import math

__all__ = ["Fabric", "FABRICS", "resolve_fabric"]


@dataclasses.dataclass(frozen=True)
class Fabric:
    """Material parameters of one garment's cloth (SI units)."""

    name: str = "custom"
    """Preset name (free text for custom fabrics)."""
    density: float = 0.18
    """Areal mass density [kg/m^2]."""
    stretch_stiffness: float = 3.0e3
    """Membrane Young's modulus times thickness along the warp [N/m] (the only stretch value of
    an isotropic fabric, whose ``weft_stiffness`` is None)."""
    shear_stiffness: float = 30.0
    """In-plane shear modulus times thickness [N/m]."""
    bending_stiffness: float = 1.0e-5
    """Flexural rigidity [N m]."""
    damping: float = 0.5
    """Mass-proportional velocity damping rate [1/s]; velocities decay as exp(-damping t)."""
    friction: float = 0.5
    """Coulomb friction coefficient against the body [-]."""
    thickness: float = 5.0e-4
    """Fabric thickness [m]; half of it is added to the body contact distance."""
    weft_stiffness: float | None = None
    """Membrane Young's modulus times thickness along the weft [N/m]; None: the same as the warp's
    ``stretch_stiffness`` (an isotropic membrane)."""

    def __post_init__(self) -> None:
        for field in ("density", "stretch_stiffness", "shear_stiffness", "thickness"):
            value = getattr(self, field)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"Fabric.{field} must be a finite number > 0 (got {value!r})")
        if self.weft_stiffness is not None and not (math.isfinite(self.weft_stiffness) and self.weft_stiffness > 0.0):
            raise ValueError(f"Fabric.weft_stiffness must be None or a finite number > 0 (got {self.weft_stiffness!r})")
        for field in ("bending_stiffness", "damping", "friction"):
            value = getattr(self, field)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"Fabric.{field} must be a finite number >= 0 (got {value!r})")


    @property
    def warp_stiffness(self) -> float:
        """Stretch stiffness along the warp [N/m] (``stretch_stiffness``)."""
        return self.stretch_stiffness

    @property
    def weft_stretch_stiffness(self) -> float:
        """Stretch stiffness along the weft [N/m]: ``weft_stiffness``, or the warp's when None."""
        return self.stretch_stiffness if self.weft_stiffness is None else self.weft_stiffness


FABRICS: dict[str, Fabric] = {
    "silk": Fabric("silk", 0.07, 1.0e3, 10.0, 2.0e-6, 0.5, 0.30, 2.0e-4, weft_stiffness=0.7e3),
    "cotton": Fabric("cotton", 0.18, 3.0e3, 30.0, 1.0e-5, 0.5, 0.50, 5.0e-4, weft_stiffness=1.5e3),
    "denim": Fabric("denim", 0.35, 8.0e3, 80.0, 6.0e-5, 0.5, 0.60, 1.0e-3, weft_stiffness=4.0e3),
    "leather": Fabric("leather", 0.70, 2.0e4, 300.0, 5.0e-4, 0.5, 0.70, 1.5e-3),
}
"""Named fabric presets (see the module docstring for the table and sources)."""


def resolve_fabric(fabric: Fabric | str) -> Fabric:
    """Return ``fabric`` itself or the preset it names; ValueError for unknown names."""
    if isinstance(fabric, Fabric):
        return fabric
    if isinstance(fabric, str):
        key = fabric.lower()
        if key not in FABRICS:
            raise ValueError(f"fabric must be one of {sorted(FABRICS)} or a Fabric (got {fabric!r})")
        return FABRICS[key]
    raise ValueError(f"fabric must be a Fabric or a preset name (got {type(fabric).__name__})")
