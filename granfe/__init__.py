"""granfe: the continuum (DOLFINx): continuum models as units (:mod:`granfe.models`), the
problem, dynamics, solvers and output over any model. Knows nothing of particles."""

# dolfinx_solver loads the MPI library dolfinx and petsc4py were built against; importing it
# here makes `import granfe` then `import dolfinx` work in any order.
import dolfinx_solver  # noqa: F401

from granfe.materials import MicropolarMaterial, lame_from_engineering

__all__ = ["MicropolarMaterial", "lame_from_engineering"]

# The FE classes import dolfinx (heavy, and MPI-initialising), so they are imported
# from their modules: granfe.problem.ContinuumProblem / MicropolarProblem,
# granfe.models (the model registry), granfe.dynamics.GeneralizedAlpha,
# granfe.io.ContinuumWriter / render_png, granfe.rod1d.Rod1D.
