"""CLOTH3D-like style parameters (seed 004, Sec. 3.2): hem length, sleeve/leg length,
looseness and width profile, with names, ranges and defaults per garment type.

Lengths are fractions in [0, 1] between a garment type's shortest and longest cut;
the cut positions are defined from the body's joints (so they scale with shape):

==========  ==============  ===========================================================
type        parameter       meaning (0 ... 1)
==========  ==============  ===========================================================
tshirt      length          hem from 55 % ... 105 % of the way from spine2 (chest) down
                            to the hip joints
            sleeve_length   cuff from 30 % ... 85 % of shoulder -> elbow
shirt       length          as tshirt
            sleeve_length   cuff from 30 % ... 92 % of elbow -> wrist
pants       leg_length      hem from 30 % ... 92 % of knee -> ankle
shorts      leg_length      hem from 35 % ... 80 % of hip -> knee
skirt       length          hem from 35 % of hip -> knee down to 20 % below the knee
top         length          as tshirt (sleeveless: armholes at the arm roots)
dress       length          skirt hem as skirt (the top part ends at the waist seam)
jumpsuit    leg_length      hem from 35 % of hip -> knee (shorts) ... 92 % of knee -> ankle
==========  ==============  ===========================================================

``looseness`` [m] is the outward offset of the garment from the body surface along
smoothed normals (for the skirt: from the hull of the hips and legs). ``width_profile``
[m] is the extra offset added linearly from a limb's anchor (near the shoulder/hip)
to its hem: the flare of sleeves, legs or the skirt. The dress's skirt widens by
``flare`` [m] at its longest hem, linearly in height from the waist seam (seed 004: a
skirt's width always increases toward the bottom).

Seed 004's sleeve and leg width profile (Sec. 3.2: constant or decreasing toward the
wrist/ankle, widening beyond a sampled point) is three parameters, with s the position
along the limb from its anchor (0) to its longest cut (1):

    offset(s) = max(looseness * (1 - taper * s) + widen * max(0, s - widen_at), min_offset)

``taper`` [-] (share of the looseness lost at s = 1), ``widen_at`` [-] and ``widen`` [m per
unit s]. The jumpsuit's legs always have them; t-shirt, shirt, pants and shorts accept them
as optional parameters (:data:`OPTIONAL_STYLE_SPECS`), absent by default so those types'
default and sampled garments are the ones without the profile. Ranges come from
:data:`simulate.garment.cloth3d.CLOTH3D`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from simulate.garment.cloth3d import CLOTH3D

GARMENT_TYPES: tuple[str, ...] = ("tshirt", "shirt", "pants", "shorts", "skirt", "top", "dress", "jumpsuit")
"""Every garment type: TailorNet's five, the sleeveless top, and the sewn dress (top + skirt)
and jumpsuit (top + trousers) of seed 004."""
TAILORNET_TYPES: tuple[str, ...] = ("tshirt", "shirt", "pants", "shorts", "skirt")
"""The single-piece types with sleeves or legs of TailorNet's garments: the static set's default
types (its budgets are measured on these)."""
SEWN_TYPES: tuple[str, ...] = ("dress", "jumpsuit")
"""Types sewn from an upper and a lower piece along the waist (``simulate.garment.templates``, its last section)."""

_PROFILE: dict[str, tuple[float, float, float, str]] = {
    "taper": (0.0, CLOTH3D.limb_taper_max, 0.0, "share of the looseness lost at the longest cut [-]"),
    "widen_at": (CLOTH3D.widen_at_range[0], CLOTH3D.widen_at_range[1], 1.0, "where widening starts along the limb [-]"),
    "widen": (0.0, CLOTH3D.limb_widen_max_m, 0.0, "widening past widen_at [m per unit length]"),
}

#: type -> parameter -> (min, max, default, unit/description)
STYLE_SPECS: dict[str, dict[str, tuple[float, float, float, str]]] = {
    "tshirt": {
        "length": (0.0, 1.0, 0.8, "hem height fraction [-]"),
        "sleeve_length": (0.0, 1.0, 0.5, "sleeve length fraction [-]"),
        "looseness": (0.005, 0.05, 0.015, "outward offset [m]"),
        "width_profile": (0.0, 0.04, 0.01, "sleeve flare at the cuff [m]"),
    },
    "shirt": {
        "length": (0.0, 1.0, 0.9, "hem height fraction [-]"),
        "sleeve_length": (0.0, 1.0, 0.9, "sleeve length fraction [-]"),
        "looseness": (0.005, 0.05, 0.015, "outward offset [m]"),
        "width_profile": (0.0, 0.04, 0.005, "sleeve flare at the cuff [m]"),
    },
    "pants": {
        "leg_length": (0.0, 1.0, 0.9, "leg length fraction [-]"),
        "looseness": (0.005, 0.05, 0.012, "outward offset [m]"),
        "width_profile": (0.0, 0.06, 0.01, "leg flare at the hem [m]"),
    },
    "shorts": {
        "leg_length": (0.0, 1.0, 0.6, "leg length fraction [-]"),
        "looseness": (0.005, 0.05, 0.012, "outward offset [m]"),
        "width_profile": (0.0, 0.06, 0.015, "leg flare at the hem [m]"),
    },
    "skirt": {
        "length": (0.0, 1.0, 0.5, "hem height fraction [-]"),
        "looseness": (0.005, 0.05, 0.015, "offset from the hip/leg hull [m]"),
        "width_profile": (0.0, 0.25, 0.08, "flare at the hem [m]"),
    },
    "top": {
        "length": (0.0, 1.0, 0.8, "hem height fraction [-]"),
        "looseness": (0.005, 0.05, 0.015, "outward offset [m]"),
    },
    "dress": {
        "length": (0.0, 1.0, 0.5, "skirt hem height fraction [-]"),
        "looseness": (0.005, 0.05, 0.015, "outward offset [m]"),
        "flare": (0.0, CLOTH3D.skirt_flare_max_m, 0.08, "skirt flare at the longest hem [m]"),
    },
    "jumpsuit": {
        "leg_length": (0.0, 1.0, 0.9, "leg length fraction [-]"),
        "looseness": (0.005, 0.05, 0.012, "outward offset [m]"),
        **_PROFILE,
    },
}

#: type -> optional parameters (as STYLE_SPECS): accepted when given, absent from a style
#: otherwise (their defaults leave the garment unchanged).
OPTIONAL_STYLE_SPECS: dict[str, dict[str, tuple[float, float, float, str]]] = {
    t: dict(_PROFILE) for t in ("tshirt", "shirt", "pants", "shorts")}


def parameter_specs(garment_type: str) -> dict[str, tuple[float, float, float, str]]:
    """Every parameter a style of the type accepts: STYLE_SPECS then OPTIONAL_STYLE_SPECS."""
    return {**STYLE_SPECS[check_garment_type(garment_type)], **OPTIONAL_STYLE_SPECS.get(garment_type, {})}


def check_garment_type(garment_type: str, *, field_name: str = "garment_type") -> str:
    """Returns the type name; ValueError listing the allowed types otherwise."""
    if garment_type not in STYLE_SPECS:
        raise ValueError(f"{field_name} {garment_type!r} is not a known garment type; "
                         f"expected one of {', '.join(GARMENT_TYPES)}")
    return garment_type


def describe_styles(garment_type: str) -> str:
    """One line listing a type's style parameters with their ranges and defaults."""
    spec = STYLE_SPECS[check_garment_type(garment_type)]
    optional = OPTIONAL_STYLE_SPECS.get(garment_type, {})
    return ", ".join([f"{k} in [{lo:g}, {hi:g}] (default {d:g}, {desc})" for k, (lo, hi, d, desc) in spec.items()]
                     + [f"{k} in [{lo:g}, {hi:g}] (optional, {desc})" for k, (lo, hi, _, desc) in optional.items()])


@dataclass(frozen=True)
class StyleParams:
    """Validated style of one garment: ``values`` maps every parameter of the type to a
    float (missing ones take the defaults of :data:`STYLE_SPECS`); optional parameters
    (:data:`OPTIONAL_STYLE_SPECS`) are in ``values`` only when given."""

    garment_type: str
    values: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        spec = parameter_specs(self.garment_type)
        full = {k: v[2] for k, v in STYLE_SPECS[self.garment_type].items()}
        for name, value in dict(self.values).items():
            if name not in spec:
                raise ValueError(f"unknown style parameter {name!r} for garment type {self.garment_type!r}; "
                                 f"allowed: {describe_styles(self.garment_type)}")
            try:
                x = float(value)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"style parameter {name} must be a number, got {value!r}") from exc
            lo, hi = spec[name][0], spec[name][1]
            if not (lo <= x <= hi):
                raise ValueError(f"style parameter {name}={x:g} for {self.garment_type!r} is outside its range "
                                 f"[{lo:g}, {hi:g}]; allowed: {describe_styles(self.garment_type)}")
            full[name] = x
        object.__setattr__(self, "values", full)

    def __getitem__(self, name: str) -> float:
        return self.values[name]

    def get(self, name: str) -> float:
        """A parameter's value, or its default when it is an optional parameter not given."""
        return self.values[name] if name in self.values else parameter_specs(self.garment_type)[name][2]

    def uses_optional(self) -> bool:
        """Whether the style gives any of its type's optional parameters (the width profile)."""
        return any(k in self.values for k in OPTIONAL_STYLE_SPECS.get(self.garment_type, {}))

    def as_array(self, optional: bool = False) -> list[float]:
        """Values in :data:`STYLE_SPECS` order; with ``optional`` the type's optional parameters
        follow in :data:`OPTIONAL_STYLE_SPECS` order (their defaults where not given), so every
        style of a dataset whose styles use the width profile has a vector of one length. Types
        without optional parameters ignore it."""
        names = list(STYLE_SPECS[self.garment_type])
        if optional:
            names += list(OPTIONAL_STYLE_SPECS.get(self.garment_type, {}))
        return [self.get(k) for k in names]

    @classmethod
    def parse(cls, garment_type: str, text: str | None) -> "StyleParams":
        """Parses ``"length=0.6,looseness=0.02"`` (empty/None = defaults)."""
        values: dict[str, float] = {}
        for item in (text or "").replace(" ", "").split(","):
            if not item:
                continue
            name, sep, value = item.partition("=")
            if not sep:
                raise ValueError(f"style item {item!r} must be NAME=VALUE; allowed: {describe_styles(garment_type)}")
            try:
                values[name] = float(value)
            except ValueError as exc:
                raise ValueError(f"style parameter {name} must be a number, got {value!r}") from exc
        return cls(garment_type, values)


def sample_styles(garment_type: str, count: int, *, seed: int = 0, optional: bool = False) -> list[StyleParams]:
    """``count`` styles drawn uniformly within every parameter's range (seeded); with
    ``optional`` the type's optional parameters (the width profile) are drawn too."""
    import numpy as np

    spec = parameter_specs(garment_type) if optional else STYLE_SPECS[check_garment_type(garment_type)]
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        out.append(StyleParams(garment_type, {k: float(rng.uniform(lo, hi)) for k, (lo, hi, _, _) in spec.items()}))
    return out
