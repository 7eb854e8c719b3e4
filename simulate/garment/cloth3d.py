"""The values of CLOTH3D-style garment generation (seed 004, Sec. 3.2-3.4), in one place.

Seed 004 generates each outfit from a few templates (t-shirt, top, trousers, skirt) by
*shaping* sleeves, legs and skirt as cylinders whose width is constant or decreasing toward
the wrist/ankle and widens beyond a sampled point (the skirt always widens), *cutting* at
uniformly sampled lengths, *resizing* to the body shape plus a tightness offset, and *sewing*
an upper and a lower garment into a dress or a jumpsuit. Its simulation picks one of four
fabrics (cotton, silk, denim, leather; upper-body garments cotton or silk only) and blends
the body from shape + tightness to shape before the sequence.

The seed text lost most of its numbers (the width-profile formula and its constants, the
tightness range, the cut ranges). :data:`CLOTH3D` states the values this project uses; the
attribute docstrings say which are the seed's and which are chosen here (marked "chosen").
Lengths along a limb are in bone units u (u = i + t: fraction t along bone i of the
shoulder-elbow-wrist or hip-knee-ankle chain, see ``simulate.garment.templates``); a
position s along a width profile runs from 0 at the profile's anchor (shoulder, hip, waist)
to 1 at the longest cut.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Cloth3DChoices:
    """Ranges and constants of the generator (see the module docstring)."""

    top_armhole_u: float = 0.08
    """Armhole of the sleeveless top and of the upper part of dresses and jumpsuits: the arm is cut
    at this bone-unit coordinate past the shoulder joint [bone units] (chosen: just past the
    shoulder, so the armhole is a loop around the arm root, not a cut through the torso)."""
    limb_taper_max: float = 0.6
    """Largest share of the looseness a sleeve or leg loses from its anchor to its longest cut (the
    seed's "constant or decreasing" width; 0 = constant) [-] (chosen; the offset never drops below
    ``min_offset_m``)."""
    limb_widen_max_m: float = 0.06
    """Largest widening of a sleeve or leg: extra outward offset per unit of s past the widening
    point [m] (chosen; the seed samples the rate "within ranges empirically set per garment")."""
    widen_at_range: tuple[float, float] = (0.2, 1.0)
    """Where widening may start along a sleeve or leg, in s [-] (seed: "a uniformly sampled point
    along the axis"; the range is chosen: 1.0 = no widening within the garment)."""
    skirt_flare_max_m: float = 0.25
    """Largest flare of a dress's skirt at its longest hem [m] (the seed: skirts always widen
    from waist to bottom; the value is the project's skirt ``width_profile`` maximum)."""
    min_offset_m: float = 0.003
    """Smallest outward offset a width profile may leave (a tapered cuff stays off the skin) [m]
    (chosen)."""
    tightness_parameters: tuple[str, str] = ("height", "weight")
    """Body-shape parameters the two tightness offsets are added to: anny's stand-ins for SMPL's
    first two shape coefficients, global size and fatness (seed 004, Sec. 3.2)."""
    tightness_range: tuple[tuple[float, float], tuple[float, float]] = ((-0.02, 0.05), (-0.1, 0.4))
    """Uniform sampling range of each tightness offset [anny parameter units; the parameters span
    [0, 1]] (chosen: the seed's range was lost; like the seed it is biased toward loose garments.
    Sign: positive = a larger (looser) garment, the reverse of the seed's convention, and the same
    for both genders because anny's height and weight mean the same for every gender (the seed
    flips the first offset's sign with gender because SMPL's first coefficient does)). On the
    neutral anny body +0.4 weight widens the waist by ~1.5 cm, +0.05 height raises the neck by
    ~4.6 cm."""
    shape_transition_frames: int = 10
    """Frames of the body-shape blend from shape + tightness to shape before a sequence (the seed
    says "a few frames"; chosen: the dataset spec's ``simulation.shape_transition_frames``
    default)."""
    fabrics: tuple[str, ...] = ("cotton", "silk", "denim", "leather")
    """The four fabrics of the seed's dataset (``simulate.cloth.fabric.FABRICS`` presets)."""
    top_fabrics: tuple[str, ...] = ("cotton", "silk")
    """Fabrics of upper-body garments (the seed: "Upper-body garments might be cotton or silk")."""
    upper_body_types: tuple[str, ...] = ("tshirt", "shirt", "top")
    """Garment types restricted to ``top_fabrics`` when fabrics are sampled."""


CLOTH3D = Cloth3DChoices()
"""The values in use."""


def allowed_fabrics(garment_type: str, fabrics=None) -> tuple[str, ...]:
    """The fabrics a garment type may be given, out of ``fabrics`` (default all four): for
    upper-body types only cotton and silk (seed 004, Sec. 3.3)."""
    names = tuple(CLOTH3D.fabrics if fabrics is None else fabrics)
    if garment_type in CLOTH3D.upper_body_types:
        return tuple(f for f in names if f in CLOTH3D.top_fabrics)
    return names


def sample_fabrics(garment_type: str, count: int, *, fabrics=None, seed: int = 0) -> list[str]:
    """``count`` fabric names drawn uniformly (seeded) from :func:`allowed_fabrics`.

    Raises ValueError when none of ``fabrics`` is allowed for the type (e.g. only denim for a top)."""
    allowed = allowed_fabrics(garment_type, fabrics)
    if not allowed:
        raise ValueError(f"fabrics {list(fabrics or ())} leave none for a {garment_type}; upper-body garments "
                         f"({', '.join(CLOTH3D.upper_body_types)}) take {' or '.join(CLOTH3D.top_fabrics)}")
    import numpy as np

    rng = np.random.default_rng(seed)
    return [allowed[i] for i in rng.integers(0, len(allowed), size=int(count))]
