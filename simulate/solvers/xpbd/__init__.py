"""XPBD cloth solver."""

from simulate.solvers.xpbd.solver_xpbd import SolverXPBD

__all__ = ["SolverXPBD"]
