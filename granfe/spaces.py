"""Function spaces of the micropolar continuum.

2D plane strain carries ``(u_x, u_y, phi_z)``, 3D carries ``(u, phi)``; both are a
``basix.ufl.mixed_element`` of a vector Lagrange element for u and a Lagrange element
for phi (scalar in 2D, 3-vector in 3D).
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before dolfinx/petsc4py)

import basix.ufl
from dolfinx import fem, mesh as _mesh

__all__ = ["micropolar_space", "sub_space", "COMPONENTS"]

# component name -> (field index, sub-component index or None)
COMPONENTS = {
    2: {"u": (0, None), "u_x": (0, 0), "u_y": (0, 1), "phi": (1, None), "phi_z": (1, None)},
    3: {
        "u": (0, None), "u_x": (0, 0), "u_y": (0, 1), "u_z": (0, 2),
        "phi": (1, None), "phi_x": (1, 0), "phi_y": (1, 1), "phi_z": (1, 2),
    },
}


def micropolar_space(domain: _mesh.Mesh, degree_u: int = 2, degree_phi: int = 1) -> fem.FunctionSpace:
    """Mixed space (u, phi) on a 2D or 3D mesh, Lagrange of the given degrees."""
    gdim = domain.geometry.dim
    tdim = domain.topology.dim
    if tdim not in (2, 3) or gdim != tdim:
        raise ValueError(
            f"micropolar_space needs a 2D mesh in the plane or a 3D mesh, got tdim={tdim}, gdim={gdim}"
        )
    for name, k in (("degree_u", degree_u), ("degree_phi", degree_phi)):
        if not (isinstance(k, int) and 1 <= k <= 4):
            raise ValueError(f"{name} must be an integer in [1, 4], got {k!r}")
    cell = domain.basix_cell()
    el_u = basix.ufl.element("Lagrange", cell, degree_u, shape=(gdim,))
    el_phi = basix.ufl.element("Lagrange", cell, degree_phi, shape=() if gdim == 2 else (3,))
    return fem.functionspace(domain, basix.ufl.mixed_element([el_u, el_phi]))


def sub_space(V: fem.FunctionSpace, component: str) -> fem.FunctionSpace:
    """The (non-collapsed) sub-space of ``V`` for a component name like ``"u_x"`` or ``"phi"``."""
    gdim = V.mesh.geometry.dim
    try:
        field, sub = COMPONENTS[gdim][component]
    except KeyError:
        raise ValueError(
            f"unknown component {component!r} for a {gdim}D micropolar space; "
            f"choose one of {sorted(COMPONENTS[gdim])}"
        ) from None
    W = V.sub(field)
    return W if sub is None else W.sub(sub)
