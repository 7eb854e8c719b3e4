"""Converged CPU float64 reference solver for the quasi-static equilibrium of the cloth model."""

from simulate.solvers.reference.solver_reference import ReferenceResult, solve_equilibrium, world_energy

__all__ = ["ReferenceResult", "solve_equilibrium", "world_energy"]
