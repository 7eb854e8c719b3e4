"""Everything physical: bodies, garments, the cloth model, solvers and contact."""
import warp as _wp

# Warp prints a banner on first init; a CLI that prints JSON should stay clean.
_wp.config.log_level = _wp.LOG_WARNING
