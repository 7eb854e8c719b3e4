"""VBD cloth solver (vertex block descent)."""

from simulate.solvers.vbd.solver_vbd import SolverVBD

__all__ = ["SolverVBD"]
