"""Semi-implicit Euler mass-spring cloth solver."""

from simulate.solvers.mass_spring.solver_mass_spring import SolverMassSpring

__all__ = ["SolverMassSpring"]
