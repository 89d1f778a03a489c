"""Quadrature-point state of history-dependent models: trial, commit, restore.

A model that keeps variables between steps (plastic strain, damage, an accumulated strain)
declares them by name and value shape; each lives in a quadrature space of the problem's
quadrature degree. The residual reads the *committed* values and the model's closed-form
update (UFL) from them to the trial state, so repeated solves of one step (Newton, a
staggered coupling, a cut-back) never touch the committed values. :meth:`commit` evaluates
the trial state at the quadrature points and makes it the new committed state once a step
is accepted; :meth:`restore` throws a trial state away. Quadrature values are cell-local:
after an evaluation the ghost cells' values are refreshed from their owners
(``scatter_forward``), so every rank integrates the same numbers.

An elastic model has no variables: the state is empty, costs nothing and is never used.
"""

from __future__ import annotations

import dolfinx_solver  # noqa: F401

import basix.ufl
import numpy as np
import ufl
from dolfinx import fem

__all__ = ["QuadratureState"]


class QuadratureState:
    """Named quadrature functions of a model's history variables.

    Args:
        domain: the mesh.
        variables: name -> value shape (``()`` for a scalar).
        degree: quadrature degree (the residual must be integrated with :attr:`dx`).
    """

    def __init__(self, domain, variables: dict[str, tuple[int, ...]], degree: int):
        self.domain, self.degree = domain, int(degree)
        self.committed: dict[str, fem.Function] = {}
        self.trial: dict[str, fem.Function] = {}
        self._expression: fem.Expression | None = None
        cell = domain.basix_cell()
        for name, shape in variables.items():
            Q = fem.functionspace(domain, basix.ufl.quadrature_element(
                cell, value_shape=tuple(shape), degree=self.degree))
            self.committed[name] = fem.Function(Q, name=name)
            self.trial[name] = fem.Function(Q, name=f"{name}_trial")
        self.dx = ufl.Measure("dx", domain=domain, metadata={
            "quadrature_degree": self.degree, "quadrature_scheme": "default"})

    def __bool__(self) -> bool:
        return bool(self.committed)

    def bind(self, trial: dict, jit_options: dict | None = None) -> None:
        """The UFL expressions of the trial state (from the model's ``state_update``), all
        components in one expression: the variables share the return mapping, which one
        expression each computed again (4x the time for Drucker-Prager's four). A variable
        whose expression is None is written by the model itself (a return computed at the
        points, not in UFL: ``evaluate_points``)."""
        if set(trial) != set(self.committed):
            raise ValueError(f"state_update returns {sorted(trial)}, the model declares "
                             f"{sorted(self.committed)}")
        components = []
        self._evaluated = [name for name in self.trial if trial[name] is not None]
        for name in self._evaluated:             # the order evaluate() reads them back
            expr = trial[name]
            shape = ufl.shape(expr)
            components += [expr[i] for i in np.ndindex(shape)] if shape else [expr]
        if not components:                       # the model fills its state itself
            return
        points = next(iter(self.trial.values())).function_space.element.interpolation_points
        self._expression = fem.Expression(ufl.as_vector(components), points, jit_options=jit_options)

    def evaluate(self) -> None:
        """The trial state of the current fields, at every quadrature point of the owned
        cells, then the ghost cells' from their owners (collective)."""
        if self._expression is None:     # no variables (an elastic model), or the model's own
            return
        tdim = self.domain.topology.dim
        cells = np.arange(self.domain.topology.index_map(tdim).size_local, dtype=np.int32)
        values = self._expression.eval(self.domain, cells).reshape(len(cells), -1, self._expression.value_size)
        start = 0
        for f in (self.trial[name] for name in self._evaluated):
            bs = f.function_space.dofmap.index_map_bs
            dofs = f.function_space.dofmap.list[:len(cells)]        # (cells, points)
            f.x.array.reshape(-1, bs)[dofs.ravel()] = values[:, :, start:start + bs].reshape(-1, bs)
            f.x.scatter_forward()
            start += bs

    def commit(self) -> None:
        """Accept the current fields: the trial state becomes the committed state."""
        self.evaluate()
        for name, f in self.committed.items():
            f.x.array[:] = self.trial[name].x.array

    def restore(self) -> None:
        """Forget the trial state (the committed state was never touched)."""
        for name, f in self.committed.items():
            self.trial[name].x.array[:] = f.x.array

    def owned(self, name: str) -> np.ndarray:
        """The committed values of the cells this rank owns (flat copy)."""
        f = self.committed[name]
        imap, bs = f.function_space.dofmap.index_map, f.function_space.dofmap.index_map_bs
        return f.x.array[:imap.size_local * bs].copy()

    def state_dict(self) -> dict[str, np.ndarray]:
        return {name: self.owned(name) for name in self.committed}

    def load_state(self, values: dict[str, np.ndarray]) -> None:
        """Restore committed values written by :meth:`state_dict` on the same partition."""
        for name, f in self.committed.items():
            if name not in values:
                raise KeyError(f"the saved state has no quadrature variable {name!r}")
            data = np.asarray(values[name])
            n = len(self.owned(name))
            if data.shape != (n,):
                raise ValueError(f"quadrature variable {name!r}: saved {data.shape}, this "
                                 f"partition holds ({n},) (another mesh or rank count?)")
            f.x.array[:n] = data
            f.x.scatter_forward()
            self.trial[name].x.array[:] = f.x.array
