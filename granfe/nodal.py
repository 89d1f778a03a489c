"""Loads given node by node: the external virtual work ``sum_i F_i dw_i`` of nodal forces F.

A partitioned coupling hands the continuum forces that live at points (the reactions of
particles whose motion the FE prescribes): their work on the FE test functions is ``N^T f``,
a vector in the dof layout, not a density. UFL has no point measure, so the vector is carried
by a function ``g`` integrated with the vertex rule: for a degree-1 Lagrange field
``int g . dw dx_vertex = sum_i m_i g_i dw_i`` with ``m_i`` the lumped (vertex-rule) volume of
node i, so ``g_i = F_i / m_i`` makes the form assemble to F exactly, and the load enters every
solver (SNES, the affine dynamic step) as any other form does.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401

import dolfinx.la
import numpy as np
import ufl
from dolfinx import default_scalar_type, fem

__all__ = ["NodalLoad"]


class NodalLoad:
    """Nodal forces on one degree-1 field of a mixed space ``V``.

    Args:
        V: the (mixed) space of the problem.
        fields: the model's field descriptors (name, shape) in V's order.
        field: the loaded field's name (``"u"``: forces, ``"phi"``: couples).
        degree: that field's Lagrange degree (1 required: the vertex rule is exact for it).
    """

    def __init__(self, V: fem.FunctionSpace, fields, field: str, degree: int):
        names = [f.name for f in fields]
        if field not in names:
            raise ValueError(f"nodal load on field {field!r}: the model's fields are {names}")
        if degree != 1:
            raise ValueError(f"nodal load on field {field!r}: degree-1 Lagrange only (the vertex "
                             f"rule is exact for it), the field has degree {degree}")
        self.index = names.index(field)
        self.shape = fields[self.index].shape
        self.g = fem.Function(V, name=f"nodal_{field}")
        domain = V.mesh
        self.dx = ufl.Measure("dx", domain=domain,
                              metadata={"quadrature_rule": "vertex", "quadrature_degree": 1})
        ones = fem.Constant(domain, np.ones(self.shape, dtype=default_scalar_type))
        dw = ufl.split(ufl.TestFunction(V))[self.index]
        lumped = fem.assemble_vector(fem.form(ufl.inner(ones, dw) * self.dx))
        lumped.scatter_reverse(dolfinx.la.InsertMode.add)
        lumped.scatter_forward()
        m = lumped.array
        self.dofs = np.flatnonzero(m > 0)     # this field's dofs (owned and ghost)
        self.m = m[self.dofs].copy()

    def work(self, dw: tuple):
        """The external virtual work form for the problem's split test functions ``dw``."""
        g = ufl.split(self.g)[self.index]
        return ufl.inner(g, dw[self.index]) * self.dx

    def set(self, F: np.ndarray) -> None:
        """Nodal forces ``F`` in V's local dof layout (owned and ghost entries, assembled:
        e.g. ``N^T f`` scattered forward); entries of other fields are ignored."""
        F = np.asarray(F, dtype=float)
        if F.shape != self.g.x.array.shape:
            raise ValueError(f"nodal forces must have V's local size {self.g.x.array.size}, got {F.shape}")
        if not np.all(np.isfinite(F[self.dofs])):
            raise ValueError("nodal forces are not finite")
        self.g.x.array[:] = 0.0
        self.g.x.array[self.dofs] = F[self.dofs] / self.m

    def values(self) -> np.ndarray:
        """The nodal forces now held (V's local layout, zero off the field)."""
        out = np.zeros_like(self.g.x.array)
        out[self.dofs] = self.g.x.array[self.dofs] * self.m
        return out
