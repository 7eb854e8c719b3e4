"""Cloth model: fabrics, builder (garments -> packed worlds), state, control, quasi-static driver."""

from simulate.cloth.builder import ClothBuilder
from simulate.cloth.fabric import FABRICS, Fabric
from simulate.cloth.model import ClothControl, ClothModel, ClothState, Features

__all__ = ["Fabric", "FABRICS", "ClothBuilder", "ClothModel", "ClothState", "ClothControl", "Features"]
