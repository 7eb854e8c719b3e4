"""Cloth solvers on a shared ClothModel: VBD (vertex block descent), XPBD (Gauss-Seidel or Jacobi) and mass-spring."""

from __future__ import annotations

from typing import Any

from simulate.cloth.model import ClothModel

__all__ = ["SolverVBD", "SolverXPBD", "SolverMassSpring", "make_solver", "SOLVERS"]

SOLVERS = ("vbd", "xpbd", "mass_spring")


def make_solver(name: str, model: ClothModel, **options: Any):
    """Create a solver by name ("vbd", "xpbd" or "mass_spring") with keyword options of its class."""
    if name == "vbd":
        from simulate.solvers.vbd import SolverVBD

        return SolverVBD(model, **options)
    if name == "xpbd":
        from simulate.solvers.xpbd import SolverXPBD

        return SolverXPBD(model, **options)
    if name == "mass_spring":
        from simulate.solvers.mass_spring import SolverMassSpring

        return SolverMassSpring(model, **options)
    raise ValueError(f"solver must be one of {SOLVERS} (got {name!r})")


def __getattr__(name: str) -> Any:
    # Lazy, so importing the package does not import every solver's kernels.
    if name == "SolverVBD":
        from simulate.solvers.vbd import SolverVBD

        return SolverVBD
    if name == "SolverXPBD":
        from simulate.solvers.xpbd import SolverXPBD

        return SolverXPBD
    if name == "SolverMassSpring":
        from simulate.solvers.mass_spring import SolverMassSpring

        return SolverMassSpring
    raise AttributeError(name)
