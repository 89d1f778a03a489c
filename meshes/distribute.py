"""Mesh a gmsh model on rank 0 and distribute it (the one place that does)."""

from __future__ import annotations

import dolfinx_solver  # noqa: F401
from mpi4py import MPI

import gmsh

__all__ = ["on_rank0"]


def on_rank0(comm: MPI.Comm, name: str, add, gdim: int):
    """Run ``add(gmsh.model)`` on rank 0 (a pure function that builds and meshes the model),
    then distribute: returns ``dolfinx.io.gmsh.MeshData``. An error in ``add`` is raised on
    every rank, so none is left waiting in the distribution."""
    from dolfinx.io import gmsh as gmshio

    initialized = gmsh.isInitialized()
    if not initialized:
        gmsh.initialize()
    gmsh.option.setNumber("General.Terminal", 0)
    error = None
    try:
        if comm.rank == 0:
            gmsh.model.add(name)
            try:
                add(gmsh.model)
            except Exception as err:  # tell every rank, do not leave them waiting
                error = err
        error = comm.bcast(error, root=0)
        if error is not None:
            raise error
        data = gmshio.model_to_mesh(gmsh.model, comm, 0, gdim=gdim)
    finally:
        if comm.rank == 0 and gmsh.model.list():
            gmsh.model.remove()
        if not initialized:
            gmsh.finalize()
    return data
