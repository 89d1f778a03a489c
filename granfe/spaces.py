"""Function spaces of a continuum model: one ``basix.ufl.mixed_element`` of its fields.

Even a one-field model gets a mixed element, so that field ``i`` is always ``V.sub(i)``
and ``ufl.split`` always returns one expression per field. Component names (``"u_x"``,
``"phi"``, ...) come from the model's :class:`~granfe.models.base.Field` declarations.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401  (orders MPI before dolfinx/petsc4py)

import basix.ufl
import ufl
from dolfinx import fem
from dolfinx import mesh as _mesh

__all__ = ["model_space", "components", "split", "sub_space", "micropolar_space", "COMPONENTS"]


def model_space(domain: _mesh.Mesh, fields, degrees) -> fem.FunctionSpace:
    """Mixed Lagrange space of ``fields`` (:class:`Field` tuple) at the given degrees."""
    gdim, tdim = domain.geometry.dim, domain.topology.dim
    if gdim != tdim:
        raise ValueError(f"a continuum needs a mesh of full dimension, got tdim={tdim}, gdim={gdim}")
    if len(degrees) != len(fields):
        raise ValueError(f"give one degree per field {[f.name for f in fields]}, got {degrees!r}")
    for f, k in zip(fields, degrees, strict=True):
        if not (isinstance(k, int) and 1 <= k <= 4):
            raise ValueError(f"degree of {f.name} must be an integer in [1, 4], got {k!r}")
    cell = domain.basix_cell()
    elements = [basix.ufl.element("Lagrange", cell, k, shape=f.shape)
                for f, k in zip(fields, degrees, strict=True)]
    return fem.functionspace(domain, basix.ufl.mixed_element(elements))


def components(fields) -> dict[str, tuple[int, int | None]]:
    """Component name -> (field index, sub-component index or None for the whole field)."""
    out = {}
    for i, f in enumerate(fields):
        out[f.name] = (i, None)
        for j, c in enumerate(f.components):
            out[c] = (i, None) if f.shape == () else (i, j)
    return out


def split(expr, fields) -> tuple:
    """One UFL expression per field of a mixed-space expression (a function, a test or trial
    function, or a linear combination of functions such as a generalized-alpha mid-point)."""
    if isinstance(expr, (fem.Function, ufl.Argument, ufl.Coefficient)):
        return ufl.split(expr)
    out, k = [], 0
    for f in fields:
        n = 1
        for s in f.shape:
            n *= s
        if f.shape == ():
            out.append(expr[k])
        else:
            out.append(ufl.as_vector([expr[k + i] for i in range(n)]))
        k += n
    return tuple(out)


def sub_space(V: fem.FunctionSpace, component: str, fields=None) -> fem.FunctionSpace:
    """The (non-collapsed) sub-space of ``V`` for a component name like ``"u_x"`` or ``"phi"``.
    Without ``fields`` the space is taken to be micropolar (the former signature)."""
    names = components(fields) if fields is not None else COMPONENTS[V.mesh.geometry.dim]
    try:
        field, sub = names[component]
    except KeyError:
        raise ValueError(f"unknown component {component!r}; choose one of {sorted(names)}") from None
    W = V.sub(field)
    return W if sub is None else W.sub(sub)


def _micropolar_fields(gdim):
    from granfe.models.micropolar import Micropolar

    return Micropolar.fields(gdim)


COMPONENTS = {gdim: components(_micropolar_fields(gdim)) for gdim in (2, 3)}


def micropolar_space(domain: _mesh.Mesh, degree_u: int = 2, degree_phi: int = 1) -> fem.FunctionSpace:
    """Mixed space (u, phi) on a 2D or 3D mesh, Lagrange of the given degrees."""
    return model_space(domain, _micropolar_fields(domain.geometry.dim), (degree_u, degree_phi))
