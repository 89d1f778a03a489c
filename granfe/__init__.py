"""granfe: the micropolar / micromorphic continuum (DOLFINx). Knows nothing of particles."""

from granfe.materials import MicropolarMaterial, lame_from_engineering

__all__ = ["MicropolarMaterial", "lame_from_engineering"]

# The FE classes import dolfinx (heavy, and MPI-initialising), so they are imported
# from their modules: granfe.problem.MicropolarProblem, granfe.dynamics.GeneralizedAlpha,
# granfe.io.ContinuumWriter / render_png, granfe.rod1d.Rod1D.
