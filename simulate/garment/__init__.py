"""Garments on the body: templates (t-shirt, shirt, pants, shorts, skirt) with the body
correspondence I, UV charts, CLOTH3D-like style parameters, canonical draping, the
TailorNet style PCA space, training shapes and prototypes."""
from simulate.garment.style import GARMENT_TYPES, STYLE_SPECS, StyleParams, sample_styles
from simulate.garment.templates import GarmentTemplate, apply_style, generate_garment, make_template

__all__ = ["GARMENT_TYPES", "STYLE_SPECS", "StyleParams", "generate_garment", "sample_styles", "GarmentTemplate",
           "make_template", "apply_style"]
