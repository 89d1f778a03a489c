"""dem: a numba discrete element engine (spheres and disks). Imports without dolfinx.

Public API: `Particles` (FREE, GHOST, FIXED kinds), `ContactMaterial`, `PlaneWall`,
`box_walls`, `Simulation`, `relax` and `ServoWall`, `PeriodicCell`, `RigidBody`,
`DistributedSimulation` (MPI domain decomposition), `Prescribed` motions of GHOST particles
inside `Simulation.step` (`Interpolated`, `Translated`), the critical time step helpers and
the named errors. `Simulation.state_dict` / `load_state` hold a run's exact state.
"""

from dem import threads  # noqa: F401  (the threading layer, before any kernel launches)
from dem.contact import LAWS, ContactMaterial
from dem.control import ServoWall, relax, unbalanced_force_ratio
from dem.errors import BlowUpError, DemError, DomainError, MaterialError, OverlapError, TimeStepError
from dem.integrate import Simulation
from dem.neighbours import NeighbourList, build_pairs
from dem.parallel import DistributedSimulation
from dem.periodic import PeriodicCell, cell_stress
from dem.prescribed import Interpolated, Prescribed, Translated
from dem.rigid import RigidBody, read_surface, sample_surface
from dem.state import FIXED, FREE, GHOST, Particles
from dem.timestep import critical_dt, default_time_step, hertz_dt, rayleigh_dt
from dem.walls import PlaneWall, WallSet, box_walls

__all__ = ["DistributedSimulation", "Interpolated", "Prescribed", "Translated", "PeriodicCell", "cell_stress",
           "RigidBody", "read_surface", "sample_surface", "ServoWall", "relax", "unbalanced_force_ratio", "FIXED",
           "FREE", "GHOST", "LAWS", "BlowUpError", "ContactMaterial", "DemError",
           "DomainError", "MaterialError", "NeighbourList", "OverlapError", "Particles",
           "PlaneWall", "Simulation", "TimeStepError", "WallSet", "box_walls", "build_pairs",
           "critical_dt", "default_time_step", "hertz_dt", "rayleigh_dt"]
