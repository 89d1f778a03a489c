"""dem: a numba discrete element engine (spheres and disks). Imports without dolfinx."""
